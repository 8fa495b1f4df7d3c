// Training on the device (the CPU trainer's `Adam` and statistics, in f32):
// the activations the projection reads, the densification statistics, and
// Adam steps on the raw parameters.

struct Params {
    len: u32,
    // Adam: 0 plain, 1 log-scale (gradient given for exp), 2 opacity logit
    // (gradient given for the sigmoid), 3 SH (first coefficient of each
    // Gaussian at `lr`, the rest at `lr_rest`). Statistics: 0 the summed
    // mean2d gradient, 1 its per-pixel absolute sums (AbsGS).
    kind: u32,
    stride: u32,
    _pad: u32,
    lr: f32,
    lr_rest: f32,
    bias1: f32,   // 1 - beta1^t
    bias2: f32,   // 1 - beta2^t
    half_width: f32,
    half_height: f32,
    beta1: f32,
    beta2: f32,
    // 1 - beta1, 1 - beta2 and epsilon as the CPU computes them in f32.
    one_minus_beta1: f32,
    one_minus_beta2: f32,
    epsilon: f32,
    // MCMC's penalty weight on the activated value (scale or opacity),
    // added to its gradient; 0 without MCMC.
    penalty: f32,
}

@group(0) @binding(0) var<uniform> params: Params;


// ---- activations: scales = exp(log-scales), opacities = sigmoid(logits) ----
@group(0) @binding(1) var<storage, read> log_scales: array<f32>;
@group(0) @binding(2) var<storage, read> logits: array<f32>;
@group(0) @binding(3) var<storage, read_write> scales: array<f32>;
@group(0) @binding(4) var<storage, read_write> opacities: array<f32>;

@compute @workgroup_size(256)
fn activate(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = flat_index(gid, groups);
    if (i >= params.len) {
        return;
    }
    for (var a = 0u; a < 3u; a++) {
        scales[3u * i + a] = exp(log_scales[3u * i + a]);
    }
    opacities[i] = 1.0 / (1.0 + exp(-logits[i]));
}

// ---- densification statistics: |screen-space mean gradient| of visible ----
@group(0) @binding(5) var<storage, read> grads2d: array<f32>;
@group(0) @binding(6) var<storage, read_write> grad_sum: array<f32>;
@group(0) @binding(7) var<storage, read_write> grad_count: array<u32>;

@compute @workgroup_size(256)
fn statistics(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = flat_index(gid, groups);
    let base = GRADS2D_FLOATS * i;
    if (i >= params.len || grads2d[base + 9u] < 0.5) {
        return;
    }
    let at = base + select(0u, 10u, params.kind == 1u);
    let gx = grads2d[at] * params.half_width;
    let gy = grads2d[at + 1u] * params.half_height;
    grad_sum[i] += sqrt(gx * gx + gy * gy);
    grad_count[i] += 1u;
}

// ---- Adam ------------------------------------------------------------------
@group(0) @binding(8) var<storage, read_write> values: array<f32>;
@group(0) @binding(9) var<storage, read> grads: array<f32>;
@group(0) @binding(10) var<storage, read_write> first: array<f32>;
@group(0) @binding(11) var<storage, read_write> second: array<f32>;

@compute @workgroup_size(256)
fn adam(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = flat_index(gid, groups);
    if (i >= params.len) {
        return;
    }
    let x = values[i];
    var g = grads[i];
    var lr = params.lr;
    if (params.kind == 1u) {
        let scale = exp(x);
        g = g * scale + params.penalty * scale;
    } else if (params.kind == 2u) {
        let o = 1.0 / (1.0 + exp(-x));
        g = g * o * (1.0 - o) + params.penalty * (o * (1.0 - o));
    } else if (params.kind == 3u && (i / 3u) % params.stride != 0u) {
        lr = params.lr_rest;
    }
    let m = params.beta1 * first[i] + params.one_minus_beta1 * g;
    let v = params.beta2 * second[i] + params.one_minus_beta2 * g * g;
    first[i] = m;
    second[i] = v;
    values[i] = x - lr * (m / params.bias1) / (sqrt(v / params.bias2) + params.epsilon);
}

// ---- MCMC noise on near-transparent splats (mcmc.rs's `add_noise`) ---------
// Uses `len`, `kind` as the seed, `stride` as the step and `lr` as the noise
// scale; the means are bound as `values`.
@group(0) @binding(12) var<storage, read> quats: array<f32>;

fn pcg_hash(x: u32) -> u32 {
    let state = x * 747796405u + 2891336453u;
    let word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

@compute @workgroup_size(256)
fn noise(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = flat_index(gid, groups);
    if (i >= params.len) {
        return;
    }
    let opacity = 1.0 / (1.0 + exp(-logits[i]));
    let gate = 1.0 / (1.0 + exp(-(100.0 * (0.005 - opacity))));
    if (gate * params.lr == 0.0) {
        return;
    }
    let base = pcg_hash(params.kind ^ pcg_hash(params.stride ^ pcg_hash(i)));
    var u: array<f32, 4>;
    for (var j = 0u; j < 4u; j++) {
        let h = pcg_hash(base + j * 0x9e3779b9u);
        u[j] = (f32(h >> 8u) + 1.0) / 16777216.0;
    }
    let radius = vec2<f32>(sqrt(-2.0 * log(u[0])), sqrt(-2.0 * log(u[2])));
    let angle = vec2<f32>(6.2831855 * u[1], 6.2831855 * u[3]);
    let z = vec3<f32>(radius.x * cos(angle.x), radius.x * sin(angle.x), radius.y * cos(angle.y));
    let r = rotation_of(vec4<f32>(quats[4u * i], quats[4u * i + 1u], quats[4u * i + 2u], quats[4u * i + 3u]));
    let variance = vec3<f32>(
        exp(2.0 * log_scales[3u * i]),
        exp(2.0 * log_scales[3u * i + 1u]),
        exp(2.0 * log_scales[3u * i + 2u]),
    );
    // Σz = R·S²·Rᵀ·z.
    let moved = r * (variance * (transpose(r) * z));
    let step = gate * params.lr;
    values[3u * i] += step * moved.x;
    values[3u * i + 1u] += step * moved.y;
    values[3u * i + 2u] += step * moved.z;
}
