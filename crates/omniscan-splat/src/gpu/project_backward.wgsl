// Backward pass of the projection (the CPU reference's `project_backward`):
// from each Gaussian's gradients of 2D mean, conic, view opacity and view
// colour to its mean, quaternion, scales, opacity and colour (RGB or SH
// coefficients, with the view direction's dependence on the mean). One
// thread per Gaussian. With `d_camera` bound at 6 floats per Gaussian, each
// also writes its share of the gradient with respect to a motion of the
// camera (the CPU reference's `camera_contribution`), which camera_sum.wgsl
// adds up; bound shorter (one float), nothing is written there.


@group(0) @binding(0) var<uniform> cam: Camera;
@group(0) @binding(1) var<storage, read> means: array<f32>;
@group(0) @binding(2) var<storage, read> scales: array<f32>;
@group(0) @binding(3) var<storage, read> quats: array<f32>;
@group(0) @binding(4) var<storage, read> opacities: array<f32>;
@group(0) @binding(5) var<storage, read> coeffs: array<f32>;
@group(0) @binding(6) var<storage, read> projected: array<f32>;
// GRADS2D_FLOATS per Gaussian (see rasterize_backward.wgsl); the tenth is set
// here to 1 for visible Gaussians (the densification statistics count them).
@group(0) @binding(7) var<storage, read_write> grads2d: array<f32>;
@group(0) @binding(8) var<storage, read_write> d_means: array<f32>;
@group(0) @binding(9) var<storage, read_write> d_quats: array<f32>;
@group(0) @binding(10) var<storage, read_write> d_scales: array<f32>;
@group(0) @binding(11) var<storage, read_write> d_opacities: array<f32>;
@group(0) @binding(12) var<storage, read_write> d_coeffs: array<f32>;
@group(0) @binding(13) var<storage, read_write> d_camera: array<f32>;

fn zero_outputs(g: u32, k: u32) {
    for (var a = 0u; a < 3u; a++) {
        d_means[3u * g + a] = 0.0;
        d_scales[3u * g + a] = 0.0;
    }
    for (var a = 0u; a < 4u; a++) {
        d_quats[4u * g + a] = 0.0;
    }
    d_opacities[g] = 0.0;
    for (var a = 0u; a < 3u * k; a++) {
        d_coeffs[3u * k * g + a] = 0.0;
    }
}

