// Exclusive prefix sum of u32 values, in place, 1024 per workgroup (4 per
// thread); `scan_blocks` leaves each block's total in `block_sums`, which is
// scanned the same way (recursively, by the host) and added back by
// `add_block_offsets`.

struct Params {
    len: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read_write> data: array<u32>;
@group(0) @binding(2) var<storage, read_write> block_sums: array<u32>;

var<workgroup> partial: array<u32, 256>;

@compute @workgroup_size(256)
fn scan_blocks(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = workgroup_index(wid, groups);
    let base = block * 1024u + lid * 4u;
    var v: array<u32, 4>;
    var sum = 0u;
    for (var i = 0u; i < 4u; i++) {
        let k = base + i;
        v[i] = select(0u, data[k], k < params.len);
        sum += v[i];
    }
    partial[lid] = sum;
    workgroupBarrier();
    // Hillis-Steele inclusive scan of the thread sums.
    for (var offset = 1u; offset < 256u; offset = offset * 2u) {
        var add = 0u;
        if (lid >= offset) {
            add = partial[lid - offset];
        }
        workgroupBarrier();
        partial[lid] += add;
        workgroupBarrier();
    }
    var running = partial[lid] - sum;
    for (var i = 0u; i < 4u; i++) {
        let k = base + i;
        if (k < params.len) {
            data[k] = running;
        }
        running += v[i];
    }
    if (lid == 255u) {
        block_sums[block] = partial[255];
    }
}

@compute @workgroup_size(256)
fn add_block_offsets(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = workgroup_index(wid, groups);
    let add = block_sums[block];
    let base = block * 1024u + lid * 4u;
    for (var i = 0u; i < 4u; i++) {
        let k = base + i;
        if (k < params.len) {
            data[k] += add;
        }
    }
}
