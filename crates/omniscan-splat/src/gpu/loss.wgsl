// The training loss on the device (the CPU trainer's `step_loss`, in f32):
// (1 − λ)·L1 + λ·(1 − SSIM) on colour against the photo with its non-object
// pixels replaced by the step's background, plus λ_o·L1 between the rendered
// alpha and the object mask, every term weighted by 1 − gripper mask and
// normalised by the remaining weight. SSIM is 3DGS's (11x11 Gaussian window,
// σ 1.5, zero padding); its gradient is assembled from blurred terms as on
// the CPU. Stages: `prepare` (targets, the 15 planes to blur), `blur`
// (separable, one direction per dispatch, any number of planes),
// `ssim_terms` (SSIM and its three blurred-gradient terms per channel),
// `gradient` (dL/d colour and dL/d alpha into the backward pass's buffer).
// Sums for the reported loss and PSNR are accumulated with float atomics.

struct Params {
    width: u32,
    height: u32,
    planes: u32,
    horizontal: u32,
    background: vec4<f32>,
    lambda_ssim: f32,
    lambda_opacity: f32,
    weight_sum: f32,
    _pad: f32,
    // The CPU's f32 SSIM window, taps 0..10 (see `blur`).
    window: array<vec4<f32>, 3>,
}

@group(0) @binding(0) var<uniform> params: Params;


// Sums: 0 Σw|Δc|, 1 Σw|Δα|, 2 Σ w·SSIM (all channels), 3 Σ squared error
// outside the gripper, 4 pixels outside the gripper.
@group(0) @binding(1) var<storage, read_write> sums: array<atomic<u32>>;

