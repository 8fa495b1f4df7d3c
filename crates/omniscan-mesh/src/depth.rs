//! The depth at which a ray's accumulated opacity reaches one half, taken
//! where the ray meets the Gaussian that crosses it (the point of its
//! greatest density along the ray, as Gaussian Opacity Fields and RaDe-GS
//! define a Gaussian's depth: Yu et al. 2024, Sec. 4; Zhang et al. 2024,
//! Sec. 4), not at the Gaussian's centre as the splat renderer's median
//! depth is. A ray crossing a flat splat off its centre meets it in its
//! plane; the centre's depth is off by the offset times the slope, and since
//! the nearer centres cross one half first, every oblique surface came out
//! about half a splat's size towards the camera (0.25 mm outwards on a box
//! of 0.5 mm splats).

use omniscan_splat::raster::{Camera, Gaussians, Projected, quat_to_rotmat};

/// The per-pixel median surface depth (camera z, metres; 0 where the
/// opacity never reaches one half), compositing in the renderer's order
/// (front to back by centre depth) with its footprints and opacities.
pub fn median_surface_depth(
    g: &Gaussians<f32>,
    camera: &Camera<f32>,
    p: &Projected<f32>,
) -> Vec<f32> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut transmittance = vec![1.0f32; w * h];
    let mut depth = vec![0.0f32; w * h];
    let mut order: Vec<usize> = (0..g.means.len()).filter(|&i| p.visible(i)).collect();
    order.sort_by(|&a, &b| p.depths[a].total_cmp(&p.depths[b]).then(a.cmp(&b)));
    let v = camera.viewmat.map(|r| r.map(f64::from));
    for i in order {
        let (mu, a) = camera_space(g, &v, i);
        let [mx, my] = p.means2d[i];
        let [rx, ry] = p.radii[i];
        let x0 = ((mx - rx as f32).floor().max(0.0) as usize).min(w);
        let x1 = ((mx + rx as f32).ceil().max(0.0) as usize).min(w);
        let y0 = ((my - ry as f32).floor().max(0.0) as usize).min(h);
        let y1 = ((my + ry as f32).ceil().max(0.0) as usize).min(h);
        let [ca, cb, cc] = p.conics[i];
        let opacity = p.opacities[i];
        for y in y0..y1 {
            for x in x0..x1 {
                let k = y * w + x;
                if transmittance[k] <= 0.5 {
                    continue;
                }
                let (dx, dy) = (mx - (x as f32 + 0.5), my - (y as f32 + 0.5));
                let sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy;
                let alpha = (opacity * (-sigma).exp()).min(0.999);
                if sigma < 0.0 || alpha < 1.0 / 255.0 {
                    continue;
                }
                let next = transmittance[k] * (1.0 - alpha);
                if next <= 0.5 {
                    let ray = [
                        (x as f64 + 0.5 - camera.cx as f64) / camera.fx as f64,
                        (y as f64 + 0.5 - camera.cy as f64) / camera.fy as f64,
                        1.0,
                    ];
                    depth[k] = densest_depth(mu, &a, ray).unwrap_or(p.depths[i]);
                }
                transmittance[k] = next;
            }
        }
    }
    depth
}

/// Gaussian `i`'s mean and inverse covariance in camera space.
fn camera_space(g: &Gaussians<f32>, v: &[[f64; 4]; 4], i: usize) -> ([f64; 3], [[f64; 3]; 3]) {
    let r = quat_to_rotmat(g.quats[i].map(f64::from));
    let inv_s2 = g.scales[i].map(|s| 1.0 / (s as f64 * s as f64).max(1e-30));
    // Σ⁻¹ in the world: R S⁻² Rᵀ; in the camera: V Σ⁻¹ Vᵀ.
    let world: [[f64; 3]; 3] = std::array::from_fn(|a| {
        std::array::from_fn(|b| (0..3).map(|k| r[a][k] * inv_s2[k] * r[b][k]).sum())
    });
    let cam: [[f64; 3]; 3] = std::array::from_fn(|a| {
        std::array::from_fn(|b| {
            (0..3)
                .map(|k| (0..3).map(|l| v[a][k] * world[k][l] * v[b][l]).sum::<f64>())
                .sum()
        })
    });
    let m = g.means[i].map(f64::from);
    let mu = std::array::from_fn(|a| (0..3).map(|k| v[a][k] * m[k]).sum::<f64>() + v[a][3]);
    (mu, cam)
}

/// The z (ray parameter, the ray's z being 1) of the densest point of the
/// Gaussian (mean `mu`, inverse covariance `a`) along `ray`.
fn densest_depth(mu: [f64; 3], a: &[[f64; 3]; 3], ray: [f64; 3]) -> Option<f32> {
    let ad: [f64; 3] = std::array::from_fn(|r| (0..3).map(|k| a[r][k] * ray[k]).sum());
    let den: f64 = (0..3).map(|k| ray[k] * ad[k]).sum();
    let num: f64 = (0..3).map(|k| mu[k] * ad[k]).sum();
    let t = num / den;
    (den > 0.0 && t.is_finite() && t > 0.0).then_some(t as f32)
}
