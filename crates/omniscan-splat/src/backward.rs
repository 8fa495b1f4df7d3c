//! Analytic gradients of the CPU reference rasterizer (the backward pass of
//! `raster`), from per-pixel gradients of colour and alpha down to every
//! Gaussian parameter, through the same steps in reverse:
//!
//! - compositing, per pixel from the last contributor to the first, with the
//!   colour accumulated behind each Gaussian (alpha clamped at 0.999 passes
//!   no gradient, as in gsplat);
//! - the Gaussian falloff to the 2D mean, conic and view opacity;
//! - the inverse 2D covariance, the EWA Jacobian (with its clamp just
//!   outside the view), the view rotation, the 3D covariance R·S·Sᵀ·Rᵀ, the
//!   quaternion normalisation, the activations exp and sigmoid;
//! - spherical harmonics, including the view direction's dependence on the mean.
//!
//! Each 4x4-pixel sub-tile replays the forward pass's compositing with the
//! forward pass's culling, all 16 pixels at once, to learn which Gaussians
//! each pixel composited; the reverse pass then runs pixel by pixel, rather
//! than every pixel replaying its whole tile's list on its own.
//! Per-tile partial sums are added in tile order, so gradients are
//! deterministic. Checked against gsplat's float64 autograd gradients and
//! against finite differences.

use rayon::prelude::*;

use crate::Real;
use crate::raster::{
    Appearance, Camera, Colors, Gaussians, LANES, Mode, Packed, Projected, Settings, SubTileLists,
    SubTiles, TILE, TileBins, ViewGeometry, bin_tiles, composite_lanes, covariance, filled,
    lane_centres, lane_pixel, quat_to_rotmat, rig_direction, sub_tile_lists,
};
use crate::sh;

/// The loss's gradient with respect to a small motion of the camera,
/// `u ↦ u + ω × u + v` on every point `u` in the camera's frame (OpenCV
/// axes): the world-to-camera matrix left-multiplied by a twist. Pose
/// refinement ([`crate::pose`]) carries it to its corrections.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CameraGradient {
    /// dL/dv, per metre.
    pub translation: [f64; 3],
    /// dL/dω, per radian.
    pub rotation: [f64; 3],
}

/// Gradients with respect to the rasterizer's intermediates and the activated parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct Gradients<F> {
    pub means2d: Vec<[F; 2]>,
    /// The per-pixel gradients with respect to the 2D mean, summed in
    /// absolute value (per axis): AbsGS's densification statistic (gsplat's
    /// `absgrad`), which opposite pulls across a splat do not cancel. Zero
    /// where the caller did not ask for it (it costs the training step a
    /// few percent).
    pub means2d_abs: Vec<[F; 2]>,
    pub conics: Vec<[F; 3]>,
    pub opacities_view: Vec<F>,
    /// With respect to the view-dependent colour (after the SH clamp).
    pub colors_view: Vec<[F; 3]>,
    pub means: Vec<[F; 3]>,
    /// With respect to the quaternion as given (not normalised).
    pub quats: Vec<[F; 4]>,
    /// With respect to the activated scales (multiply by the scale for log-scales).
    pub scales: Vec<[F; 3]>,
    /// With respect to the activated opacities.
    pub opacities: Vec<F>,
    /// With respect to the colours: RGB, or SH coefficients (basis index major).
    pub colors: Vec<[F; 3]>,
}

impl<F: Real> Gradients<F> {
    /// Gradients with respect to log-scales: dL/ds · s.
    pub fn log_scales(&self, g: &Gaussians<F>) -> Vec<[F; 3]> {
        self.scales
            .par_iter()
            .zip(&g.scales)
            .map(|(d, s)| [d[0] * s[0], d[1] * s[1], d[2] * s[2]])
            .collect()
    }
    /// Gradients with respect to opacity logits: dL/do · o(1 − o).
    pub fn opacity_logits(&self, g: &Gaussians<F>) -> Vec<F> {
        self.opacities
            .par_iter()
            .zip(&g.opacities)
            .map(|(d, &o)| *d * o * (F::one() - o))
            .collect()
    }
}

/// Each lane's (pixel's) contributors: index in the sub-tile's list, alpha,
/// e^(−σ), the transmittance in front, and whether alpha was clamped (which
/// passes no gradient).
type LaneContributors<F> = [Vec<(u32, F, F, F, bool)>; LANES];

/// A per-tile accumulator: (Gaussian, d mean2d, d conic, d opacity_view,
/// d colour, |d mean2d| summed per pixel).
type TileGrad<F> = (u32, [F; 2], [F; 3], F, [F; 3], [F; 2]);
type TileGrads<F> = Vec<TileGrad<F>>;

/// The Gaussians' index range is cut into this many buckets, each summed on
/// its own thread. A Gaussian is in one bucket and at most once per tile,
/// so its sum still runs over the tiles in order: the same gradients to the
/// bit as one serial sum, which took 8 s of a 3000-step DTU run's backward
/// pass on one thread while the others waited.
const MERGE_BUCKETS: usize = 32;

/// What a thread's tiles reuse in the backward pass, so that lists grown
/// on one tile are not allocated and grown again on the next: the tile's
/// partial gradients, its Gaussians as the compositing reads them (with
/// their slots in the tile's list), the sub-tiles' lists and each lane's
/// contributions.
struct TileScratch<F> {
    acc: TileGrads<F>,
    gathered: Vec<(Packed<F>, u32)>,
    dealt: SubTileLists<(Packed<F>, u32)>,
    contributors: LaneContributors<F>,
}