fn add_float(i: u32, v: f32) {
    var old = atomicLoad(&sums[i]);
    loop {
        let swapped = atomicCompareExchangeWeak(&sums[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (swapped.exchanged) {
            break;
        }
        old = swapped.old_value;
    }
}

// ---- prepare -----------------------------------------------------------------
// PIXEL_FLOATS per pixel from the forward pass: r, g, b, alpha, depth, count, median depth.
@group(0) @binding(2) var<storage, read> image: array<f32>;
// 5 floats per pixel: photo r, g, b; object mask; gripper mask.
@group(0) @binding(3) var<storage, read> target_data: array<f32>;
// 15 planes: per channel c, x, y, x², y², xy at planes 5c..5c+4.
@group(0) @binding(4) var<storage, read_write> planes: array<f32>;

var<workgroup> partial: array<vec4<f32>, 256>;

// The loss weight of pixel `i` (0 on the gripper).
fn weight_of(i: u32) -> f32 {
    return 1.0 - target_data[5u * i + 4u];
}

// Channel `c` of the target at pixel `i`: the photo on the object, the
// step's background elsewhere.
fn target_colour(i: u32, c: u32) -> f32 {
    let m = target_data[5u * i + 3u];
    return target_data[5u * i + c] * m + params.background[c] * (1.0 - m);
}

// Sums `partial` over the workgroup (call from uniform control flow).
fn workgroup_sum(lid: u32) -> vec4<f32> {
    workgroupBarrier();
    for (var stride = 128u; stride > 0u; stride = stride / 2u) {
        if (lid < stride) {
            partial[lid] += partial[lid + stride];
        }
        workgroupBarrier();
    }
    return partial[0];
}

@compute @workgroup_size(256)
fn prepare(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = flat_index(gid, groups);
    let n = params.width * params.height;
    var mine = vec4<f32>(0.0);
    if (i < n) {
        let m = target_data[5u * i + 3u];
        let weight = weight_of(i);
        for (var c = 0u; c < 3u; c++) {
            let x = image[PIXEL_FLOATS * i + c];
            let y = target_colour(i, c);
            planes[(5u * c) * n + i] = x;
            planes[(5u * c + 1u) * n + i] = y;
            planes[(5u * c + 2u) * n + i] = x * x;
            planes[(5u * c + 3u) * n + i] = y * y;
            planes[(5u * c + 4u) * n + i] = x * y;
            let d = x - y;
            mine.x += weight * abs(d);
            if (weight > 0.5) {
                mine.z += d * d;
            }
        }
        mine.y = weight * abs(image[PIXEL_FLOATS * i + 3u] - m);
        mine.w = select(0.0, 1.0, weight > 0.5);
    }
    partial[lid] = mine;
    let total = workgroup_sum(lid);
    if (lid == 0u) {
        add_float(0u, total.x);
        add_float(1u, total.y);
        add_float(3u, total.z);
        add_float(4u, total.w);
    }
}

// ---- blur: one direction, every plane ------------------------------------------
@group(0) @binding(5) var<storage, read> blur_in: array<f32>;
@group(0) @binding(6) var<storage, read_write> blur_out: array<f32>;

const RADIUS: i32 = 5;

// Tap k (−5..5) of the normalised Gaussian window (σ = 1.5), as the host
// computed it for the CPU's SSIM: evaluated here in f32 (132 exponentials
// per blurred value, unless the shader compiler folds them) it differed
// from the CPU's taps in the last bits.
fn window(k: i32) -> f32 {
    let tap = u32(k + RADIUS);
    return params.window[tap / 4u][tap % 4u];
}

@compute @workgroup_size(256)
fn blur(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let n = params.width * params.height;
    let flat = gid.x + gid.y * groups.x * 256u;
    if (flat >= n * params.planes) {
        return;
    }
    let plane = flat / n;
    let i = flat % n;
    let x = i32(i % params.width);
    let y = i32(i / params.width);
    var s = 0.0;
    for (var k = -RADIUS; k <= RADIUS; k++) {
        var xx = x;
        var yy = y;
        if (params.horizontal == 1u) {
            xx = x + k;
        } else {
            yy = y + k;
        }
        if (xx >= 0 && xx < i32(params.width) && yy >= 0 && yy < i32(params.height)) {
            s += window(k) * blur_in[plane * n + u32(yy) * params.width + u32(xx)];
        }
    }
    blur_out[flat] = s;
}

// ---- SSIM and its gradient terms -------------------------------------------------
// From the 15 blurred planes (μx, μy, E[x²], E[y²], E[xy] per channel) to
// 9 planes: per channel c, A, B, C at 3c..3c+2 (weighted by w/(3·Σw)).
@group(0) @binding(7) var<storage, read> blurred: array<f32>;
@group(0) @binding(8) var<storage, read_write> terms: array<f32>;

const C1: f32 = 0.0001;
const C2: f32 = 0.0009;

@compute @workgroup_size(256)
fn ssim_terms(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = flat_index(gid, groups);
    let n = params.width * params.height;
    var mine = 0.0;
    if (i < n) {
        let weight = weight_of(i) / (3.0 * params.weight_sum);
        for (var c = 0u; c < 3u; c++) {
            let mx = blurred[(5u * c) * n + i];
            let my = blurred[(5u * c + 1u) * n + i];
            let sx = blurred[(5u * c + 2u) * n + i] - mx * mx;
            let sy = blurred[(5u * c + 3u) * n + i] - my * my;
            let sxy = blurred[(5u * c + 4u) * n + i] - mx * my;
            let n1 = 2.0 * mx * my + C1;
            let n2 = 2.0 * sxy + C2;
            let d1 = mx * mx + my * my + C1;
            let d2 = sx + sy + C2;
            let s = n1 * n2 / (d1 * d2);
            let d_mx = 2.0 * my * n2 / (d1 * d2) - s * 2.0 * mx / d1;
            let d_sx = -s / d2;
            let d_sxy = 2.0 * n1 / (d1 * d2);
            mine += weight * s;
            terms[(3u * c) * n + i] = weight * (d_mx - 2.0 * d_sx * mx - d_sxy * my);
            terms[(3u * c + 1u) * n + i] = weight * d_sx;
            terms[(3u * c + 2u) * n + i] = weight * d_sxy;
        }
    }
    partial[lid] = vec4<f32>(mine, 0.0, 0.0, 0.0);
    let total = workgroup_sum(lid);
    if (lid == 0u) {
        add_float(2u, total.x);
    }
}

// ---- gradient ----------------------------------------------------------------
// The blurred terms (9 planes) and the pixels to dL/d(rgb), dL/d(alpha).
@group(0) @binding(9) var<storage, read> blurred_terms: array<f32>;
@group(0) @binding(10) var<storage, read_write> d_image: array<f32>;

// The CPU's f32 `signum`: +1 for +0.
fn signum(v: f32) -> f32 {
    return select(-1.0, 1.0, v >= 0.0);
}

@compute @workgroup_size(256)
fn gradient(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = flat_index(gid, groups);
    let n = params.width * params.height;
    if (i >= n) {
        return;
    }
    let m = target_data[5u * i + 3u];
    let weight = weight_of(i);
    let lam = params.lambda_ssim;
    for (var c = 0u; c < 3u; c++) {
        let x = image[PIXEL_FLOATS * i + c];
        let y = target_colour(i, c);
        let l1 = (1.0 - lam) * weight * signum(x - y) / (3.0 * params.weight_sum);
        let ga = blurred_terms[(3u * c) * n + i];
        let gb = blurred_terms[(3u * c + 1u) * n + i];
        let gc = blurred_terms[(3u * c + 2u) * n + i];
        d_image[4u * i + c] = l1 - lam * (ga + 2.0 * x * gb + y * gc);
    }
    d_image[4u * i + 3u] = params.lambda_opacity * weight * signum(image[PIXEL_FLOATS * i + 3u] - m) / params.weight_sum;
}
