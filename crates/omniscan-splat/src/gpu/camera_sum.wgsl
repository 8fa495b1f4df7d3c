// Sums the Gaussians' shares of the camera gradient (6 floats each, written
// by project_backward.wgsl) over each workgroup of 256: one partial sum of 6
// per workgroup, which the host adds up in f64.

@group(0) @binding(0) var<uniform> count: vec4<u32>;
@group(0) @binding(1) var<storage, read> d_camera: array<f32>;
@group(0) @binding(2) var<storage, read_write> partials: array<f32>;

var<workgroup> shares: array<f32, 1536>;

@compute @workgroup_size(256)
fn main(
    @builtin(local_invocation_index) lid: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
) {
    let w = workgroup_index(wid, groups);
    let g = 256u * w + lid;
    for (var c = 0u; c < 6u; c++) {
        shares[6u * lid + c] = select(0.0, d_camera[6u * g + c], g < count.x);
    }
    workgroupBarrier();
    for (var span = 128u; span > 0u; span = span / 2u) {
        if (lid < span) {
            for (var c = 0u; c < 6u; c++) {
                shares[6u * lid + c] += shares[6u * (lid + span) + c];
            }
        }
        workgroupBarrier();
    }
    if (lid == 0u) {
        for (var c = 0u; c < 6u; c++) {
            partials[6u * w + c] = shares[c];
        }
    }
}
