// Backward pass of the compositing (the CPU reference's `backward`, first
// half): per pixel, from its last contributor to its first, the gradients of
// the loss with respect to each Gaussian's 2D mean, conic, view opacity and
// view colour. Transmittance is recovered going backwards by dividing by
// (1 - alpha), as gsplat does. One workgroup per tile; for each Gaussian the
// pixels' contributions are summed across the subgroup first, so only one
// lane per subgroup adds them to the global sums (float adds by
// compare-and-swap, which every device supports).


@group(0) @binding(0) var<uniform> params: RasterParams;
@group(0) @binding(1) var<storage, read> projected: array<f32>;
@group(0) @binding(2) var<storage, read> sorted_index: array<u32>;
@group(0) @binding(3) var<storage, read> ranges: array<u32>;
@group(0) @binding(4) var<storage, read> image: array<f32>;
@group(0) @binding(5) var<storage, read> last_contributor: array<u32>;
// 4 per pixel: dL/dr, dL/dg, dL/db, dL/dalpha.
@group(0) @binding(6) var<storage, read> d_image: array<f32>;
// GRADS2D_FLOATS (12) per Gaussian: mean2d x, y; conic a, b, c; view opacity;
// view colour r, g, b; visibility (written by the projection backward); the
// per-pixel mean2d gradients summed in absolute value, x, y (AbsGS).
@group(0) @binding(7) var<storage, read_write> grads: array<atomic<u32>>;
// x: 1 to sum the absolute mean2d gradients (AbsGS), 0 to spare the work.
@group(0) @binding(8) var<uniform> options: vec4<u32>;


var<workgroup> tile_range: vec2<u32>;
var<workgroup> furthest: atomic<u32>;
var<workgroup> furthest_plain: u32;
var<workgroup> batch_id: array<u32, 256>;
var<workgroup> batch_mean: array<vec2<f32>, 256>;
var<workgroup> batch_conic: array<vec3<f32>, 256>;
var<workgroup> batch_opacity: array<f32, 256>;
var<workgroup> batch_colour: array<vec3<f32>, 256>;