// This Gaussian's share of dL/dv and dL/dω for the camera-frame motion
// u -> u + ω × u + v: the camera-frame mean moves (and, for a translation,
// the view direction as the world mean would); a rotation turns the
// covariance, dΣc = ω̂Σc − Σcω̂, so dL = tr(Aω̂) with A = ΣcGᵀ − GᵀΣc.
fn write_camera_share(
    g: u32,
    R: array<array<f32, 3>, 3>,
    pc: vec3<f32>,
    d_pc: vec3<f32>,
    d_view_dir: vec3<f32>,
    cov_c: array<array<f32, 3>, 3>,
    d_cov_c: array<array<f32, 3>, 3>,
    rig_turn: vec3<f32>,
) {
    var a: array<array<f32, 3>, 3>;
    for (var r = 0u; r < 3u; r++) {
        for (var c = 0u; c < 3u; c++) {
            var acc = 0.0;
            for (var u = 0u; u < 3u; u++) {
                acc += cov_c[r][u] * d_cov_c[c][u] - d_cov_c[u][r] * cov_c[u][c];
            }
            a[r][c] = acc;
        }
    }
    let turn = cross(pc, d_pc)
        + vec3<f32>(a[1][2] - a[2][1], a[2][0] - a[0][2], a[0][1] - a[1][0])
        + rig_turn;
    for (var r = 0u; r < 3u; r++) {
        d_camera[6u * g + r] = d_pc[r] + R[r][0] * d_view_dir.x + R[r][1] * d_view_dir.y + R[r][2] * d_view_dir.z;
        d_camera[6u * g + 3u + r] = turn[r];
    }
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let g = flat_index(gid, groups);
    let n = cam.counts.x;
    if (g >= n) {
        return;
    }
    let k = cam.counts.y;
    let stride = cam.counts2.y;
    zero_outputs(g, stride);
    let camera_wanted = arrayLength(&d_camera) >= 6u * n;
    if (camera_wanted) {
        for (var a = 0u; a < 6u; a++) {
            d_camera[6u * g + a] = 0.0;
        }
    }
    let b9 = GRADS2D_FLOATS * g;
    let visible = projected[12u * g + 10u] > 0.5;
    grads2d[b9 + 9u] = select(0.0, 1.0, visible);
    if (!visible) {
        return;
    }
    let dm2 = vec2<f32>(grads2d[b9], grads2d[b9 + 1u]);
    let dconic = vec3<f32>(grads2d[b9 + 2u], grads2d[b9 + 3u], grads2d[b9 + 4u]);
    let d_ov = grads2d[b9 + 5u];
    let d_cv = vec3<f32>(grads2d[b9 + 6u], grads2d[b9 + 7u], grads2d[b9 + 8u]);

    var R: array<array<f32, 3>, 3>;
    R[0] = array<f32, 3>(cam.rot0.x, cam.rot0.y, cam.rot0.z);
    R[1] = array<f32, 3>(cam.rot1.x, cam.rot1.y, cam.rot1.z);
    R[2] = array<f32, 3>(cam.rot2.x, cam.rot2.y, cam.rot2.z);
    let trans = vec3<f32>(cam.rot0.w, cam.rot1.w, cam.rot2.w);
    let m = vec3<f32>(means[3u * g], means[3u * g + 1u], means[3u * g + 2u]);
    var pc = trans;
    for (var r = 0u; r < 3u; r++) {
        pc[r] += R[r][0] * m.x + R[r][1] * m.y + R[r][2] * m.z;
    }
    let x = pc.x;
    let y = pc.y;
    let z = pc.z;

    // Opacity, and the antialiasing compensation.
    let antialiased = cam.footprint.y > 0.5;
    let compensation = projected[12u * g + 11u];
    var d_comp = 0.0;
    if (antialiased) {
        d_opacities[g] = d_ov * compensation;
        d_comp = d_ov * opacities[g];
    } else {
        d_opacities[g] = d_ov;
    }

    // The splat's rotation (rows of R(q̂)) and scales, for the colour and the covariance.
    var q = vec4<f32>(quats[4u * g], quats[4u * g + 1u], quats[4u * g + 2u], quats[4u * g + 3u]);
    let norm = sqrt(dot(q, q));
    q = q / norm;
    let qw = q.x;
    let qx = q.y;
    let qy = q.z;
    let qz = q.w;
    var r: array<array<f32, 3>, 3>;
    r[0] = array<f32, 3>(1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy));
    r[1] = array<f32, 3>(2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx));
    r[2] = array<f32, 3>(2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy));
    let s = array<f32, 3>(scales[3u * g], scales[3u * g + 1u], scales[3u * g + 2u]);

    // Colour: through the clamp to RGB or SH, and the SH view direction.
    var d_mean = vec3<f32>(0.0);
    // Under the fixed-rig appearance, the colour's gradient into the column
    // `rig_axis` of the splat's rotation.
    let rig = cam.footprint.z > 0.5;
    var rig_axis = 0u;
    var d_rig = vec3<f32>(0.0);
    // A fixed-rig direction turns with the camera: dL/dω = d × dL/dd.
    var rig_turn = vec3<f32>(0.0);
    if (cam.counts.z == 1u) {
        d_coeffs[3u * g] = d_cv.x;
        d_coeffs[3u * g + 1u] = d_cv.y;
        d_coeffs[3u * g + 2u] = d_cv.z;
    } else {
        let dvec = m - cam.campos.xyz;
        let len = sqrt(dot(dvec, dvec));
        var dir = dvec / len;
        var rig_sign = 1.0;
        if (rig) {
            rig_axis = shortest_axis(vec3<f32>(s[0], s[1], s[2]));
            var u = vec3<f32>(0.0);
            for (var a = 0u; a < 3u; a++) {
                for (var b = 0u; b < 3u; b++) {
                    u[a] += R[a][b] * r[b][rig_axis];
                }
            }
            rig_sign = select(1.0, -1.0, u.z > 0.0);
            dir = u * rig_sign;
        }
        let dx = dir.x;
        let dy = dir.y;
        let dz = dir.z;
        let xx = dx * dx;
        let yy = dy * dy;
        let zz = dz * dz;
        let b = sh_basis(dir, k);
        // The basis functions' gradients with respect to the direction.
        var db: array<vec3<f32>, 16>;
        db[0] = vec3<f32>(0.0);
        if (k > 1u) {
            db[1] = vec3<f32>(0.0, -SH_C1, 0.0);
            db[2] = vec3<f32>(0.0, 0.0, SH_C1);
            db[3] = vec3<f32>(-SH_C1, 0.0, 0.0);
        }
        if (k > 4u) {
            db[4] = vec3<f32>(SH_C2_0 * dy, SH_C2_0 * dx, 0.0);
            db[5] = vec3<f32>(0.0, SH_C2_1 * dz, SH_C2_1 * dy);
            db[6] = vec3<f32>(-2.0 * SH_C2_2 * dx, -2.0 * SH_C2_2 * dy, 4.0 * SH_C2_2 * dz);
            db[7] = vec3<f32>(SH_C2_3 * dz, 0.0, SH_C2_3 * dx);
            db[8] = vec3<f32>(2.0 * SH_C2_4 * dx, -2.0 * SH_C2_4 * dy, 0.0);
        }
        if (k > 9u) {
            db[9] = vec3<f32>(6.0 * SH_C3_0 * dx * dy, SH_C3_0 * (3.0 * xx - 3.0 * yy), 0.0);
            db[10] = vec3<f32>(SH_C3_1 * dy * dz, SH_C3_1 * dx * dz, SH_C3_1 * dx * dy);
            db[11] = vec3<f32>(-2.0 * SH_C3_2 * dx * dy, SH_C3_2 * (4.0 * zz - xx - 3.0 * yy), 8.0 * SH_C3_2 * dy * dz);
            db[12] = vec3<f32>(-6.0 * SH_C3_3 * dx * dz, -6.0 * SH_C3_3 * dy * dz, SH_C3_3 * (6.0 * zz - 3.0 * xx - 3.0 * yy));
            db[13] = vec3<f32>(SH_C3_4 * (4.0 * zz - 3.0 * xx - yy), -2.0 * SH_C3_4 * dx * dy, 8.0 * SH_C3_4 * dx * dz);
            db[14] = vec3<f32>(2.0 * SH_C3_5 * dx * dz, -2.0 * SH_C3_5 * dy * dz, SH_C3_5 * (xx - yy));
            db[15] = vec3<f32>(SH_C3_6 * (3.0 * xx - 3.0 * yy), -6.0 * SH_C3_6 * dx * dy, 0.0);
        }
        let base = 3u * stride * g;
        var raw = vec3<f32>(0.0);
        for (var i = 0u; i < k; i++) {
            raw += b[i] * vec3<f32>(coeffs[base + 3u * i], coeffs[base + 3u * i + 1u], coeffs[base + 3u * i + 2u]);
        }
        let d_raw = select(d_cv, vec3<f32>(0.0), raw + vec3<f32>(0.5) < vec3<f32>(0.0));
        var d_dir = vec3<f32>(0.0);
        for (var i = 0u; i < k; i++) {
            let c = vec3<f32>(coeffs[base + 3u * i], coeffs[base + 3u * i + 1u], coeffs[base + 3u * i + 2u]);
            d_coeffs[base + 3u * i] = b[i] * d_raw.x;
            d_coeffs[base + 3u * i + 1u] = b[i] * d_raw.y;
            d_coeffs[base + 3u * i + 2u] = b[i] * d_raw.z;
            d_dir += db[i] * dot(c, d_raw);
        }
        if (rig) {
            rig_turn = cross(dir, d_dir);
            for (var c = 0u; c < 3u; c++) {
                d_rig[c] = rig_sign * (R[0][c] * d_dir.x + R[1][c] * d_dir.y + R[2][c] * d_dir.z);
            }
        } else {
            d_mean += (d_dir - dir * dot(d_dir, dir)) / len;
        }
    }

    // The forward quantities this Gaussian needs.
    var mm: array<array<f32, 3>, 3>;
    for (var a = 0u; a < 3u; a++) {
        for (var c = 0u; c < 3u; c++) {
            mm[a][c] = r[a][c] * s[c];
        }
    }
    var cov_w: array<array<f32, 3>, 3>;
    for (var a = 0u; a < 3u; a++) {
        for (var c = 0u; c < 3u; c++) {
            cov_w[a][c] = mm[a][0] * mm[c][0] + mm[a][1] * mm[c][1] + mm[a][2] * mm[c][2];
        }
    }
    var rc: array<array<f32, 3>, 3>;
    for (var a = 0u; a < 3u; a++) {
        for (var c = 0u; c < 3u; c++) {
            rc[a][c] = R[a][0] * cov_w[0][c] + R[a][1] * cov_w[1][c] + R[a][2] * cov_w[2][c];
        }
    }
    var cov_c: array<array<f32, 3>, 3>;
    for (var a = 0u; a < 3u; a++) {
        for (var c = 0u; c < 3u; c++) {
            cov_c[a][c] = rc[a][0] * R[c][0] + rc[a][1] * R[c][1] + rc[a][2] * R[c][2];
        }
    }
    let fx = cam.intrinsics.x;
    let fy = cam.intrinsics.y;
    let rx = x / z;
    let ry = y / z;
    let clamped_x = rx < -cam.limits.x || rx > cam.limits.y;
    let clamped_y = ry < -cam.limits.z || ry > cam.limits.w;
    let tx = z * min(max(rx, -cam.limits.x), cam.limits.y);
    let ty = z * min(max(ry, -cam.limits.z), cam.limits.w);
    var J: array<array<f32, 3>, 2>;
    J[0] = array<f32, 3>(fx / z, 0.0, -fx * tx / (z * z));
    J[1] = array<f32, 3>(0.0, fy / z, -fy * ty / (z * z));
    var cov2: array<array<f32, 2>, 2>;
    for (var a = 0u; a < 2u; a++) {
        for (var c = 0u; c < 2u; c++) {
            var acc = 0.0;
            for (var u = 0u; u < 3u; u++) {
                for (var v = 0u; v < 3u; v++) {
                    acc += J[a][u] * cov_c[u][v] * J[c][v];
                }
            }
            cov2[a][c] = acc;
        }
    }
    let eps = cam.footprint.x;
    let ca = cov2[0][0] + eps;
    let cb = (cov2[0][1] + cov2[1][0]) * 0.5;
    let cc = cov2[1][1] + eps;
    let det = ca * cc - cb * cb;
    var inv: array<array<f32, 2>, 2>;
    inv[0] = array<f32, 2>(cc / det, -cb / det);
    inv[1] = array<f32, 2>(-cb / det, ca / det);
    var gm: array<array<f32, 2>, 2>;
    gm[0] = array<f32, 2>(dconic.x, dconic.y * 0.5);
    gm[1] = array<f32, 2>(dconic.y * 0.5, dconic.z);
    var d_cov2: array<array<f32, 2>, 2>;
    for (var a = 0u; a < 2u; a++) {
        for (var c = 0u; c < 2u; c++) {
            var acc = 0.0;
            for (var u = 0u; u < 2u; u++) {
                for (var v = 0u; v < 2u; v++) {
                    acc += inv[a][u] * gm[u][v] * inv[v][c];
                }
            }
            d_cov2[a][c] = -acc;
        }
    }
    if (antialiased && d_comp != 0.0) {
        let det_raw = cov2[0][0] * cov2[1][1] - cov2[0][1] * cov2[1][0];
        if (det_raw > 0.0 && compensation > 0.0) {
            var inv_raw: array<array<f32, 2>, 2>;
            inv_raw[0] = array<f32, 2>(cov2[1][1] / det_raw, -cov2[0][1] / det_raw);
            inv_raw[1] = array<f32, 2>(-cov2[1][0] / det_raw, cov2[0][0] / det_raw);
            for (var a = 0u; a < 2u; a++) {
                for (var c = 0u; c < 2u; c++) {
                    d_cov2[a][c] += d_comp * compensation * 0.5 * (inv_raw[a][c] - inv[a][c]);
                }
            }
        }
    }
    // Mean: means2d = (fx x/z + cx, fy y/z + cy).
    var d_pc = vec3<f32>(
        dm2.x * fx / z,
        dm2.y * fy / z,
        -dm2.x * fx * x / (z * z) - dm2.y * fy * y / (z * z),
    );
    // cov2 = J Σc Jᵀ: dΣc = Jᵀ G J, dJ = (G + Gᵀ) J Σc.
    var d_cov_c: array<array<f32, 3>, 3>;
    for (var a = 0u; a < 3u; a++) {
        for (var c = 0u; c < 3u; c++) {
            var acc = 0.0;
            for (var u = 0u; u < 2u; u++) {
                for (var v = 0u; v < 2u; v++) {
                    acc += J[u][a] * d_cov2[u][v] * J[v][c];
                }
            }
            d_cov_c[a][c] = acc;
        }
    }
    var d_j: array<array<f32, 3>, 2>;
    for (var u = 0u; u < 2u; u++) {
        for (var a = 0u; a < 3u; a++) {
            var acc = 0.0;
            for (var v = 0u; v < 2u; v++) {
                for (var c = 0u; c < 3u; c++) {
                    acc += (d_cov2[u][v] + d_cov2[v][u]) * J[v][c] * cov_c[c][a];
                }
            }
            d_j[u][a] = acc;
        }
    }
    let z2 = z * z;
    let z3 = z2 * z;
    d_pc.z -= d_j[0][0] * fx / z2 + d_j[1][1] * fy / z2;
    if (clamped_x) {
        d_pc.z += d_j[0][2] * fx * (tx / z) / z2;
    } else {
        d_pc.x -= d_j[0][2] * fx / z2;
        d_pc.z += d_j[0][2] * 2.0 * fx * tx / z3;
    }
    if (clamped_y) {
        d_pc.z += d_j[1][2] * fy * (ty / z) / z2;
    } else {
        d_pc.y -= d_j[1][2] * fy / z2;
        d_pc.z += d_j[1][2] * 2.0 * fy * ty / z3;
    }
    if (camera_wanted) {
        // Here d_mean holds only the colour's (world-frame) pull on the mean.
        write_camera_share(g, R, pc, d_pc, d_mean, cov_c, d_cov_c, rig_turn);
    }
    // Camera to world: the mean through Rᵀ, the covariance as Rᵀ dΣc R.
    for (var a = 0u; a < 3u; a++) {
        d_mean[a] += R[0][a] * d_pc.x + R[1][a] * d_pc.y + R[2][a] * d_pc.z;
    }
    d_means[3u * g] = d_mean.x;
    d_means[3u * g + 1u] = d_mean.y;
    d_means[3u * g + 2u] = d_mean.z;
    var t1: array<array<f32, 3>, 3>;
    for (var a = 0u; a < 3u; a++) {
        for (var c = 0u; c < 3u; c++) {
            t1[a][c] = R[0][a] * d_cov_c[0][c] + R[1][a] * d_cov_c[1][c] + R[2][a] * d_cov_c[2][c];
        }
    }
    var d_cov_w: array<array<f32, 3>, 3>;
    for (var a = 0u; a < 3u; a++) {
        for (var c = 0u; c < 3u; c++) {
            d_cov_w[a][c] = t1[a][0] * R[0][c] + t1[a][1] * R[1][c] + t1[a][2] * R[2][c];
        }
    }
    // Σ = M Mᵀ with M = R S.
    var d_r: array<array<f32, 3>, 3>;
    var d_s = vec3<f32>(0.0);
    for (var a = 0u; a < 3u; a++) {
        for (var c = 0u; c < 3u; c++) {
            var d_m = 0.0;
            for (var u = 0u; u < 3u; u++) {
                d_m += (d_cov_w[a][u] + d_cov_w[u][a]) * mm[u][c];
            }
            d_r[a][c] = d_m * s[c];
            d_s[c] += d_m * r[a][c];
        }
    }
    if (rig) {
        for (var a = 0u; a < 3u; a++) {
            d_r[a][rig_axis] += d_rig[a];
        }
    }
    d_scales[3u * g] = d_s.x;
    d_scales[3u * g + 1u] = d_s.y;
    d_scales[3u * g + 2u] = d_s.z;
    // Rotation matrix to the normalised quaternion, then through the normalisation.
    let d_hat = vec4<f32>(
        2.0 * (-qz * d_r[0][1] + qy * d_r[0][2] + qz * d_r[1][0] - qx * d_r[1][2] - qy * d_r[2][0] + qx * d_r[2][1]),
        2.0 * (qy * d_r[0][1] + qz * d_r[0][2] + qy * d_r[1][0] - 2.0 * qx * d_r[1][1] - qw * d_r[1][2]
            + qz * d_r[2][0] + qw * d_r[2][1] - 2.0 * qx * d_r[2][2]),
        2.0 * (-2.0 * qy * d_r[0][0] + qx * d_r[0][1] + qw * d_r[0][2] + qx * d_r[1][0] + qz * d_r[1][2]
            - qw * d_r[2][0] + qz * d_r[2][1] - 2.0 * qy * d_r[2][2]),
        2.0 * (-2.0 * qz * d_r[0][0] - qw * d_r[0][1] + qx * d_r[0][2] + qw * d_r[1][0] - 2.0 * qz * d_r[1][1]
            + qy * d_r[1][2] + qx * d_r[2][0] + qy * d_r[2][1]),
    );
    let d_q = (d_hat - q * dot(d_hat, q)) / norm;
    d_quats[4u * g] = d_q.x;
    d_quats[4u * g + 1u] = d_q.y;
    d_quats[4u * g + 2u] = d_q.z;
    d_quats[4u * g + 3u] = d_q.w;
}
