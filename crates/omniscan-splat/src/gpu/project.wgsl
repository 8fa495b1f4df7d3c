// Projection of every Gaussian (one thread each), the same arithmetic as the
// CPU reference's `raster::project` and `Projected::reach` in f32: EWA with
// the Jacobian clamped 30% beyond the image, +eps2d low-pass, optional
// antialiasing compensation, SH colour towards the camera, and the tile
// rectangle where the Gaussian can reach alpha >= 1/255.


@group(0) @binding(0) var<uniform> cam: Camera;
@group(0) @binding(1) var<storage, read> means: array<f32>;
@group(0) @binding(2) var<storage, read> scales: array<f32>;
@group(0) @binding(3) var<storage, read> quats: array<f32>;
@group(0) @binding(4) var<storage, read> opacities: array<f32>;
@group(0) @binding(5) var<storage, read> coeffs: array<f32>;
// 12 floats per Gaussian: mean x, y; conic a, b, c; opacity; r, g, b; depth;
// visible (1 or 0; the CPU reference's non-zero radii); compensation.
@group(0) @binding(6) var<storage, read_write> projected: array<f32>;
// 4 per Gaussian: tile x0, x1, y0, y1 (half-open).
@group(0) @binding(7) var<storage, read_write> rects: array<u32>;
// Tiles touched per Gaussian; one extra entry (0) so its exclusive scan ends in the total.
@group(0) @binding(8) var<storage, read_write> tile_counts: array<u32>;

const RADIUS_SIGMA: f32 = 3.33;
const TILE: f32 = 16.0;

fn sh_colour(g: u32, dir: vec3<f32>) -> vec3<f32> {
    let k = cam.counts.y;
    let base = g * cam.counts2.y * 3u;
    let b = sh_basis(dir, k);
    var c = vec3<f32>(0.0);
    for (var i = 0u; i < k; i++) {
        let o = base + 3u * i;
        c += b[i] * vec3<f32>(coeffs[o], coeffs[o + 1u], coeffs[o + 2u]);
    }
    return max(c + vec3<f32>(0.5), vec3<f32>(0.0));
}