impl<F> Default for TileScratch<F> {
    fn default() -> Self {
        TileScratch {
            acc: Vec::new(),
            gathered: Vec::new(),
            dealt: sub_tile_lists(),
            contributors: std::array::from_fn(|_| Vec::new()),
        }
    }
}

/// A tile's partial gradients ordered by bucket (a counting sort of
/// `acc`), with where each bucket starts; `bucket_of` maps a Gaussian's
/// index to its bucket.
fn by_bucket<F: Copy>(
    acc: &[TileGrad<F>],
    bucket_of: impl Fn(u32) -> usize,
) -> (TileGrads<F>, [u32; MERGE_BUCKETS + 1]) {
    let mut starts = [0u32; MERGE_BUCKETS + 1];
    for e in acc {
        starts[bucket_of(e.0) + 1] += 1;
    }
    for b in 0..MERGE_BUCKETS {
        starts[b + 1] += starts[b];
    }
    let mut next = starts;
    let mut sorted = acc.to_vec();
    for &e in acc {
        let b = bucket_of(e.0);
        sorted[next[b] as usize] = e;
        next[b] += 1;
    }
    (sorted, starts)
}

/// Gradients of L given dL/d(rgb) and dL/d(alpha) per pixel (row-major),
/// [`Gradients::means2d_abs`] included.
pub fn backward<F: Real>(
    g: &Gaussians<F>,
    camera: &Camera<F>,
    settings: &Settings<F>,
    p: &Projected<F>,
    d_rgb: &[[F; 3]],
    d_alpha: &[F],
) -> Gradients<F> {
    let bins = bin_tiles(p, camera.width, camera.height);
    let wanted = Wanted {
        absolute: true,
        camera: false,
    };
    backward_binned(g, camera, settings, p, &bins, d_rgb, d_alpha, wanted).0
}

/// [`backward`], and the gradient with respect to the camera's pose.
pub fn backward_with_camera<F: Real>(
    g: &Gaussians<F>,
    camera: &Camera<F>,
    settings: &Settings<F>,
    p: &Projected<F>,
    d_rgb: &[[F; 3]],
    d_alpha: &[F],
) -> (Gradients<F>, CameraGradient) {
    let bins = bin_tiles(p, camera.width, camera.height);
    let wanted = Wanted {
        absolute: true,
        camera: true,
    };
    backward_binned(g, camera, settings, p, &bins, d_rgb, d_alpha, wanted)
}

/// What a backward pass computes besides the parameters' gradients.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Wanted {
    /// [`Gradients::means2d_abs`] (it costs the training step a few percent).
    pub absolute: bool,
    /// The camera's gradient (zero when not wanted).
    pub camera: bool,
}

