// Declarations every kernel module starts with (prepended by the host).

// The camera and scene counts of the projection kernels.
struct Camera {
    rot0: vec4<f32>,        // world-to-camera rotation rows; .w = translation
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    campos: vec4<f32>,      // camera centre in world coordinates
    intrinsics: vec4<f32>,  // fx, fy, cx, cy
    limits: vec4<f32>,      // x/z clamp (negative side, positive side), y/z clamp
    size: vec4<f32>,        // width, height, near, far
    footprint: vec4<f32>,   // eps2d, antialiased (0/1), SH by the normal in the camera's frame (0/1)
    background: vec4<f32>,
    counts: vec4<u32>,      // gaussians, SH coefficients used per channel, plain RGB (0/1), tiles in x
    counts2: vec4<u32>,     // tiles in y, colour coefficients stored per Gaussian
}

// The image of the compositing kernels.
struct RasterParams {
    width: u32,
    height: u32,
    tiles_x: u32,
    _pad: u32,
    background: vec4<f32>,
}

// The compositing limits of the CPU reference (`raster.rs`).
const ALPHA_MAX: f32 = 0.999;
const ALPHA_MIN: f32 = 0.00392156862745098; // 1/255
const SIGMA_SKIP: f32 = 5.55;
const T_STOP: f32 = 1e-4;
// Floats per pixel of the forward image (see rasterize.wgsl).
const PIXEL_FLOATS: u32 = 7u;
// Floats per Gaussian of the 2D gradients (see rasterize_backward.wgsl).
const GRADS2D_FLOATS: u32 = 12u;

// The flat index of a thread in a 256-wide dispatch folded into two dimensions.
fn flat_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * 256u;
}

// The index of a workgroup in a dispatch folded into two dimensions.
fn workgroup_index(wid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return wid.x + wid.y * groups.x;
}

// The rotation of a quaternion (w, x, y, z), normalised first, as columns
// (raster.rs's quat_to_rotmat).
fn rotation_of(quaternion: vec4<f32>) -> mat3x3<f32> {
    let q = quaternion / sqrt(dot(quaternion, quaternion));
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    return mat3x3<f32>(
        vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
        vec3<f32>(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
        vec3<f32>(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
    );
}

// The shortest of the axes with scales `s`, ties to the lower (as the CPU
// reference's `rig_direction` picks it).
fn shortest_axis(s: vec3<f32>) -> u32 {
    var axis = 0u;
    if (s.y < s.x) {
        axis = 1u;
    }
    if (s.z < select(s.x, s.y, axis == 1u)) {
        axis = 2u;
    }
    return axis;
}

// Real SH constants up to degree 3 (the CPU reference's `sh.rs`).
const SH_C0: f32 = 0.28209479177387814;
const SH_C1: f32 = 0.4886025119029199;
const SH_C2_0: f32 = 1.0925484305920792;
const SH_C2_1: f32 = -1.0925484305920792;
const SH_C2_2: f32 = 0.31539156525252005;
const SH_C2_3: f32 = -1.0925484305920792;
const SH_C2_4: f32 = 0.5462742152960396;
const SH_C3_0: f32 = -0.5900435899266435;
const SH_C3_1: f32 = 2.890611442640554;
const SH_C3_2: f32 = -0.4570457994644658;
const SH_C3_3: f32 = 0.3731763325901154;
const SH_C3_4: f32 = -0.4570457994644658;
const SH_C3_5: f32 = 1.445305721320277;
const SH_C3_6: f32 = -0.5900435899266435;

// The first `k` SH basis functions at unit direction `dir` (the rest 0).
fn sh_basis(dir: vec3<f32>, k: u32) -> array<f32, 16> {
    var b: array<f32, 16>;
    b[0] = SH_C0;
    let x = dir.x;
    let y = dir.y;
    let z = dir.z;
    if (k > 1u) {
        b[1] = -SH_C1 * y;
        b[2] = SH_C1 * z;
        b[3] = -SH_C1 * x;
    }
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    if (k > 4u) {
        b[4] = SH_C2_0 * x * y;
        b[5] = SH_C2_1 * y * z;
        b[6] = SH_C2_2 * (2.0 * zz - xx - yy);
        b[7] = SH_C2_3 * x * z;
        b[8] = SH_C2_4 * (xx - yy);
    }
    if (k > 9u) {
        b[9] = SH_C3_0 * y * (3.0 * xx - yy);
        b[10] = SH_C3_1 * x * y * z;
        b[11] = SH_C3_2 * y * (4.0 * zz - xx - yy);
        b[12] = SH_C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
        b[13] = SH_C3_4 * x * (4.0 * zz - xx - yy);
        b[14] = SH_C3_5 * z * (xx - yy);
        b[15] = SH_C3_6 * x * (xx - 3.0 * yy);
    }
    return b;
}