fn invisible(g: u32) {
    projected[12u * g + 10u] = 0.0;
    rects[4u * g] = 0u;
    rects[4u * g + 1u] = 0u;
    rects[4u * g + 2u] = 0u;
    rects[4u * g + 3u] = 0u;
    tile_counts[g] = 0u;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let g = flat_index(gid, groups);
    let n = cam.counts.x;
    if (g == n) {
        tile_counts[n] = 0u;
    }
    if (g >= n) {
        return;
    }
    let m = vec3<f32>(means[3u * g], means[3u * g + 1u], means[3u * g + 2u]);
    let rot = mat3x3<f32>(
        vec3<f32>(cam.rot0.x, cam.rot1.x, cam.rot2.x),
        vec3<f32>(cam.rot0.y, cam.rot1.y, cam.rot2.y),
        vec3<f32>(cam.rot0.z, cam.rot1.z, cam.rot2.z),
    );
    let pc = rot * m + vec3<f32>(cam.rot0.w, cam.rot1.w, cam.rot2.w);
    let z = pc.z;

    // World covariance R S Sᵀ Rᵀ from the normalised quaternion (w, x, y, z).
    let r = rotation_of(vec4<f32>(quats[4u * g], quats[4u * g + 1u], quats[4u * g + 2u], quats[4u * g + 3u]));
    let s = vec3<f32>(scales[3u * g], scales[3u * g + 1u], scales[3u * g + 2u]);
    let rs = mat3x3<f32>(r[0] * s.x, r[1] * s.y, r[2] * s.z);
    let cov_w = rs * transpose(rs);
    let cov_c = rot * cov_w * transpose(rot);

    let fx = cam.intrinsics.x;
    let fy = cam.intrinsics.y;
    let tx = z * min(max(pc.x / z, -cam.limits.x), cam.limits.y);
    let ty = z * min(max(pc.y / z, -cam.limits.z), cam.limits.w);
    // J (2x3) as columns of a 3x2 transpose: rows j0, j1.
    let j0 = vec3<f32>(fx / z, 0.0, -fx * tx / (z * z));
    let j1 = vec3<f32>(0.0, fy / z, -fy * ty / (z * z));
    let cj0 = cov_c * j0;
    let cj1 = cov_c * j1;
    let c00 = dot(j0, cj0);
    let c01 = dot(j0, cj1);
    let c10 = dot(j1, cj0);
    let c11 = dot(j1, cj1);
    let det_raw = c00 * c11 - c01 * c10;
    let eps = cam.footprint.x;
    let a = c00 + eps;
    let b = (c01 + c10) * 0.5;
    let c = c11 + eps;
    let det = max(a * c - b * b, 1e-10);
    let compensation = sqrt(max(det_raw / det, 0.0));
    let conic = vec3<f32>(c / det, -b / det, a / det);
    let mean2d = vec2<f32>(fx * pc.x / z + cam.intrinsics.z, fy * pc.y / z + cam.intrinsics.w);
    let rx = ceil(RADIUS_SIGMA * sqrt(a));
    let ry = ceil(RADIUS_SIGMA * sqrt(c));
    let w = cam.size.x;
    let h = cam.size.y;
    let in_depth = z > cam.size.z && z < cam.size.w;
    let on_image = mean2d.x + rx > 0.0 && mean2d.x - rx < w && mean2d.y + ry > 0.0 && mean2d.y - ry < h;
    if (!(in_depth && on_image && det < 1e30) || rx < 1.0 || ry < 1.0) {
        invisible(g);
        return;
    }
    var opacity = opacities[g];
    if (cam.footprint.y > 0.5) {
        opacity = opacity * compensation;
    }
    var colour: vec3<f32>;
    if (cam.counts.z == 1u) {
        colour = vec3<f32>(coeffs[3u * g], coeffs[3u * g + 1u], coeffs[3u * g + 2u]);
    } else if (cam.footprint.z > 0.5) {
        // The shortest axis in the camera's frame, facing the camera.
        var columns = r;
        let u = rot * columns[shortest_axis(s)];
        colour = sh_colour(g, select(u, -u, u.z > 0.0));
    } else {
        let d = m - cam.campos.xyz;
        colour = sh_colour(g, d / sqrt(dot(d, d)));
    }
    let o = 12u * g;
    projected[o] = mean2d.x;
    projected[o + 1u] = mean2d.y;
    projected[o + 2u] = conic.x;
    projected[o + 3u] = conic.y;
    projected[o + 4u] = conic.z;
    projected[o + 5u] = opacity;
    projected[o + 6u] = colour.x;
    projected[o + 7u] = colour.y;
    projected[o + 8u] = colour.z;
    projected[o + 9u] = z;
    projected[o + 10u] = 1.0;
    projected[o + 11u] = compensation;

    // Reach: where opacity·e^(-σ) = 1/255, clamped to the 3.33σ radii.
    if (opacity < ALPHA_MIN) {
        // Visible but too faint to reach 1/255 anywhere: no tiles.
        rects[4u * g] = 0u;
        rects[4u * g + 1u] = 0u;
        rects[4u * g + 2u] = 0u;
        rects[4u * g + 3u] = 0u;
        tile_counts[g] = 0u;
        return;
    }
    let level = 2.0 * log(opacity / ALPHA_MIN);
    let inverse_det = conic.x * conic.z - conic.y * conic.y;
    var reach = vec2<f32>(rx, ry);
    if (inverse_det > 0.0) {
        let sxx = conic.z / inverse_det;
        let syy = conic.x / inverse_det;
        if (sxx < 1e30 && syy < 1e30) {
            reach = vec2<f32>(min(sqrt(level * sxx), rx), min(sqrt(level * syy), ry));
        }
    }
    let tiles_x = f32(cam.counts.w);
    let tiles_y = f32(cam.counts2.x);
    let x0 = u32(clamp(floor((mean2d.x - reach.x) / TILE), 0.0, tiles_x));
    let x1 = u32(clamp(ceil((mean2d.x + reach.x) / TILE), 0.0, tiles_x));
    let y0 = u32(clamp(floor((mean2d.y - reach.y) / TILE), 0.0, tiles_y));
    let y1 = u32(clamp(ceil((mean2d.y + reach.y) / TILE), 0.0, tiles_y));
    rects[4u * g] = x0;
    rects[4u * g + 1u] = x1;
    rects[4u * g + 2u] = y0;
    rects[4u * g + 3u] = y1;
    tile_counts[g] = select(0u, (x1 - x0) * (y1 - y0), x1 > x0 && y1 > y0);
}
