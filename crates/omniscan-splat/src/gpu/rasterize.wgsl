// Front-to-back compositing, one workgroup per 16x16 tile and one thread per
// pixel, with the CPU reference's limits (alpha <= 0.999, skip below 1/255
// or past σ = 5.55, stop before transmittance falls to 1e-4). The tile's
// Gaussians are staged through workgroup memory 256 at a time.


@group(0) @binding(0) var<uniform> params: RasterParams;
@group(0) @binding(1) var<storage, read> projected: array<f32>;
@group(0) @binding(2) var<storage, read> sorted_index: array<u32>;
@group(0) @binding(3) var<storage, read> ranges: array<u32>;
// PIXEL_FLOATS per pixel: r, g, b, alpha, depth sum, contributors, median depth.
@group(0) @binding(4) var<storage, read_write> image: array<f32>;
// Per pixel: one past the position (in the sorted list) of its last
// contributor, where the backward pass starts.
@group(0) @binding(5) var<storage, read_write> last_contributor: array<u32>;


var<workgroup> tile_range: vec2<u32>;
var<workgroup> batch_mean: array<vec2<f32>, 256>;
var<workgroup> batch_conic: array<vec3<f32>, 256>;
var<workgroup> batch_opacity: array<f32, 256>;
var<workgroup> batch_colour: array<vec3<f32>, 256>;
var<workgroup> batch_depth: array<f32, 256>;

@compute @workgroup_size(16, 16)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) local: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let tile = wid.x + wid.y * params.tiles_x;
    if (lid == 0u) {
        tile_range = vec2<u32>(ranges[2u * tile], ranges[2u * tile + 1u]);
    }
    let range = workgroupUniformLoad(&tile_range);
    let px = wid.x * 16u + local.x;
    let py = wid.y * 16u + local.y;
    let inside = px < params.width && py < params.height;
    let fx = f32(px) + 0.5;
    let fy = f32(py) + 0.5;
    var transmittance = 1.0;
    var colour = vec3<f32>(0.0);
    var depth = 0.0;
    var median = 0.0;
    var count = 0u;
    var last = range.x;
    var done = !inside;
    for (var start = range.x; start < range.y; start += 256u) {
        let k = start + lid;
        if (k < range.y) {
            let g = sorted_index[k];
            let o = 12u * g;
            batch_mean[lid] = vec2<f32>(projected[o], projected[o + 1u]);
            batch_conic[lid] = vec3<f32>(projected[o + 2u], projected[o + 3u], projected[o + 4u]);
            batch_opacity[lid] = projected[o + 5u];
            batch_colour[lid] = vec3<f32>(projected[o + 6u], projected[o + 7u], projected[o + 8u]);
            batch_depth[lid] = projected[o + 9u];
        }
        workgroupBarrier();
        let size = min(256u, range.y - start);
        for (var j = 0u; j < size && !done; j++) {
            let dx = batch_mean[j].x - fx;
            let dy = batch_mean[j].y - fy;
            let conic = batch_conic[j];
            let sigma = 0.5 * (conic.x * dx * dx + conic.z * dy * dy) + conic.y * dx * dy;
            if (sigma < 0.0 || sigma > SIGMA_SKIP) {
                continue;
            }
            let alpha = min(batch_opacity[j] * exp(-sigma), ALPHA_MAX);
            if (alpha < ALPHA_MIN) {
                continue;
            }
            let next = transmittance * (1.0 - alpha);
            if (next <= T_STOP) {
                done = true;
                break;
            }
            let w = alpha * transmittance;
            colour += batch_colour[j] * w;
            depth += batch_depth[j] * w;
            if (transmittance > 0.5 && next <= 0.5) {
                median = batch_depth[j];
            }
            transmittance = next;
            count++;
            last = start + j + 1u;
        }
        workgroupBarrier();
    }
    if (inside) {
        let o = PIXEL_FLOATS * (py * params.width + px);
        let rgb = colour + transmittance * params.background.xyz;
        image[o] = rgb.x;
        image[o + 1u] = rgb.y;
        image[o + 2u] = rgb.z;
        image[o + 3u] = 1.0 - transmittance;
        image[o + 4u] = depth;
        image[o + 5u] = f32(count);
        image[o + 6u] = median;
        last_contributor[py * params.width + px] = last;
    }
}