fn add_float(i: u32, v: f32) {
    var old = atomicLoad(&grads[i]);
    loop {
        let swapped = atomicCompareExchangeWeak(&grads[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (swapped.exchanged) {
            break;
        }
        old = swapped.old_value;
    }
}

// One-dimensional workgroup: subgroup builtins need one.
@compute @workgroup_size(256)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
    @builtin(subgroup_invocation_id) lane: u32,
) {
    let tile = wid.x + wid.y * params.tiles_x;
    let px = wid.x * 16u + lid % 16u;
    let py = wid.y * 16u + lid / 16u;
    let inside = px < params.width && py < params.height;
    let pixel = py * params.width + px;
    if (lid == 0u) {
        tile_range = vec2<u32>(ranges[2u * tile], ranges[2u * tile + 1u]);
        atomicStore(&furthest, 0u);
    }
    workgroupBarrier();
    var last = 0u;
    var t_final = 1.0;
    var dc = vec3<f32>(0.0);
    var da = 0.0;
    if (inside) {
        last = last_contributor[pixel];
        t_final = 1.0 - image[PIXEL_FLOATS * pixel + 3u];
        dc = vec3<f32>(d_image[4u * pixel], d_image[4u * pixel + 1u], d_image[4u * pixel + 2u]);
        da = d_image[4u * pixel + 3u];
        atomicMax(&furthest, last);
    }
    workgroupBarrier();
    if (lid == 0u) {
        furthest_plain = atomicLoad(&furthest);
    }
    let range = workgroupUniformLoad(&tile_range);
    let end = max(workgroupUniformLoad(&furthest_plain), range.x);
    var transmittance = t_final;
    var behind = params.background.xyz * t_final;
    let fx = f32(px) + 0.5;
    let fy = f32(py) + 0.5;
    // Batches from the back: [batch_start, batch_end).
    var batch_end = end;
    while (batch_end > range.x) {
        let batch_start = max(range.x, select(0u, batch_end - 256u, batch_end >= 256u));
        let size = batch_end - batch_start;
        if (lid < size) {
            // Slot 0 is the last entry of the batch, so iteration runs back to front.
            let k = batch_end - 1u - lid;
            let g = sorted_index[k];
            let o = 12u * g;
            batch_id[lid] = g;
            batch_mean[lid] = vec2<f32>(projected[o], projected[o + 1u]);
            batch_conic[lid] = vec3<f32>(projected[o + 2u], projected[o + 3u], projected[o + 4u]);
            batch_opacity[lid] = projected[o + 5u];
            batch_colour[lid] = vec3<f32>(projected[o + 6u], projected[o + 7u], projected[o + 8u]);
        }
        workgroupBarrier();
        for (var j = 0u; j < size; j++) {
            let k = batch_end - 1u - j;
            var d_mean = vec2<f32>(0.0);
            var d_conic = vec3<f32>(0.0);
            var d_opacity = 0.0;
            var d_colour = vec3<f32>(0.0);
            var contributes = false;
            if (inside && k < last) {
                let mean = batch_mean[j];
                let conic = batch_conic[j];
                let dx = mean.x - fx;
                let dy = mean.y - fy;
                let sigma = 0.5 * (conic.x * dx * dx + conic.z * dy * dy) + conic.y * dx * dy;
                if (sigma >= 0.0 && sigma <= SIGMA_SKIP) {
                    let vis = exp(-sigma);
                    let raw = batch_opacity[j] * vis;
                    let alpha = min(raw, ALPHA_MAX);
                    if (alpha >= ALPHA_MIN) {
                        contributes = true;
                        let one_minus = 1.0 - alpha;
                        let t_i = transmittance / one_minus;
                        let c = batch_colour[j];
                        let w = alpha * t_i;
                        d_colour = w * dc;
                        var d_alpha = da * t_final / one_minus;
                        d_alpha += dot(dc, c * t_i - behind / one_minus);
                        behind += c * w;
                        transmittance = t_i;
                        if (raw <= ALPHA_MAX) {
                            d_opacity = d_alpha * vis;
                            let d_sigma = -d_alpha * alpha;
                            d_conic = vec3<f32>(d_sigma * 0.5 * dx * dx, d_sigma * dx * dy, d_sigma * 0.5 * dy * dy);
                            d_mean = vec2<f32>(d_sigma * (conic.x * dx + conic.y * dy), d_sigma * (conic.y * dx + conic.z * dy));
                        }
                    }
                }
            }
            let any_contribution = subgroupAny(contributes);
            if (any_contribution) {
                let s_mean = subgroupAdd(d_mean);
                let s_conic = subgroupAdd(d_conic);
                let s_opacity = subgroupAdd(d_opacity);
                let s_colour = subgroupAdd(d_colour);
                // `options` is uniform, so every lane takes the same branch.
                var s_mean_abs = vec2<f32>(0.0);
                if (options.x == 1u) {
                    s_mean_abs = subgroupAdd(abs(d_mean));
                }
                if (lane == 0u) {
                    let base = GRADS2D_FLOATS * batch_id[j];
                    add_float(base, s_mean.x);
                    add_float(base + 1u, s_mean.y);
                    add_float(base + 2u, s_conic.x);
                    add_float(base + 3u, s_conic.y);
                    add_float(base + 4u, s_conic.z);
                    add_float(base + 5u, s_opacity);
                    add_float(base + 6u, s_colour.x);
                    add_float(base + 7u, s_colour.y);
                    add_float(base + 8u, s_colour.z);
                    if (options.x == 1u) {
                        add_float(base + 10u, s_mean_abs.x);
                        add_float(base + 11u, s_mean_abs.y);
                    }
                }
            }
        }
        workgroupBarrier();
        batch_end = batch_start;
    }
}
