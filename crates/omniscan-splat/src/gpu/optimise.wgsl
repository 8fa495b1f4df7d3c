// Training on the device (the CPU trainer's `Adam` and statistics, in f32):
// the activations the projection reads, the densification statistics, and
// Adam steps on the raw parameters.

struct Params {
    len: u32,
    // 0 plain, 1 log-scale (gradient given for exp), 2 opacity logit
    // (gradient given for the sigmoid), 3 SH (first coefficient of each
    // Gaussian at `lr`, the rest at `lr_rest`).
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
    _pad2: f32,
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
    if (i >= params.len || grads2d[10u * i + 9u] < 0.5) {
        return;
    }
    let gx = grads2d[10u * i] * params.half_width;
    let gy = grads2d[10u * i + 1u] * params.half_height;
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
        g = g * exp(x);
    } else if (params.kind == 2u) {
        let o = 1.0 / (1.0 + exp(-x));
        g = g * o * (1.0 - o);
    } else if (params.kind == 3u && (i / 3u) % params.stride != 0u) {
        lr = params.lr_rest;
    }
    let m = params.beta1 * first[i] + params.one_minus_beta1 * g;
    let v = params.beta2 * second[i] + params.one_minus_beta2 * g * g;
    first[i] = m;
    second[i] = v;
    values[i] = x - lr * (m / params.bias1) / (sqrt(v / params.bias2) + params.epsilon);
}
