// Tile intersections in (tile, depth, index) order, as Brush orders them:
// the Gaussians are sorted by depth first (a stable least-significant-digit
// radix sort, 4 bits per pass), their intersections emitted in that order,
// then sorted stably by tile; finally each tile's range is found. Sorting
// Gaussians by depth rather than intersections does the 8 depth passes over
// N elements instead of over the several times larger intersection count.

struct Params {
    len: u32,       // intersections
    shift: u32,     // digit position of this radix pass
    blocks: u32,    // 256-element blocks
    gaussians: u32,
    tiles_x: u32,
    tiles: u32,
}

@group(0) @binding(0) var<uniform> params: Params;

// ---- depth keys: one thread per Gaussian ------------------------------------
@group(0) @binding(1) var<storage, read> projected: array<f32>;
@group(0) @binding(2) var<storage, read> rects: array<u32>;
@group(0) @binding(30) var<storage, read> tile_counts: array<u32>;
@group(0) @binding(31) var<storage, read_write> key_tile: array<u32>;
@group(0) @binding(32) var<storage, read_write> key_depth: array<u32>;
@group(0) @binding(33) var<storage, read_write> key_index: array<u32>;


@compute @workgroup_size(256)
fn depth_keys(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let g = flat_index(gid, groups);
    if (g >= params.gaussians) {
        return;
    }
    // Depths of drawn Gaussians are positive (beyond the near plane), so
    // their bits sort as numbers; the undrawn go last.
    key_depth[g] = select(0xffffffffu, bitcast<u32>(projected[12u * g + 9u]), tile_counts[g] > 0u);
    key_tile[g] = 0u;
    key_index[g] = g;
}

// ---- counts in depth order (one extra 0 so the scan ends in the total) ------
@group(0) @binding(34) var<storage, read> depth_order: array<u32>;
@group(0) @binding(35) var<storage, read_write> ordered_counts: array<u32>;

@compute @workgroup_size(256)
fn gather_counts(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = flat_index(gid, groups);
    if (i < params.gaussians) {
        ordered_counts[i] = tile_counts[depth_order[i]];
    } else if (i == params.gaussians) {
        ordered_counts[i] = 0u;
    }
}

// ---- emit: one thread per Gaussian, in depth order ---------------------------
@group(0) @binding(3) var<storage, read> ordered_offsets: array<u32>;
@group(0) @binding(4) var<storage, read_write> emit_tile: array<u32>;
@group(0) @binding(5) var<storage, read_write> emit_depth: array<u32>;
@group(0) @binding(6) var<storage, read_write> emit_index: array<u32>;

@compute @workgroup_size(256)
fn emit(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = flat_index(gid, groups);
    if (i >= params.gaussians) {
        return;
    }
    let g = depth_order[i];
    let x0 = rects[4u * g];
    let x1 = rects[4u * g + 1u];
    let y0 = rects[4u * g + 2u];
    let y1 = rects[4u * g + 3u];
    var k = ordered_offsets[i];
    for (var y = y0; y < y1; y++) {
        for (var x = x0; x < x1; x++) {
            emit_tile[k] = y * params.tiles_x + x;
            emit_depth[k] = 0u;
            emit_index[k] = g;
            k++;
        }
    }
}

// ---- radix passes: 256 elements per workgroup -------------------------------
// The key is the depth, or the tile when `shift` >= 32 (its digit at shift - 32).
@group(0) @binding(10) var<storage, read> in_tile: array<u32>;
@group(0) @binding(11) var<storage, read> in_depth: array<u32>;
@group(0) @binding(12) var<storage, read> in_index: array<u32>;
@group(0) @binding(13) var<storage, read_write> histogram: array<u32>;
@group(0) @binding(14) var<storage, read_write> out_tile: array<u32>;
@group(0) @binding(15) var<storage, read_write> out_depth: array<u32>;
@group(0) @binding(16) var<storage, read_write> out_index: array<u32>;

var<workgroup> counts: array<atomic<u32>, 16>;
var<workgroup> digits: array<u32, 256>;

fn digit_of(k: u32) -> u32 {
    if (params.shift >= 32u) {
        return (in_tile[k] >> (params.shift - 32u)) & 15u;
    }
    return (in_depth[k] >> params.shift) & 15u;
}

// histogram[digit * blocks + block] = elements of the block with that digit.
@compute @workgroup_size(256)
fn radix_histogram(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = workgroup_index(wid, groups);
    if (lid < 16u) {
        atomicStore(&counts[lid], 0u);
    }
    workgroupBarrier();
    let k = block * 256u + lid;
    if (k < params.len) {
        atomicAdd(&counts[digit_of(k)], 1u);
    }
    workgroupBarrier();
    if (lid < 16u && block < params.blocks) {
        histogram[lid * params.blocks + block] = atomicLoad(&counts[lid]);
    }
}

// After the histogram's exclusive scan: each element goes to its digit's
// offset for its block plus the number of earlier elements of the block
// with the same digit (which keeps the sort stable).
@compute @workgroup_size(256)
fn radix_scatter(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let block = workgroup_index(wid, groups);
    let k = block * 256u + lid;
    let inside = k < params.len;
    var d = 16u;
    if (inside) {
        d = digit_of(k);
    }
    digits[lid] = d;
    workgroupBarrier();
    if (!inside) {
        return;
    }
    var rank = 0u;
    for (var j = 0u; j < lid; j++) {
        rank += select(0u, 1u, digits[j] == d);
    }
    let dest = histogram[d * params.blocks + block] + rank;
    out_tile[dest] = in_tile[k];
    out_depth[dest] = in_depth[k];
    out_index[dest] = in_index[k];
}

// ---- tile ranges: ranges[2t], ranges[2t+1] = first and one past last -------
@group(0) @binding(20) var<storage, read> sorted_tile: array<u32>;
@group(0) @binding(21) var<storage, read_write> ranges: array<u32>;

@compute @workgroup_size(256)
fn tile_ranges(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let k = flat_index(gid, groups);
    if (k >= params.len) {
        return;
    }
    let t = sorted_tile[k];
    if (k == 0u || sorted_tile[k - 1u] != t) {
        ranges[2u * t] = k;
    }
    if (k + 1u == params.len || sorted_tile[k + 1u] != t) {
        ranges[2u * t + 1u] = k + 1u;
    }
}