/// [`backward_with_camera`] with the forward pass's tile bins, computing
/// what is `wanted`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn backward_binned<F: Real>(
    g: &Gaussians<F>,
    camera: &Camera<F>,
    settings: &Settings<F>,
    p: &Projected<F>,
    bins: &TileBins<F>,
    d_rgb: &[[F; 3]],
    d_alpha: &[F],
    wanted: Wanted,
) -> (Gradients<F>, CameraGradient) {
    let absolute = wanted.absolute;
    let n = g.means.len();
    let (width, height) = (camera.width, camera.height);
    let TileBins { packed, tiles } = bins;
    let tx = width.div_ceil(TILE);
    let bucket_size = n.div_ceil(MERGE_BUCKETS).max(1);
    let bucket_of = |i: u32| i as usize / bucket_size;
    let per_tile: Vec<(TileGrads<F>, [u32; MERGE_BUCKETS + 1])> = (0..tiles.len())
        .into_par_iter()
        .map_init(TileScratch::<F>::default, |scratch, t| {
            let TileScratch {
                acc,
                gathered,
                dealt,
                contributors,
            } = scratch;
            let list = &tiles[t];
            acc.clear();
            acc.extend(list.iter().map(|&i| {
                let zero2 = [F::zero(); 2];
                (i, zero2, [F::zero(); 3], F::zero(), [F::zero(); 3], zero2)
            }));
            let (ox, oy) = ((t as u32 % tx) * TILE, (t as u32 / tx) * TILE);
            // The forward pass's packing and sub-tile culling, so each pixel
            // meets exactly the Gaussians it composited, read from contiguous
            // memory; each keeps its slot in the tile's list.
            gathered.clear();
            gathered.extend(
                (list.iter().enumerate()).map(|(slot, &g)| (packed[g as usize], slot as u32)),
            );
            let sub_tiles =
                SubTiles::deal(gathered, |(g, _)| g.5, (ox, oy), (width, height), dealt);
            for (q, local) in dealt.iter().enumerate() {
                let Some(pixels) = sub_tiles.pixels(q) else {
                    continue;
                };
                let (x0, x1, y0, y1) = pixels;
                let (centres_x, centres_y) = lane_centres::<F>(x0, y0);
                contributors.iter_mut().for_each(Vec::clear);
                let t_final = composite_lanes(
                    local,
                    |(g, _)| g,
                    pixels,
                    |k, index, share| {
                        contributors[k].push((
                            index as u32,
                            share.alpha,
                            share.vis,
                            share.transmittance,
                            share.clamped,
                        ));
                    },
                );
                for (k, lane) in contributors.iter().enumerate() {
                    let (px, py) = lane_pixel(x0, y0, k);
                    if px >= x1 || py >= y1 {
                        continue;
                    }
                    let (fx, fy) = (centres_x[k], centres_y[k]);
                    let pix = (py * width + px) as usize;
                    let dc = d_rgb[pix];
                    let da = d_alpha[pix];
                    let t_final = t_final[k];
                    let mut behind = settings.background.map(|bg| bg * t_final);
                    for &(index, alpha, vis, t_i, clamped) in lane.iter().rev() {
                        let (([mx, my], [a, b, cc], _, c, _, _), slot) = local[index as usize];
                        let entry = &mut acc[slot as usize];
                        let w = alpha * t_i;
                        for ch in 0..3 {
                            entry.4[ch] = entry.4[ch] + w * dc[ch];
                        }
                        let one_minus = F::one() - alpha;
                        let mut d_alpha_i = da * t_final / one_minus;
                        for ch in 0..3 {
                            d_alpha_i = d_alpha_i + dc[ch] * (c[ch] * t_i - behind[ch] / one_minus);
                            behind[ch] = behind[ch] + c[ch] * w;
                        }
                        if clamped {
                            continue;
                        }
                        entry.3 = entry.3 + d_alpha_i * vis;
                        let d_sigma = -d_alpha_i * alpha;
                        let (dx, dy) = (mx - fx, my - fy);
                        entry.2[0] = entry.2[0] + d_sigma * F::c(0.5) * dx * dx;
                        entry.2[1] = entry.2[1] + d_sigma * dx * dy;
                        entry.2[2] = entry.2[2] + d_sigma * F::c(0.5) * dy * dy;
                        let d_mean = [d_sigma * (a * dx + b * dy), d_sigma * (b * dx + cc * dy)];
                        for k in 0..2 {
                            entry.1[k] = entry.1[k] + d_mean[k];
                        }
                        if absolute {
                            for k in 0..2 {
                                entry.5[k] = entry.5[k] + d_mean[k].abs();
                            }
                        }
                    }
                }
            }
            by_bucket(acc, bucket_of)
        })
        .collect();

    let mut d_mean2d = filled(n, [F::zero(); 2]);
    let mut d_mean2d_abs = filled(n, [F::zero(); 2]);
    let mut d_conic = filled(n, [F::zero(); 3]);
    let mut d_opacity_view = filled(n, F::zero());
    let mut d_color_view = filled(n, [F::zero(); 3]);
    d_mean2d
        .par_chunks_mut(bucket_size)
        .zip(d_mean2d_abs.par_chunks_mut(bucket_size))
        .zip(d_conic.par_chunks_mut(bucket_size))
        .zip(d_opacity_view.par_chunks_mut(bucket_size))
        .zip(d_color_view.par_chunks_mut(bucket_size))
        .enumerate()
        .for_each(|(b, ((((mean2d, mean2d_abs), conic), opacity), color))| {
            let first = b * bucket_size;
            for (tile_grads, starts) in &per_tile {
                let bucket = &tile_grads[starts[b] as usize..starts[b + 1] as usize];
                for &(i, m, c, o, col, m_abs) in bucket {
                    let i = i as usize - first;
                    for k in 0..2 {
                        mean2d[i][k] = mean2d[i][k] + m[k];
                        mean2d_abs[i][k] = mean2d_abs[i][k] + m_abs[k];
                    }
                    for k in 0..3 {
                        conic[i][k] = conic[i][k] + c[k];
                        color[i][k] = color[i][k] + col[k];
                    }
                    opacity[i] = opacity[i] + o;
                }
            }
        });
    let mut grads = Gradients {
        means2d: d_mean2d,
        means2d_abs: d_mean2d_abs,
        conics: d_conic,
        opacities_view: d_opacity_view,
        colors_view: d_color_view,
        means: filled(n, [F::zero(); 3]),
        quats: filled(n, [F::zero(); 4]),
        scales: filled(n, [F::zero(); 3]),
        opacities: filled(n, F::zero()),
        colors: match &g.colors {
            Colors::Rgb(c) => filled(c.len(), [F::zero(); 3]),
            Colors::Sh { coeffs, .. } => filled(coeffs.len(), [F::zero(); 3]),
        },
    };
    let camera_gradient = project_backward(g, camera, settings, p, &mut grads, wanted.camera);
    (grads, camera_gradient)
}

