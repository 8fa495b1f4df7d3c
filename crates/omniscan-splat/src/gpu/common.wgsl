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
    footprint: vec4<f32>,   // eps2d, antialiased (0/1)
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

// The flat index of a thread in a 256-wide dispatch folded into two dimensions.
fn flat_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * 256u;
}