fn mat3_mul<F: Real>(a: &[[F; 3]; 3], b: &[[F; 3]; 3]) -> [[F; 3]; 3] {
    let mut o = [[F::zero(); 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            o[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    o
}

fn mat3_t<F: Real>(a: &[[F; 3]; 3]) -> [[F; 3]; 3] {
    let mut o = [[F::zero(); 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            o[i][j] = a[j][i];
        }
    }
    o
}

/// The projection's backward pass, per splat; returns the camera's
/// gradient, summed over the splats in index order (the same bits on any
/// number of threads).
fn project_backward<F: Real>(
    g: &Gaussians<F>,
    camera: &Camera<F>,
    settings: &Settings<F>,
    p: &Projected<F>,
    grads: &mut Gradients<F>,
    camera_wanted: bool,
) -> CameraGradient {
    let ViewGeometry {
        rot,
        trans,
        campos,
        lim_x: (lim_x_neg, lim_x_pos),
        lim_y: (lim_y_neg, lim_y_pos),
    } = ViewGeometry::new(camera);
    let (fx, fy) = (camera.fx, camera.fy);
    let two = F::c(2.0);
    let Gradients {
        means2d,
        conics,
        opacities_view,
        colors_view,
        means,
        quats,
        scales,
        opacities,
        colors,
        ..
    } = grads;
    let per_splat = match &g.colors {
        Colors::Rgb(_) => 1,
        Colors::Sh { degree, .. } => sh::coefficients(*degree),
    };
    // Each splat writes only its own entries.
    let outputs = means
        .par_iter_mut()
        .zip(quats.par_iter_mut())
        .zip(scales.par_iter_mut())
        .zip(opacities.par_iter_mut())
        .zip(colors.par_chunks_mut(per_splat));
    let per_splat_camera: Vec<[F; 6]> = outputs
        .enumerate()
        .map(
            |(i, ((((d_mean_out, d_quat_out), d_scale_out), d_opacity_out), d_colors_out))| {
                if !p.visible(i) {
                    return [F::zero(); 6];
                }
                let m = g.means[i];
                let pc = [0, 1, 2]
                    .map(|r| rot[r][0] * m[0] + rot[r][1] * m[1] + rot[r][2] * m[2] + trans[r]);
                let (x, y, z) = (pc[0], pc[1], pc[2]);
                // Opacity (and the antialiasing compensation).
                let d_ov = opacities_view[i];
                let (d_opacity, d_comp) = match settings.mode {
                    Mode::Classic => (d_ov, F::zero()),
                    Mode::Antialiased => (d_ov * p.compensations[i], d_ov * g.opacities[i]),
                };
                *d_opacity_out = d_opacity;
                // Colour: through the clamp, to RGB or SH (and the SH view direction).
                let mut d_pc = [F::zero(); 3];
                let mut d_mean = [F::zero(); 3];
                let mut d_rig_axis = [F::zero(); 3];
                let mut rig_axis = None;
                // A fixed-rig direction turns with the camera: dL/dω = d × dL/dd.
                let mut rig_turn = [F::zero(); 3];
                let r = quat_to_rotmat(g.quats[i]);
                match &g.colors {
                    Colors::Rgb(_) => d_colors_out[0] = colors_view[i],
                    Colors::Sh { degree, coeffs } => {
                        let k = sh::coefficients(*degree);
                        let dvec = [m[0] - campos[0], m[1] - campos[1], m[2] - campos[2]];
                        let len =
                            (dvec[0] * dvec[0] + dvec[1] * dvec[1] + dvec[2] * dvec[2]).sqrt();
                        let rig = match settings.appearance {
                            Appearance::ViewDirection => None,
                            Appearance::FixedRig => Some(rig_direction(&rot, &r, g.scales[i])),
                        };
                        let dir = rig.map_or_else(|| dvec.map(|t| t / len), |rig| rig.0);
                        let raw = sh::evaluate(*degree, dir, &coeffs[i * k..(i + 1) * k]);
                        let d_raw: [F; 3] = [0, 1, 2].map(|ch| {
                            if raw[ch] + F::c(0.5) < F::zero() {
                                F::zero()
                            } else {
                                colors_view[i][ch]
                            }
                        });
                        let basis = sh::basis(*degree, dir);
                        for kk in 0..k {
                            for ch in 0..3 {
                                d_colors_out[kk][ch] = basis[kk] * d_raw[ch];
                            }
                        }
                        let dbasis = sh::basis_gradient(*degree, dir);
                        let mut d_dir = [F::zero(); 3];
                        for kk in 0..k {
                            let s: F = (0..3).map(|ch| coeffs[i * k + kk][ch] * d_raw[ch]).sum();
                            for a in 0..3 {
                                d_dir[a] = d_dir[a] + dbasis[kk][a] * s;
                            }
                        }
                        match rig {
                            // Through the normalisation d = v/|v|.
                            None => {
                                let dot = d_dir[0] * dir[0] + d_dir[1] * dir[1] + d_dir[2] * dir[2];
                                for a in 0..3 {
                                    d_mean[a] = d_mean[a] + (d_dir[a] - dir[a] * dot) / len;
                                }
                            }
                            // d = sign · rot · r[:, axis]: into that column of
                            // the splat's rotation (the axis choice and the sign
                            // are piecewise constant).
                            Some((_, axis, sign)) => {
                                rig_turn = cross(dir, d_dir);
                                for (b, d_rb) in d_rig_axis.iter_mut().enumerate() {
                                    *d_rb = sign * (0..3).map(|a| rot[a][b] * d_dir[a]).sum::<F>();
                                }
                                rig_axis = Some(axis);
                            }
                        }
                    }
                }
                // Recompute the forward quantities this Gaussian needs.
                let cov_w = covariance(&r, g.scales[i]);
                let cov_c = mat3_mul(&mat3_mul(&rot, &cov_w), &mat3_t(&rot));
                let (rx, ry) = (x / z, y / z);
                let clamped_x = rx < -lim_x_neg || rx > lim_x_pos;
                let clamped_y = ry < -lim_y_neg || ry > lim_y_pos;
                let tx = z * rx.max(-lim_x_neg).min(lim_x_pos);
                let ty = z * ry.max(-lim_y_neg).min(lim_y_pos);
                let j = [
                    [fx / z, F::zero(), -fx * tx / (z * z)],
                    [F::zero(), fy / z, -fy * ty / (z * z)],
                ];
                let mut cov2 = [[F::zero(); 2]; 2];
                for r in 0..2 {
                    for c in 0..2 {
                        let mut s = F::zero();
                        for a in 0..3 {
                            for b in 0..3 {
                                s = s + j[r][a] * cov_c[a][b] * j[c][b];
                            }
                        }
                        cov2[r][c] = s;
                    }
                }
                let (a, b, c) = (
                    cov2[0][0] + settings.eps2d,
                    (cov2[0][1] + cov2[1][0]) * F::c(0.5),
                    cov2[1][1] + settings.eps2d,
                );
                let det = a * c - b * b;
                // Conic = inverse of [[a, b], [b, c]]; dL/dCov = −Inv·G·Inv with G symmetric.
                let inv = [[c / det, -b / det], [-b / det, a / det]];
                let dc = conics[i];
                let gm = [[dc[0], dc[1] * F::c(0.5)], [dc[1] * F::c(0.5), dc[2]]];
                let mut d_cov2 = [[F::zero(); 2]; 2];
                for r in 0..2 {
                    for s in 0..2 {
                        let mut acc = F::zero();
                        for u in 0..2 {
                            for t in 0..2 {
                                acc = acc + inv[r][u] * gm[u][t] * inv[t][s];
                            }
                        }
                        d_cov2[r][s] = -acc;
                    }
                }
                if settings.mode == Mode::Antialiased && d_comp != F::zero() {
                    // comp = sqrt(det(cov) / det(cov + εI)); d comp/d cov = comp/2 · (cov⁻¹ − (cov + εI)⁻¹).
                    let det_raw = cov2[0][0] * cov2[1][1] - cov2[0][1] * cov2[1][0];
                    let comp = p.compensations[i];
                    if det_raw > F::zero() && comp > F::zero() {
                        let inv_raw = [
                            [cov2[1][1] / det_raw, -cov2[0][1] / det_raw],
                            [-cov2[1][0] / det_raw, cov2[0][0] / det_raw],
                        ];
                        for r in 0..2 {
                            for s in 0..2 {
                                d_cov2[r][s] = d_cov2[r][s]
                                    + d_comp * comp * F::c(0.5) * (inv_raw[r][s] - inv[r][s]);
                            }
                        }
                    }
                }
                // Mean: means2d = (fx x/z + cx, fy y/z + cy).
                let dm2 = means2d[i];
                d_pc[0] = d_pc[0] + dm2[0] * fx / z;
                d_pc[1] = d_pc[1] + dm2[1] * fy / z;
                d_pc[2] = d_pc[2] - dm2[0] * fx * x / (z * z) - dm2[1] * fy * y / (z * z);
                // cov2 = J Σc Jᵀ: dΣc = Jᵀ G J, dJ = (G + Gᵀ) J Σc.
                let mut d_cov_c = [[F::zero(); 3]; 3];
                for a in 0..3 {
                    for b in 0..3 {
                        let mut s = F::zero();
                        for r in 0..2 {
                            for t in 0..2 {
                                s = s + j[r][a] * d_cov2[r][t] * j[t][b];
                            }
                        }
                        d_cov_c[a][b] = s;
                    }
                }
                let mut d_j = [[F::zero(); 3]; 2];
                for r in 0..2 {
                    for a in 0..3 {
                        let mut s = F::zero();
                        for t in 0..2 {
                            for b in 0..3 {
                                s = s + (d_cov2[r][t] + d_cov2[t][r]) * j[t][b] * cov_c[b][a];
                            }
                        }
                        d_j[r][a] = s;
                    }
                }
                // J's dependence on the camera-space mean (the clamp freezes x/z or y/z).
                let z2 = z * z;
                let z3 = z2 * z;
                d_pc[2] = d_pc[2] - d_j[0][0] * fx / z2 - d_j[1][1] * fy / z2;
                if clamped_x {
                    d_pc[2] = d_pc[2] + d_j[0][2] * fx * (tx / z) / z2;
                } else {
                    d_pc[0] = d_pc[0] - d_j[0][2] * fx / z2;
                    d_pc[2] = d_pc[2] + d_j[0][2] * two * fx * tx / z3;
                }
                if clamped_y {
                    d_pc[2] = d_pc[2] + d_j[1][2] * fy * (ty / z) / z2;
                } else {
                    d_pc[1] = d_pc[1] - d_j[1][2] * fy / z2;
                    d_pc[2] = d_pc[2] + d_j[1][2] * two * fy * ty / z3;
                }
                let camera_part = if camera_wanted {
                    camera_contribution(&rot, pc, d_pc, d_mean, &cov_c, &d_cov_c, rig_turn)
                } else {
                    [F::zero(); 6]
                };
                // Camera to world: mean through Rᵀ, covariance as Rᵀ dΣc R.
                for a in 0..3 {
                    d_mean[a] =
                        d_mean[a] + rot[0][a] * d_pc[0] + rot[1][a] * d_pc[1] + rot[2][a] * d_pc[2];
                }
                *d_mean_out = d_mean;
                let d_cov_w = mat3_mul(&mat3_mul(&mat3_t(&rot), &d_cov_c), &rot);
                // Σ = M Mᵀ, M = R S.
                let s = g.scales[i];
                let mut mm = r;
                for row in &mut mm {
                    for (jj, val) in row.iter_mut().enumerate() {
                        *val = *val * s[jj];
                    }
                }
                let sym = {
                    let mut o = [[F::zero(); 3]; 3];
                    for a in 0..3 {
                        for b in 0..3 {
                            o[a][b] = d_cov_w[a][b] + d_cov_w[b][a];
                        }
                    }
                    o
                };
                let d_m = mat3_mul(&sym, &mm);
                let mut d_r = [[F::zero(); 3]; 3];
                for a in 0..3 {
                    for b in 0..3 {
                        d_r[a][b] = d_m[a][b] * s[b];
                        d_scale_out[b] = d_scale_out[b] + d_m[a][b] * r[a][b];
                    }
                }
                if let Some(axis) = rig_axis {
                    for (row, d) in d_r.iter_mut().zip(d_rig_axis) {
                        row[axis] = row[axis] + d;
                    }
                }
                // Rotation matrix to the normalised quaternion, then through the normalisation.
                let q = g.quats[i];
                let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
                let [qw, qx, qy, qz] = q.map(|t| t / norm);
                let gq = d_r;
                let d_hat = [
                    two * (-qz * gq[0][1] + qy * gq[0][2] + qz * gq[1][0]
                        - qx * gq[1][2]
                        - qy * gq[2][0]
                        + qx * gq[2][1]),
                    two * (qy * gq[0][1] + qz * gq[0][2] + qy * gq[1][0]
                        - two * qx * gq[1][1]
                        - qw * gq[1][2]
                        + qz * gq[2][0]
                        + qw * gq[2][1]
                        - two * qx * gq[2][2]),
                    two * (-two * qy * gq[0][0]
                        + qx * gq[0][1]
                        + qw * gq[0][2]
                        + qx * gq[1][0]
                        + qz * gq[1][2]
                        - qw * gq[2][0]
                        + qz * gq[2][1]
                        - two * qy * gq[2][2]),
                    two * (-two * qz * gq[0][0] - qw * gq[0][1] + qx * gq[0][2] + qw * gq[1][0]
                        - two * qz * gq[1][1]
                        + qy * gq[1][2]
                        + qx * gq[2][0]
                        + qy * gq[2][1]),
                ];
                let hat = [qw, qx, qy, qz];
                let dot = (0..4).map(|k| d_hat[k] * hat[k]).sum::<F>();
                *d_quat_out = [0, 1, 2, 3].map(|k| (d_hat[k] - hat[k] * dot) / norm);
                camera_part
            },
        )
        .collect();
    let mut total = CameraGradient::default();
    for part in per_splat_camera {
        for a in 0..3 {
            total.translation[a] += part[a].to_f64().unwrap_or(f64::NAN);
            total.rotation[a] += part[3 + a].to_f64().unwrap_or(f64::NAN);
        }
    }
    total
}

fn cross<F: Real>(a: [F; 3], b: [F; 3]) -> [F; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// One splat's share of the camera's gradient ([`CameraGradient`], as
/// translation then rotation). A camera-frame motion moves the splat's
/// camera-frame mean `pc` (gradient `d_pc`) and, for a translation, the
/// view direction as the world mean would (`d_view_dir`, the world-frame
/// gradient the SH put on the mean); a rotation turns the camera-frame
/// covariance, dΣc = ω̂Σc − Σcω̂, and a fixed-rig direction (`rig_turn`).
fn camera_contribution<F: Real>(
    rot: &[[F; 3]; 3],
    pc: [F; 3],
    d_pc: [F; 3],
    d_view_dir: [F; 3],
    cov_c: &[[F; 3]; 3],
    d_cov_c: &[[F; 3]; 3],
    rig_turn: [F; 3],
) -> [F; 6] {
    let translation =
        [0, 1, 2].map(|a| d_pc[a] + (0..3).map(|b| rot[a][b] * d_view_dir[b]).sum::<F>());
    // dL = tr(Gᵀ(ω̂Σ − Σω̂)) = tr(Aω̂) with A = ΣGᵀ − GᵀΣ.
    let g_t = mat3_t(d_cov_c);
    let (sg, gs) = (mat3_mul(cov_c, &g_t), mat3_mul(&g_t, cov_c));
    let a = |r: usize, c: usize| sg[r][c] - gs[r][c];
    let turn = cross(pc, d_pc);
    let covariance_turn = [a(1, 2) - a(2, 1), a(2, 0) - a(0, 2), a(0, 1) - a(1, 0)];
    let rotation = [0, 1, 2].map(|k| turn[k] + covariance_turn[k] + rig_turn[k]);
    [
        translation[0],
        translation[1],
        translation[2],
        rotation[0],
        rotation[1],
        rotation[2],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::{Colors, Mode, render};
    use crate::test_support::Lcg;

    /// A scene with its camera, settings and the loss weights for colour and alpha.
    type Scene = (
        Gaussians<f64>,
        Camera<f64>,
        Settings<f64>,
        Vec<[f64; 3]>,
        Vec<f64>,
    );

    fn scene(mode: Mode, sh_degree: Option<usize>, appearance: Appearance) -> Scene {
        scene_of(12, 1, mode, sh_degree, appearance)
    }

    /// `n` Gaussians seen by an image `zoom` times the base 24x20 (same
    /// field of view).
    fn scene_of(
        n: usize,
        zoom: u32,
        mode: Mode,
        sh_degree: Option<usize>,
        appearance: Appearance,
    ) -> Scene {
        let mut r = Lcg(7);
        let mut g = Gaussians {
            means: (0..n)
                .map(|_| [r.next() - 0.5, r.next() - 0.5, 2.0 + r.next()])
                .collect(),
            scales: (0..n)
                .map(|_| {
                    [
                        0.05 + 0.1 * r.next(),
                        0.05 + 0.1 * r.next(),
                        0.05 + 0.1 * r.next(),
                    ]
                })
                .collect(),
            quats: (0..n)
                .map(|_| {
                    [
                        r.next() + 0.2,
                        r.next() - 0.5,
                        r.next() - 0.5,
                        r.next() - 0.5,
                    ]
                })
                .collect(),
            opacities: (0..n).map(|_| 0.2 + 0.7 * r.next()).collect(),
            colors: Colors::Rgb((0..n).map(|_| [r.next(), r.next(), r.next()]).collect()),
        };
        if let Some(d) = sh_degree {
            let k = crate::sh::coefficients(d);
            g.colors = Colors::Sh {
                degree: d,
                coeffs: (0..n * k)
                    .map(|_| [r.next() - 0.5, r.next() - 0.5, r.next() - 0.5])
                    .collect(),
            };
        }
        let camera = Camera {
            viewmat: [
                [1.0, 0.0, 0.0, 0.05],
                [0.0, 0.96, -0.28, 0.1],
                [0.0, 0.28, 0.96, 0.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
            fx: 30.0 * zoom as f64,
            fy: 28.0 * zoom as f64,
            cx: 12.3 * zoom as f64,
            cy: 9.7 * zoom as f64,
            width: 24 * zoom,
            height: 20 * zoom,
            near: 0.01,
            far: 100.0,
        };
        let settings = Settings {
            eps2d: 0.3,
            mode,
            background: [0.1, 0.2, 0.3],
            appearance,
        };
        let px = (camera.width * camera.height) as usize;
        let w_rgb = (0..px)
            .map(|_| {
                [
                    r.next() * 2.0 - 1.0,
                    r.next() * 2.0 - 1.0,
                    r.next() * 2.0 - 1.0,
                ]
            })
            .collect();
        let w_a = (0..px).map(|_| r.next() * 2.0 - 1.0).collect();
        (g, camera, settings, w_rgb, w_a)
    }

    fn loss(
        g: &Gaussians<f64>,
        camera: &Camera<f64>,
        settings: &Settings<f64>,
        w_rgb: &[[f64; 3]],
        w_a: &[f64],
    ) -> f64 {
        let (_, r) = render(g, camera, settings);
        let mut l = 0.0;
        for i in 0..w_a.len() {
            l += w_a[i] * r.alpha[i];
            for ch in 0..3 {
                l += w_rgb[i][ch] * r.rgb[i][ch];
            }
        }
        l
    }

    /// The loss's central difference under `edit(g, ±h)`, h = 1e-6.
    fn central_difference(
        g: &Gaussians<f64>,
        camera: &Camera<f64>,
        settings: &Settings<f64>,
        w_rgb: &[[f64; 3]],
        w_a: &[f64],
        edit: &dyn Fn(&mut Gaussians<f64>, f64),
    ) -> f64 {
        let h = 1e-6;
        let mut plus = g.clone();
        edit(&mut plus, h);
        let mut minus = g.clone();
        edit(&mut minus, -h);
        (loss(&plus, camera, settings, w_rgb, w_a) - loss(&minus, camera, settings, w_rgb, w_a))
            / (2.0 * h)
    }

    /// The camera moved by `u ↦ u + ω × u + v` to first order: its
    /// world-to-camera matrix left-multiplied by the exact rigid motion
    /// (Rodrigues' rotation by ω, then v).
    fn moved_camera(camera: &Camera<f64>, v: [f64; 3], w: [f64; 3]) -> Camera<f64> {
        let motion =
            nalgebra::Isometry3::new(nalgebra::Vector3::from(v), nalgebra::Vector3::from(w));
        let m = motion.to_homogeneous() * nalgebra::Matrix4::from_fn(|r, c| camera.viewmat[r][c]);
        Camera {
            viewmat: std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)])),
            ..*camera
        }
    }

    #[test]
    fn camera_gradient_agrees_with_central_differences() {
        for (mode, sh_degree, appearance) in [
            (Mode::Classic, None, Appearance::ViewDirection),
            (Mode::Antialiased, Some(2), Appearance::ViewDirection),
            (Mode::Classic, Some(3), Appearance::FixedRig),
        ] {
            let (g, camera, settings, w_rgb, w_a) = scene(mode, sh_degree, appearance);
            let (p, _) = render(&g, &camera, &settings);
            let (_, analytic) = backward_with_camera(&g, &camera, &settings, &p, &w_rgb, &w_a);
            let h = 1e-6;
            for k in 0..6 {
                let step = |e: f64| {
                    let mut twist = [0.0; 6];
                    twist[k] = e;
                    let moved = moved_camera(
                        &camera,
                        [twist[0], twist[1], twist[2]],
                        [twist[3], twist[4], twist[5]],
                    );
                    loss(&g, &moved, &settings, &w_rgb, &w_a)
                };
                let numeric = (step(h) - step(-h)) / (2.0 * h);
                let value = match k {
                    0..3 => analytic.translation[k],
                    _ => analytic.rotation[k - 3],
                };
                assert!(
                    (value - numeric).abs() <= 1e-4 * (1.0 + numeric.abs()),
                    "{mode:?} {appearance:?} camera twist {k}: analytic {value} vs numeric {numeric}"
                );
                assert!(
                    numeric.abs() > 1e-3,
                    "twist {k} moves the loss in this scene"
                );
            }
        }
    }

    #[test]
    fn gradients_agree_with_central_differences() {
        for (mode, sh_degree, appearance) in [
            (Mode::Classic, None, Appearance::ViewDirection),
            (Mode::Antialiased, Some(2), Appearance::ViewDirection),
            // The colour depends on the rotation through the splat's normal.
            (Mode::Classic, Some(3), Appearance::FixedRig),
        ] {
            let (g, camera, settings, w_rgb, w_a) = scene(mode, sh_degree, appearance);
            let (p, _) = render(&g, &camera, &settings);
            let grads = backward(&g, &camera, &settings, &p, &w_rgb, &w_a);
            let numeric = |edit: &dyn Fn(&mut Gaussians<f64>, f64)| {
                central_difference(&g, &camera, &settings, &w_rgb, &w_a, edit)
            };
            let compare = |name: &str, analytic: f64, fd: f64| {
                assert!(
                    (analytic - fd).abs() <= 1e-4 * (1.0 + fd.abs()),
                    "{mode:?} {appearance:?} {name}: analytic {analytic} vs numeric {fd}"
                );
            };
            for i in 0..g.means.len() {
                for a in 0..3 {
                    compare(
                        &format!("mean[{i}][{a}]"),
                        grads.means[i][a],
                        numeric(&|g, e| g.means[i][a] += e),
                    );
                    compare(
                        &format!("scale[{i}][{a}]"),
                        grads.scales[i][a],
                        numeric(&|g, e| g.scales[i][a] += e),
                    );
                }
                for a in 0..4 {
                    compare(
                        &format!("quat[{i}][{a}]"),
                        grads.quats[i][a],
                        numeric(&|g, e| g.quats[i][a] += e),
                    );
                }
                compare(
                    &format!("opacity[{i}]"),
                    grads.opacities[i],
                    numeric(&|g, e| g.opacities[i] += e),
                );
            }
            let colors = grads.colors.len();
            for c in (0..colors).step_by(3) {
                compare(
                    &format!("colour[{c}]"),
                    grads.colors[c][1],
                    numeric(&|g, e| match &mut g.colors {
                        Colors::Rgb(v) => v[c][1] += e,
                        Colors::Sh { coeffs, .. } => coeffs[c][1] += e,
                    }),
                );
            }
        }
    }

    /// With more Gaussians than merge buckets, each bucket sums several
    /// Gaussians' partials from several tiles: a wrong bucket boundary or
    /// offset would give another Gaussian's gradient.
    #[test]
    fn gradients_merged_by_bucket_agree_with_central_differences() {
        let (g, camera, settings, w_rgb, w_a) =
            scene_of(150, 3, Mode::Classic, None, Appearance::ViewDirection);
        assert!(g.means.len() > 4 * MERGE_BUCKETS);
        let (p, _) = render(&g, &camera, &settings);
        assert!(camera.width.div_ceil(TILE) * camera.height.div_ceil(TILE) >= 16);
        let grads = backward(&g, &camera, &settings, &p, &w_rgb, &w_a);
        let mut checked = 0;
        // Each bucket's first and last Gaussians, and one inside.
        let bucket = g.means.len().div_ceil(MERGE_BUCKETS);
        for b in 0..MERGE_BUCKETS {
            for i in [b * bucket, b * bucket + 2, (b + 1) * bucket - 1] {
                if i >= g.means.len() || !p.visible(i) {
                    continue;
                }
                let numeric = |edit: &dyn Fn(&mut Gaussians<f64>, f64)| {
                    central_difference(&g, &camera, &settings, &w_rgb, &w_a, edit)
                };
                for (name, analytic, fd) in [
                    (
                        "opacity",
                        grads.opacities[i],
                        numeric(&|g, e| g.opacities[i] += e),
                    ),
                    (
                        "mean x",
                        grads.means[i][0],
                        numeric(&|g, e| g.means[i][0] += e),
                    ),
                ] {
                    assert!(
                        (analytic - fd).abs() <= 1e-4 * (1.0 + fd.abs()),
                        "Gaussian {i} {name}: analytic {analytic} vs numeric {fd}"
                    );
                }
                checked += 1;
            }
        }
        assert!(checked > 40, "only {checked} Gaussians were visible");
    }

    /// AbsGS's statistic is the sum over pixels of each pixel's own 2D mean
    /// gradient in absolute value: the backward pass of a loss on one pixel
    /// alone gives that pixel's, for every pixel in turn.
    #[test]
    fn absolute_mean2d_gradients_sum_each_pixels_own() {
        let (g, camera, settings, w_rgb, w_a) =
            scene(Mode::Classic, Some(1), Appearance::ViewDirection);
        let (p, _) = render(&g, &camera, &settings);
        let all = backward(&g, &camera, &settings, &p, &w_rgb, &w_a);
        let mut summed = vec![[0.0; 2]; g.means.len()];
        for pixel in 0..w_a.len() {
            let mut one_rgb = vec![[0.0; 3]; w_a.len()];
            let mut one_alpha = vec![0.0; w_a.len()];
            one_rgb[pixel] = w_rgb[pixel];
            one_alpha[pixel] = w_a[pixel];
            let single = backward(&g, &camera, &settings, &p, &one_rgb, &one_alpha);
            for (sum, d) in summed.iter_mut().zip(&single.means2d) {
                sum[0] += d[0].abs();
                sum[1] += d[1].abs();
            }
        }
        let mut cancelled = false;
        for i in 0..g.means.len() {
            for a in 0..2 {
                let (got, want) = (all.means2d_abs[i][a], summed[i][a]);
                assert!(
                    (got - want).abs() <= 1e-9 * (1.0 + want),
                    "splat {i} axis {a}: {got} against {want}"
                );
                assert!(got + 1e-12 >= all.means2d[i][a].abs());
                cancelled |= got > 2.0 * all.means2d[i][a].abs() + 1e-9;
            }
        }
        assert!(cancelled, "some splat's pulls cancel in the plain sum");
    }
}
