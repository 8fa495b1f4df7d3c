//! CPU reference rasterizer, forward pass, in gsplat's conventions (see the
//! crate docs): project every Gaussian (EWA with the Jacobian's clamp just
//! outside the view, +0.3 px low-pass, optional antialiasing compensation),
//! bin by 16x16 tiles, sort each tile by depth, composite front to back.
//! Generic over f32/f64; tiles run in parallel and each pixel's sum is taken
//! in a fixed order, so results are deterministic.

use rayon::prelude::*;

use crate::Real;
use crate::sh;

/// Activated Gaussian parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct Gaussians<F> {
    pub means: Vec<[F; 3]>,
    /// exp(log-scale).
    pub scales: Vec<[F; 3]>,
    /// (w, x, y, z); normalised inside the projection.
    pub quats: Vec<[F; 4]>,
    /// sigmoid(logit).
    pub opacities: Vec<F>,
    pub colors: Colors<F>,
}

/// Per-Gaussian colour: plain RGB, or SH coefficients evaluated towards the camera.
#[derive(Debug, Clone, PartialEq)]
pub enum Colors<F> {
    Rgb(Vec<[F; 3]>),
    /// `(degree+1)²` RGB triples per Gaussian, basis index major.
    Sh {
        degree: usize,
        coeffs: Vec<[F; 3]>,
    },
}

/// A pinhole camera: world-to-camera matrix (OpenCV axes) and intrinsics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera<F> {
    pub viewmat: [[F; 4]; 4],
    pub fx: F,
    pub fy: F,
    pub cx: F,
    pub cy: F,
    pub width: u32,
    pub height: u32,
    pub near: F,
    pub far: F,
}

/// The world position of the camera whose world-to-camera matrix is
/// `viewmat`: −Rᵀt.
pub fn viewmat_centre<F: Real>(viewmat: &[[F; 4]; 4]) -> [F; 3] {
    let v = viewmat;
    [0, 1, 2].map(|j| -(v[0][j] * v[0][3] + v[1][j] * v[1][3] + v[2][j] * v[2][3]))
}

impl<F: Real> Camera<F> {
    /// The camera's position in the world.
    pub fn centre(&self) -> [F; 3] {
        viewmat_centre(&self.viewmat)
    }

    /// A camera at `camera_to_world` (OpenCV axes) with the given intrinsics.
    pub fn from_pose(
        camera_to_world: &omniscan_core::Pose,
        k: &omniscan_core::Intrinsics,
    ) -> Camera<F> {
        let v = camera_to_world.inverse().to_homogeneous();
        let mut viewmat = [[F::zero(); 4]; 4];
        for (r, row) in viewmat.iter_mut().enumerate() {
            for (c, x) in row.iter_mut().enumerate() {
                *x = F::c(v[(r, c)]);
            }
        }
        Camera {
            viewmat,
            fx: F::c(k.fx),
            fy: F::c(k.fy),
            cx: F::c(k.cx),
            cy: F::c(k.cy),
            width: k.width,
            height: k.height,
            near: F::c(0.01),
            far: F::c(100.0),
        }
    }
}

/// What projection needs of a camera: the view rotation and translation,
/// the camera centre (for SH view directions) and the limits of x/z and y/z
/// at which the EWA Jacobian is clamped (30% beyond the image, as gsplat).
pub(crate) struct ViewGeometry<F> {
    pub rot: [[F; 3]; 3],
    pub trans: [F; 3],
    pub campos: [F; 3],
    pub lim_x: (F, F),
    pub lim_y: (F, F),
}

impl<F: Real> ViewGeometry<F> {
    pub fn new(camera: &Camera<F>) -> ViewGeometry<F> {
        let v = &camera.viewmat;
        let rot = [
            [v[0][0], v[0][1], v[0][2]],
            [v[1][0], v[1][1], v[1][2]],
            [v[2][0], v[2][1], v[2][2]],
        ];
        let trans = [v[0][3], v[1][3], v[2][3]];
        let campos = camera.centre();
        let (w, h) = (F::c(camera.width as f64), F::c(camera.height as f64));
        let tan_x = F::c(0.5) * w / camera.fx;
        let tan_y = F::c(0.5) * h / camera.fy;
        ViewGeometry {
            rot,
            trans,
            campos,
            lim_x: (
                camera.cx / camera.fx + F::c(0.3) * tan_x,
                (w - camera.cx) / camera.fx + F::c(0.3) * tan_x,
            ),
            lim_y: (
                camera.cy / camera.fy + F::c(0.3) * tan_y,
                (h - camera.cy) / camera.fy + F::c(0.3) * tan_y,
            ),
        }
    }
}

/// How the 2D footprint is low-pass filtered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Add 0.3 px² to the 2D covariance (original 3DGS).
    Classic,
    /// Also scale opacity by the determinant ratio (Mip-Splatting's 2D filter).
    Antialiased,
}

/// What a splat's spherical harmonics are a function of.
///
/// 3DGS assumes the lights are fixed to the object, so a splat's colour
/// depends on where it is seen from: its SH are evaluated at the viewing
/// direction in the model's frame. In the paper's scan the camera and the
/// lights are fixed and the object turns in the gripper, so a surface
/// element's colour depends on how its normal faces that rig: for an
/// isotropic surface under distant lights, on the normal in the camera's
/// frame alone. One arm's scan shows each viewing direction in one roll
/// only, so the viewing direction serves there; the two arms' scans show the
/// same direction rolled differently under the same lights, and a merged
/// model evaluated by viewing direction cannot fit both. On a simulated
/// flashlight (320x240, 3000 steps, merged by the true transform) it fell
/// 3.2 dB below the left arm's own model on the left arm's views, 9.7 dB on
/// the worst; with [`Appearance::FixedRig`], 0.6 and 3.6 dB, and its
/// held-out masked PSNR rose from 27.5 to 28.7 dB. Under ambient light
/// alone the gap was 0.5 dB by viewing direction: it is the lights.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Appearance {
    /// SH at the direction from the camera to the splat, in the model's
    /// frame (3DGS, gsplat and every viewer).
    #[default]
    ViewDirection,
    /// SH at the splat's normal (its shortest axis, turned to face the
    /// camera) in the camera's frame: camera and lights fixed, the object
    /// moving.
    FixedRig,
}

impl Appearance {
    /// The name files, reports and the command line use.
    pub fn name(self) -> &'static str {
        match self {
            Appearance::ViewDirection => "view-direction",
            Appearance::FixedRig => "fixed-rig",
        }
    }

    /// The appearance called `name` (see [`Appearance::name`]).
    pub fn from_name(name: &str) -> Option<Appearance> {
        [Appearance::ViewDirection, Appearance::FixedRig]
            .into_iter()
            .find(|a| a.name() == name)
    }
}

/// Rendering settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settings<F> {
    pub eps2d: F,
    pub mode: Mode,
    pub background: [F; 3],
    pub appearance: Appearance,
}

impl<F: Real> Default for Settings<F> {
    fn default() -> Self {
        Settings {
            eps2d: F::c(0.3),
            mode: Mode::Classic,
            background: [F::zero(); 3],
            appearance: Appearance::ViewDirection,
        }
    }
}

pub const TILE: u32 = 16;
pub(crate) const ALPHA_MAX: f64 = 0.999;
pub(crate) const ALPHA_MIN: f64 = 1.0 / 255.0;
/// Opacities are at most 1, so past this exponent alpha < 1/255 whatever the
/// opacity (e^-5.55 < 1/255): the pixel is skipped without evaluating the
/// exponential, whose underflow path is slow for the far tails.
pub(crate) const SIGMA_SKIP: f64 = 5.55;
pub(crate) const T_STOP: f64 = 1e-4;
const RADIUS_SIGMA: f64 = 3.33;

/// Projection of every Gaussian; invisible ones have zero radii.
#[derive(Debug, Clone, PartialEq)]
pub struct Projected<F> {
    pub means2d: Vec<[F; 2]>,
    pub depths: Vec<F>,
    /// Upper triangle of the inverse 2D covariance: (a, b, c).
    pub conics: Vec<[F; 3]>,
    pub radii: Vec<[i32; 2]>,
    pub compensations: Vec<F>,
    /// Opacity used for compositing (compensated in antialiased mode).
    pub opacities: Vec<F>,
    /// View-dependent colour, clamped at 0 for SH.
    pub colors: Vec<[F; 3]>,
}

impl<F> Projected<F> {
    pub fn visible(&self, i: usize) -> bool {
        self.radii[i][0] > 0 && self.radii[i][1] > 0
    }
}

impl<F: Real> Projected<F> {
    /// Half-extents in x and y of the ellipse where Gaussian `g`'s
    /// opacity·e^(-σ) falls to 1/255 (clamped to its 3.33σ radii), and the
    /// exponent past which the compositing skips it (see [`skip_exponent`]);
    /// `None` when it can never reach 1/255. Every pixel outside is skipped
    /// by the compositing anyway, so culling by it changes no image, and faint
    /// Gaussians, the bulk of a trained model, shrink most.
    pub(crate) fn reach(&self, g: usize) -> Option<(F, F, F)> {
        let opacity = self.opacities[g];
        if opacity < F::c(ALPHA_MIN) {
            return None;
        }
        // σ where opacity·e^(−σ) is 1/255.
        let cut = (opacity * F::c(1.0 / ALPHA_MIN)).ln();
        let level = F::c(2.0) * cut;
        let [ca, cb, cc] = self.conics[g];
        let inverse_det = ca * cc - cb * cb;
        let (sxx, syy) = (cc / inverse_det, ca / inverse_det);
        let [rx, ry] = self.radii[g].map(|r| F::c(r as f64));
        let (half_x, half_y) = if inverse_det > F::zero() && sxx.is_finite() && syy.is_finite() {
            ((level * sxx).sqrt().min(rx), (level * syy).sqrt().min(ry))
        } else {
            (rx, ry)
        };
        Some((half_x, half_y, skip_exponent(cut)))
    }
}

/// The Gaussian exponent σ = 0.5·(a·dx² + c·dy²) + b·dx·dy of a splat with
/// conic (a, b, c) at offset d = mean − sample point.
#[inline]
pub(crate) fn exponent<F: Real>([a, b, c]: [F; 3], dx: F, dy: F) -> F {
    F::c(0.5) * (a * dx * dx + c * dy * dy) + b * dx * dy
}

/// Rotation matrix of the normalised quaternion (w, x, y, z).
pub fn quat_to_rotmat<F: Real>(q: [F; 4]) -> [[F; 3]; 3] {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    let [w, x, y, z] = q.map(|v| v / n);
    let (one, two) = (F::one(), F::c(2.0));
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
        ],
        [
            two * (x * y + w * z),
            one - two * (x * x + z * z),
            two * (y * z - w * x),
        ],
        [
            two * (x * z - w * y),
            two * (y * z + w * x),
            one - two * (x * x + y * y),
        ],
    ]
}

fn matmul3<F: Real>(a: &[[F; 3]; 3], b: &[[F; 3]; 3]) -> [[F; 3]; 3] {
    let mut out = [[F::zero(); 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    out
}

fn transpose3<F: Real>(a: &[[F; 3]; 3]) -> [[F; 3]; 3] {
    let mut out = [[F::zero(); 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = a[j][i];
        }
    }
    out
}

/// World-space covariance R·S·Sᵀ·Rᵀ of a splat with rotation matrix `r`.
pub fn covariance<F: Real>(r: &[[F; 3]; 3], scale: [F; 3]) -> [[F; 3]; 3] {
    let mut m = *r;
    for row in &mut m {
        for (j, v) in row.iter_mut().enumerate() {
            *v = *v * scale[j];
        }
    }
    matmul3(&m, &transpose3(&m))
}

/// The direction a splat's SH are evaluated at under
/// [`Appearance::FixedRig`], and how it was made: the column `axis` of the
/// splat's rotation matrix `r` (its shortest axis) turned into the camera's
/// frame by `rot` and multiplied by `sign` (±1) so that it faces the camera
/// (negative z). A unit vector, since both rotations are.
pub fn rig_direction<F: Real>(
    rot: &[[F; 3]; 3],
    r: &[[F; 3]; 3],
    scale: [F; 3],
) -> ([F; 3], usize, F) {
    // Ties go to the lower axis, on both backends.
    let axis = (1..3).fold(0, |k, j| if scale[j] < scale[k] { j } else { k });
    let u = [0, 1, 2].map(|a| (0..3).map(|b| rot[a][b] * r[b][axis]).sum::<F>());
    let sign = if u[2] > F::zero() {
        -F::one()
    } else {
        F::one()
    };
    (u.map(|v| v * sign), axis, sign)
}

/// Projects every Gaussian through `camera`.
pub fn project<F: Real>(
    g: &Gaussians<F>,
    camera: &Camera<F>,
    settings: &Settings<F>,
) -> Projected<F> {
    let n = g.means.len();
    let ViewGeometry {
        rot,
        trans,
        campos,
        lim_x: (lim_x_neg, lim_x_pos),
        lim_y: (lim_y_neg, lim_y_pos),
    } = ViewGeometry::new(camera);
    let (w, h) = (F::c(camera.width as f64), F::c(camera.height as f64));
    let project_one = |i: usize| {
        let m = g.means[i];
        let pc =
            [0, 1, 2].map(|r| rot[r][0] * m[0] + rot[r][1] * m[1] + rot[r][2] * m[2] + trans[r]);
        let (x, y, z) = (pc[0], pc[1], pc[2]);
        let rotation = quat_to_rotmat(g.quats[i]);
        let cov_w = covariance(&rotation, g.scales[i]);
        let cov_c = matmul3(&matmul3(&rot, &cov_w), &transpose3(&rot));
        let tx = z * (x / z).max(-lim_x_neg).min(lim_x_pos);
        let ty = z * (y / z).max(-lim_y_neg).min(lim_y_pos);
        let j = [
            [camera.fx / z, F::zero(), -camera.fx * tx / (z * z)],
            [F::zero(), camera.fy / z, -camera.fy * ty / (z * z)],
        ];
        // cov2d = J Σ Jᵀ
        let mut js = [[F::zero(); 3]; 2];
        for r in 0..2 {
            for c in 0..3 {
                js[r][c] = j[r][0] * cov_c[0][c] + j[r][1] * cov_c[1][c] + j[r][2] * cov_c[2][c];
            }
        }
        let mut cov2 = [[F::zero(); 2]; 2];
        for r in 0..2 {
            for c in 0..2 {
                cov2[r][c] = js[r][0] * j[c][0] + js[r][1] * j[c][1] + js[r][2] * j[c][2];
            }
        }
        let det_raw = cov2[0][0] * cov2[1][1] - cov2[0][1] * cov2[1][0];
        let (a, b, c) = (
            cov2[0][0] + settings.eps2d,
            (cov2[0][1] + cov2[1][0]) * F::c(0.5),
            cov2[1][1] + settings.eps2d,
        );
        let det = (a * c - b * b).max(F::c(1e-10));
        let compensation = (det_raw / det).max(F::zero()).sqrt();
        let conic = [c / det, -b / det, a / det];
        let mean2d = [camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy];
        let rx = (F::c(RADIUS_SIGMA) * a.sqrt()).ceil();
        let ry = (F::c(RADIUS_SIGMA) * c.sqrt()).ceil();
        let in_depth = z > camera.near && z < camera.far;
        let on_image = mean2d[0] + rx > F::zero()
            && mean2d[0] - rx < w
            && mean2d[1] + ry > F::zero()
            && mean2d[1] - ry < h;
        let visible = in_depth && on_image && det.is_finite();
        let radii = if visible {
            [rx.to_i32().unwrap_or(0), ry.to_i32().unwrap_or(0)]
        } else {
            [0, 0]
        };
        let opacity = match settings.mode {
            Mode::Classic => g.opacities[i],
            Mode::Antialiased => g.opacities[i] * compensation,
        };
        let color = match &g.colors {
            Colors::Rgb(c) => c[i],
            Colors::Sh { degree, coeffs } => {
                let k = sh::coefficients(*degree);
                let d = [m[0] - campos[0], m[1] - campos[1], m[2] - campos[2]];
                let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                let dir = match settings.appearance {
                    Appearance::ViewDirection => d.map(|v| v / len),
                    Appearance::FixedRig => rig_direction(&rot, &rotation, g.scales[i]).0,
                };
                let raw = sh::evaluate(*degree, dir, &coeffs[i * k..(i + 1) * k]);
                raw.map(|v| (v + F::c(0.5)).max(F::zero()))
            }
        };
        (mean2d, z, conic, radii, compensation, opacity, color)
    };
    // Written in place by every thread (gathering a list of tuples into the
    // seven arrays on one thread took a second of a 3000-step DTU run).
    let mut p = Projected {
        means2d: filled(n, [F::zero(); 2]),
        depths: filled(n, F::zero()),
        conics: filled(n, [F::zero(); 3]),
        radii: filled(n, [0; 2]),
        compensations: filled(n, F::zero()),
        opacities: filled(n, F::zero()),
        colors: filled(n, [F::zero(); 3]),
    };
    (
        p.means2d.par_iter_mut(),
        p.depths.par_iter_mut(),
        p.conics.par_iter_mut(),
        p.radii.par_iter_mut(),
        p.compensations.par_iter_mut(),
        p.opacities.par_iter_mut(),
        p.colors.par_iter_mut(),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(i, out)| {
            let (mean2d, z, conic, radii, compensation, opacity, color) = project_one(i);
            *out.0 = mean2d;
            *out.1 = z;
            *out.2 = conic;
            *out.3 = radii;
            *out.4 = compensation;
            *out.5 = opacity;
            *out.6 = color;
        });
    p
}

/// `n` copies of `value`, written by every thread (one thread filling a
/// training step's large arrays left the others waiting).
pub(crate) fn filled<T: Copy + Send + Sync>(n: usize, value: T) -> Vec<T> {
    (0..n).into_par_iter().map(|_| value).collect()
}

/// Every Gaussian as the compositing reads it ([`Packed`], computed once
/// though most appear in several tiles: the reach alone, a logarithm and two
/// square roots, was a tenth of a training step when each tile recomputed
/// it), and the Gaussians touching each tile, front to back (ties by index).
pub(crate) struct TileBins<F> {
    pub packed: Vec<Packed<F>>,
    pub tiles: Vec<Vec<u32>>,
}

pub(crate) fn bin_tiles<F: Real>(p: &Projected<F>, width: u32, height: u32) -> TileBins<F> {
    let (tx, ty) = (width.div_ceil(TILE), height.div_ceil(TILE));
    let tile = F::c(TILE as f64);
    let cells = |v: F, round: fn(F) -> F, limit: u32| {
        round(v / tile).to_i64().unwrap_or(0).clamp(0, limit as i64) as u32
    };
    // Each Gaussian packed, and the tiles its reach covers: x0..x1, y0..y1.
    let (packed, covered): (Vec<Packed<F>>, Vec<Option<[u32; 4]>>) = (0..p.means2d.len())
        .into_par_iter()
        .map(|i| {
            let reach = p.reach(i).filter(|_| p.visible(i));
            // An unreached Gaussian is in no tile: its skip is never read.
            let (rx, ry, skip) = reach.unwrap_or((F::zero(), F::zero(), F::zero()));
            let [mx, my] = p.means2d[i];
            let reach_box = [mx - rx, mx + rx, my - ry, my + ry];
            let packed = (
                p.means2d[i],
                p.conics[i],
                [p.opacities[i], skip],
                p.colors[i],
                p.depths[i],
                reach_box,
            );
            let rect = reach.map(|_| {
                [
                    cells(reach_box[0], F::floor, tx),
                    cells(reach_box[1], F::ceil, tx),
                    cells(reach_box[2], F::floor, ty),
                    cells(reach_box[3], F::ceil, ty),
                ]
            });
            (packed, rect)
        })
        .unzip();
    // Depths as integers that sort the same way (IEEE order for finite
    // values), ties by index: the order every tile's list takes.
    let key = |i: usize| {
        let bits = p.depths[i].to_f64().unwrap_or(f64::NAN).to_bits();
        let ordered = if bits >> 63 == 1 {
            !bits
        } else {
            bits | 1 << 63
        };
        (ordered, i as u32)
    };
    // The reached Gaussians sorted once, front to back, then binned in that
    // order (`omniscan_core::tiles` keeps it), so every list comes out
    // sorted. Sorting each tile's list instead sorted every Gaussian once
    // per tile it touches.
    let mut by_depth: Vec<(u64, u32)> = (0..covered.len())
        .into_par_iter()
        .filter(|&i| covered[i].is_some())
        .map(key)
        .collect();
    by_depth.par_sort_unstable();
    let order: Vec<u32> = by_depth.into_par_iter().map(|(_, i)| i).collect();
    let tile_count = (tx * ty) as usize;
    let run = order
        .len()
        .div_ceil(4 * rayon::current_num_threads())
        .max(1);
    let mut tiles = omniscan_core::tiles::bin_in_order(order.len(), tile_count, run, |rank| {
        let [x0, x1, y0, y1] = covered[order[rank] as usize].unwrap_or([0; 4]);
        (y0..y1).flat_map(move |y| (x0..x1).map(move |x| (y * tx + x) as usize))
    });
    tiles.par_iter_mut().for_each(|list| {
        for slot in list.iter_mut() {
            *slot = order[*slot as usize];
        }
    });
    TileBins { packed, tiles }
}

/// A rendered image: colour with background, accumulated alpha, and the
/// alpha-weighted depth sum (divide by alpha for expected depth).
#[derive(Debug, Clone, PartialEq)]
pub struct Render<F> {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<[F; 3]>,
    pub alpha: Vec<F>,
    pub depth: Vec<F>,
    /// Depth of the Gaussian at which the accumulated alpha reaches one
    /// half (the median depth), 0 where it never does. Unlike the expected
    /// depth it is a point on the first surface: behind a 95%-opaque skin
    /// the expected depth is pulled towards whatever lies behind it
    /// (measured: 0.35 mm behind a box face that has another face 40 mm
    /// back), which misplaces every surface sample taken from it.
    pub median_depth: Vec<F>,
    /// How many Gaussians were composited at each pixel.
    pub contributors: Vec<u32>,
}

/// A Gaussian as the compositing reads it: mean, conic, opacity and the
/// exponent past which it is skipped (see [`skip_exponent`]), colour, depth,
/// and the pixel box it can reach (x0, x1, y0, y1).
pub(crate) type Packed<F> = ([F; 2], [F; 3], [F; 2], [F; 3], F, [F; 4]);

/// The exponent σ past which a Gaussian whose opacity·e^(−σ) falls to 1/255
/// at σ = `cut` (ln(255·opacity)) is certainly below it, with room for
/// rounding, so the compositing skips the pixel without evaluating the
/// exponential, as it would after evaluating it. At most [`SIGMA_SKIP`], the
/// bound for opacity 1. On a 3000-step DTU run, 23% of the exponentials
/// evaluated, forward and backward, were such pixels'.
fn skip_exponent<F: Real>(cut: F) -> F {
    let cut = cut + F::c(1e-3);
    if cut < F::c(SIGMA_SKIP) {
        cut
    } else {
        F::c(SIGMA_SKIP)
    }
}

/// Side of the sub-tiles that cull Gaussians before compositing and are
/// composited together (4x4 pixels; with pixel-by-pixel compositing it was
/// 20% faster than 8x8 at 160x120 on faint models, 2x2 slower).
pub(crate) const SUBTILE: u32 = TILE / 4;

/// One pixel's result: index, colour, alpha, depth sum, median depth, contributors.
type PixelResult<F> = (usize, [F; 3], F, F, F, u32);

/// Composites the projected Gaussians into an image.
pub fn rasterize<F: Real>(
    p: &Projected<F>,
    width: u32,
    height: u32,
    background: [F; 3],
) -> Render<F> {
    rasterize_binned(&bin_tiles(p, width, height), width, height, background)
}

/// [`rasterize`] with the tile bins given, so that a training step bins
/// once for its forward and backward passes.
pub(crate) fn rasterize_binned<F: Real>(
    bins: &TileBins<F>,
    width: u32,
    height: u32,
    background: [F; 3],
) -> Render<F> {
    let TileBins { packed, tiles } = bins;
    let tx = width.div_ceil(TILE);
    let n = (width * height) as usize;
    // In tile order, row by row.
    let tile_out: Vec<Vec<PixelResult<F>>> = (0..tiles.len() as u32)
        .into_par_iter()
        .map_init(
            || (Vec::new(), sub_tile_lists()),
            |(gathered, dealt), t| {
                let (ox, oy) = ((t % tx) * TILE, (t / tx) * TILE);
                let mut out = Vec::with_capacity((TILE * TILE) as usize);
                // Gathered once per tile so the per-pixel loop reads contiguous memory.
                gathered.clear();
                gathered.extend(tiles[t as usize].iter().map(|&g| packed[g as usize]));
                let sub_tiles = SubTiles::deal(gathered, |g| g.5, (ox, oy), (width, height), dealt);
                for (q, local) in dealt.iter().enumerate() {
                    if let Some(pixels) = sub_tiles.pixels(q) {
                        composite_block(local, pixels, width, background, &mut out);
                    }
                }
                out
            },
        )
        .collect();
    let mut r = Render {
        width,
        height,
        rgb: filled(n, [F::zero(); 3]),
        alpha: filled(n, F::zero()),
        depth: filled(n, F::zero()),
        median_depth: filled(n, F::zero()),
        contributors: filled(n, 0),
    };
    // Each band of tile rows is written by one thread: its tiles' pixels
    // are its own.
    let band = (width * TILE) as usize;
    if band > 0 {
        (
            r.rgb.par_chunks_mut(band),
            r.alpha.par_chunks_mut(band),
            r.depth.par_chunks_mut(band),
            r.median_depth.par_chunks_mut(band),
            r.contributors.par_chunks_mut(band),
        )
            .into_par_iter()
            .zip(tile_out.par_chunks(tx as usize))
            .enumerate()
            .for_each(|(row, ((rgb, alpha, depth, median, count), tiles))| {
                let first = row * band;
                for pixels in tiles {
                    for &(i, c, a, d, m, k) in pixels {
                        let i = i - first;
                        rgb[i] = c;
                        alpha[i] = a;
                        depth[i] = d;
                        median[i] = m;
                        count[i] = k;
                    }
                }
            });
    }
    r
}

/// Sub-tiles per tile side.
const SIDE: usize = (TILE / SUBTILE) as usize;

/// A list per sub-tile of a tile, row-major.
pub(crate) type SubTileLists<T> = [Vec<T>; SIDE * SIDE];

/// Empty lists for [`SubTiles::deal`].
pub(crate) fn sub_tile_lists<T>() -> SubTileLists<T> {
    std::array::from_fn(|_| Vec::new())
}

/// The sub-tiles of one tile: the pixels each covers (clipped to the image)
/// and the pixel centres at its edges.
pub(crate) struct SubTiles<F> {
    columns: [(u32, u32, F, F); SIDE],
    rows: [(u32, u32, F, F); SIDE],
}

impl<F: Real> SubTiles<F> {
    /// Deals the tile's Gaussians (`items`, front to back) to the sub-tiles
    /// their reach box (x0, x1, y0, y1) touches, in one pass over the list,
    /// keeping their order: compositing a sub-tile with only its own gives
    /// the same pixels with fewer misses. The lists in `dealt` are emptied
    /// first and keep their capacity, so a thread's lists stop growing after
    /// its first tiles. (Fresh lists for every tile, grown push by push, were
    /// a tenth of the CPU time of a step on 200k random Gaussians at 640x480.)
    pub(crate) fn deal<T: Copy>(
        items: &[T],
        reach_box: impl Fn(&T) -> [F; 4],
        (ox, oy): (u32, u32),
        (width, height): (u32, u32),
        dealt: &mut SubTileLists<T>,
    ) -> SubTiles<F> {
        let bounds = |o: u32, q: u32, limit: u32| {
            let (lo, hi) = (o + q * SUBTILE, (o + (q + 1) * SUBTILE).min(limit));
            (lo, hi, F::c(lo as f64 + 0.5), F::c(hi as f64 - 0.5))
        };
        let sub_tiles = SubTiles {
            columns: std::array::from_fn(|q| bounds(ox, q as u32, width)),
            rows: std::array::from_fn(|q| bounds(oy, q as u32, height)),
        };
        dealt.iter_mut().for_each(Vec::clear);
        for item in items {
            let [bx0, bx1, by0, by1] = reach_box(item);
            for (qy, &(y0, y1, lo_y, hi_y)) in sub_tiles.rows.iter().enumerate() {
                if y0 >= y1 || by1 < lo_y || by0 > hi_y {
                    continue;
                }
                for (qx, &(x0, x1, lo_x, hi_x)) in sub_tiles.columns.iter().enumerate() {
                    if x0 < x1 && bx1 >= lo_x && bx0 <= hi_x {
                        dealt[qy * SIDE + qx].push(*item);
                    }
                }
            }
        }
        sub_tiles
    }

    /// Pixels `x0..x1` × `y0..y1` of sub-tile `q` (as dealt), if any lie in the image.
    pub(crate) fn pixels(&self, q: usize) -> Option<(u32, u32, u32, u32)> {
        let (x0, x1, _, _) = self.columns[q % SIDE];
        let (y0, y1, _, _) = self.rows[q / SIDE];
        (x0 < x1 && y0 < y1).then_some((x0, x1, y0, y1))
    }
}

/// Pixels composited together: one sub-tile.
pub(crate) const LANES: usize = (SUBTILE * SUBTILE) as usize;

/// One Gaussian's share of one pixel, as the compositing meets it: its
/// alpha, e^(−σ), the transmittance in front of it and behind it, and
/// whether alpha was clamped at 0.99.
pub(crate) struct Contribution<F> {
    pub alpha: F,
    pub vis: F,
    pub transmittance: F,
    pub next: F,
    pub clamped: bool,
}

/// Composites the sub-tile's Gaussians (`local`, front to back; `packed`
/// reads each one's [`Packed`]) over the pixels `x0..x1` × `y0..y1`, all
/// pixels at once: each Gaussian's exponent is computed for the 16 pixels
/// in one branch-free loop, and the list is read once per sub-tile instead
/// of once per pixel (1.5x faster at 160x120). `visit(lane, index, share)`
/// is called for every contribution, lanes row-major in the sub-tile;
/// returns each lane's final transmittance. Every pixel sees the same
/// operations in the same order as a pixel-by-pixel loop, so the image
/// (and the backward pass's replay of it) is the same to the bit.
pub(crate) fn composite_lanes<F: Real, T>(
    local: &[T],
    packed: impl Fn(&T) -> &Packed<F>,
    (x0, x1, y0, y1): (u32, u32, u32, u32),
    mut visit: impl FnMut(usize, usize, &Contribution<F>),
) -> [F; LANES] {
    let (fx, fy) = lane_centres(x0, y0);
    // Lanes outside the image (a partial sub-tile) start finished.
    let mut done: [bool; LANES] = std::array::from_fn(|k| {
        let (px, py) = lane_pixel(x0, y0, k);
        px >= x1 || py >= y1
    });
    let mut active = done.iter().filter(|d| !**d).count();
    let mut t_acc = [F::one(); LANES];
    let mut sigma = [F::zero(); LANES];
    let mut hit = [false; LANES];
    for (index, item) in local.iter().enumerate() {
        let &([mx, my], conic, [opacity, skip], ..) = packed(item);
        let mut any = false;
        for k in 0..LANES {
            sigma[k] = exponent(conic, mx - fx[k], my - fy[k]);
            hit[k] = !done[k] && sigma[k] >= F::zero() && sigma[k] <= skip;
            any |= hit[k];
        }
        if !any {
            continue;
        }
        for k in 0..LANES {
            if !hit[k] {
                continue;
            }
            let vis = (-sigma[k]).exp();
            let raw = opacity * vis;
            let alpha = raw.min(F::c(ALPHA_MAX));
            if alpha < F::c(ALPHA_MIN) {
                continue;
            }
            let next = t_acc[k] * (F::one() - alpha);
            if next <= F::c(T_STOP) {
                done[k] = true;
                active -= 1;
                continue;
            }
            let share = Contribution {
                alpha,
                vis,
                transmittance: t_acc[k],
                next,
                clamped: raw > F::c(ALPHA_MAX),
            };
            visit(k, index, &share);
            t_acc[k] = next;
        }
        if active == 0 {
            break;
        }
    }
    t_acc
}

/// The pixel of lane `k` of the sub-tile whose corner is (x0, y0).
pub(crate) fn lane_pixel(x0: u32, y0: u32, k: usize) -> (u32, u32) {
    (x0 + k as u32 % SUBTILE, y0 + k as u32 / SUBTILE)
}

/// The pixel centres of the lanes of the sub-tile whose corner is (x0, y0).
pub(crate) fn lane_centres<F: Real>(x0: u32, y0: u32) -> ([F; LANES], [F; LANES]) {
    let centre = |v: u32| F::c(v as f64 + 0.5);
    (
        std::array::from_fn(|k| centre(lane_pixel(x0, y0, k).0)),
        std::array::from_fn(|k| centre(lane_pixel(x0, y0, k).1)),
    )
}

/// Composites one sub-tile into `out`: colour over the background, alpha,
/// depth sum, median depth and contributor count per pixel.
fn composite_block<F: Real>(
    local: &[Packed<F>],
    pixels: (u32, u32, u32, u32),
    width: u32,
    background: [F; 3],
    out: &mut Vec<PixelResult<F>>,
) {
    let mut c = [[F::zero(); 3]; LANES];
    let mut d = [F::zero(); LANES];
    let mut median = [F::zero(); LANES];
    let mut count = [0u32; LANES];
    let t_final = composite_lanes(
        local,
        |g| g,
        pixels,
        |k, index, share| {
            let (_, _, _, color, depth, _) = local[index];
            let w = share.alpha * share.transmittance;
            for (acc, col) in c[k].iter_mut().zip(color) {
                *acc = *acc + col * w;
            }
            d[k] = d[k] + depth * w;
            if share.transmittance > F::c(0.5) && share.next <= F::c(0.5) {
                median[k] = depth;
            }
            count[k] += 1;
        },
    );
    let (x0, x1, y0, y1) = pixels;
    for (k, t) in t_final.iter().enumerate() {
        let (px, py) = lane_pixel(x0, y0, k);
        if px >= x1 || py >= y1 {
            continue;
        }
        let rgb = [0, 1, 2].map(|ch| c[k][ch] + *t * background[ch]);
        out.push((
            (py * width + px) as usize,
            rgb,
            F::one() - *t,
            d[k],
            median[k],
            count[k],
        ));
    }
}

/// Projects and rasterizes in one call.
pub fn render<F: Real>(
    g: &Gaussians<F>,
    camera: &Camera<F>,
    settings: &Settings<F>,
) -> (Projected<F>, Render<F>) {
    let p = project(g, camera, settings);
    let r = rasterize(&p, camera.width, camera.height, settings.background);
    (p, r)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A repeatable value in [0, 1) for item `i` and stream `k`, to build
    /// scenes from.
    fn pseudo_random(i: usize, k: f64) -> f64 {
        ((i as f64 * k).sin() * 43758.5453).fract().abs()
    }

    fn camera() -> Camera<f64> {
        let id = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        Camera {
            viewmat: id,
            fx: 50.0,
            fy: 50.0,
            cx: 16.0,
            cy: 16.0,
            width: 32,
            height: 32,
            near: 0.01,
            far: 100.0,
        }
    }

    #[test]
    fn an_isotropic_gaussian_matches_its_closed_form() {
        // One Gaussian straight ahead: σ² = (50·s/z)² + 0.3 pixels², opacity 0.5.
        let g = Gaussians {
            means: vec![[0.0, 0.0, 2.0]],
            scales: vec![[0.1; 3]],
            quats: vec![[1.0, 0.0, 0.0, 0.0]],
            opacities: vec![0.5],
            colors: Colors::Rgb(vec![[1.0, 0.5, 0.25]]),
        };
        let (p, r) = render(&g, &camera(), &Settings::default());
        let var = (50.0 * 0.1 / 2.0f64).powi(2) + 0.3;
        assert!((p.conics[0][0] - 1.0 / var).abs() < 1e-12 && p.conics[0][1].abs() < 1e-12);
        for (px, py) in [(16, 16), (18, 15), (25, 20)] {
            let (dx, dy) = (16.0 - (px as f64 + 0.5), 16.0 - (py as f64 + 0.5));
            let alpha = 0.5 * (-0.5 * (dx * dx + dy * dy) / var).exp();
            let i = py * 32 + px;
            if alpha >= 1.0 / 255.0 {
                assert!((r.alpha[i] - alpha).abs() < 1e-12, "{px},{py}");
                assert!((r.rgb[i][1] - 0.5 * alpha).abs() < 1e-12);
                assert!((r.depth[i] - 2.0 * alpha).abs() < 1e-12);
            } else {
                assert_eq!(r.alpha[i], 0.0);
            }
        }
    }

    #[test]
    fn tiled_compositing_equals_a_plain_loop_over_every_gaussian() {
        // Many overlapping anisotropic Gaussians on an image whose size is
        // not a multiple of the tile or sub-tile, against a per-pixel loop
        // over all visible Gaussians in depth order: equal to the bit.
        let n = 300;
        let r = pseudo_random;
        let g = Gaussians {
            means: (0..n)
                .map(|i| [r(i, 1.1) - 0.5, r(i, 2.3) - 0.5, 1.5 + r(i, 3.7)])
                .collect(),
            scales: (0..n)
                .map(|i| [0.01 + 0.1 * r(i, 4.1), 0.01 + 0.05 * r(i, 5.3), 0.02])
                .collect(),
            quats: (0..n)
                .map(|i| [1.0, r(i, 6.7) - 0.5, r(i, 7.9) - 0.5, r(i, 8.3) - 0.5])
                .collect(),
            opacities: (0..n).map(|i| 0.02 + 0.97 * r(i, 9.1)).collect(),
            colors: Colors::Rgb(
                (0..n)
                    .map(|i| [r(i, 10.0), r(i, 11.0), r(i, 12.0)])
                    .collect(),
            ),
        };
        let mut cam = camera();
        (cam.width, cam.height, cam.cx, cam.cy) = (37, 29, 18.5, 14.5);
        let settings = Settings::default();
        let (p, image) = render(&g, &cam, &settings);
        let mut order: Vec<usize> = (0..n).filter(|&i| p.visible(i)).collect();
        order.sort_by(|&a, &b| p.depths[a].total_cmp(&p.depths[b]).then(a.cmp(&b)));
        for py in 0..29 {
            for px in 0..37 {
                let (fx, fy) = (px as f64 + 0.5, py as f64 + 0.5);
                let (mut t, mut c, mut count) = (1.0, [0.0; 3], 0);
                for &i in &order {
                    let [a, b, cc] = p.conics[i];
                    let (dx, dy) = (p.means2d[i][0] - fx, p.means2d[i][1] - fy);
                    let sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy;
                    if !(0.0..=SIGMA_SKIP).contains(&sigma) {
                        continue;
                    }
                    let alpha = (p.opacities[i] * (-sigma).exp()).min(ALPHA_MAX);
                    if alpha < ALPHA_MIN {
                        continue;
                    }
                    let next = t * (1.0 - alpha);
                    if next <= T_STOP {
                        break;
                    }
                    for ch in 0..3 {
                        c[ch] += p.colors[i][ch] * (alpha * t);
                    }
                    t = next;
                    count += 1;
                }
                let k = py * 37 + px;
                assert_eq!(image.alpha[k], 1.0 - t, "alpha at {px},{py}");
                assert_eq!(image.contributors[k], count, "contributors at {px},{py}");
                for ch in 0..3 {
                    let expected = c[ch] + t * settings.background[ch];
                    assert!(
                        (image.rgb[k][ch] - expected).abs() < 1e-12,
                        "colour at {px},{py}"
                    );
                }
            }
        }
        assert!(image.contributors.iter().any(|&c| c > 5));
    }

    #[test]
    fn every_tile_lists_the_gaussians_it_reaches_by_depth_then_index() {
        // Depths drawn from three values, so most of a tile's Gaussians tie
        // with others, on an image whose size is not a multiple of the tile:
        // each list against the reached Gaussians whose box meets the tile,
        // sorted by depth and then by index.
        let n = 400;
        let r = pseudo_random;
        let g = Gaussians {
            means: (0..n)
                .map(|i| [r(i, 1.3) - 0.5, r(i, 2.9) - 0.5, [1.0, 1.5, 2.0][i % 3]])
                .collect(),
            scales: (0..n)
                .map(|i| [0.004 + 0.06 * r(i, 4.7), 0.004 + 0.03 * r(i, 5.9), 0.01])
                .collect(),
            quats: (0..n).map(|i| [1.0, r(i, 6.1) - 0.5, 0.0, 0.0]).collect(),
            opacities: (0..n).map(|i| 0.001 + 0.99 * r(i, 9.7)).collect(),
            colors: Colors::Rgb(vec![[0.5; 3]; n]),
        };
        let mut cam = camera();
        (cam.width, cam.height, cam.cx, cam.cy) = (70, 45, 35.0, 22.5);
        let p = project(&g, &cam, &Settings::default());
        let bins = bin_tiles(&p, cam.width, cam.height);
        let (tx, ty) = (cam.width.div_ceil(TILE), cam.height.div_ceil(TILE));
        assert_eq!(bins.tiles.len(), (tx * ty) as usize);
        let mut ties = 0;
        for (t, list) in bins.tiles.iter().enumerate() {
            let (x, y) = ((t as u32 % tx) as f64, (t as u32 / tx) as f64);
            let tile = TILE as f64;
            let mut expected: Vec<u32> = (0..n)
                .filter(|&i| p.visible(i))
                .filter(|&i| {
                    let Some((rx, ry, _)) = p.reach(i) else {
                        return false;
                    };
                    let [mx, my] = p.means2d[i];
                    let covers = |m: f64, r: f64, at: f64, count: u32| {
                        let first = ((m - r) / tile).floor().clamp(0.0, count as f64);
                        let end = ((m + r) / tile).ceil().clamp(0.0, count as f64);
                        first <= at && at < end
                    };
                    covers(mx, rx, x, tx) && covers(my, ry, y, ty)
                })
                .map(|i| i as u32)
                .collect();
            expected.sort_by(|&a, &b| {
                let depth = |i: u32| p.depths[i as usize];
                depth(a).total_cmp(&depth(b)).then(a.cmp(&b))
            });
            assert_eq!(list, &expected, "tile {t}");
            ties += list
                .windows(2)
                .filter(|w| p.depths[w[0] as usize] == p.depths[w[1] as usize])
                .count();
        }
        assert!(ties > 100, "only {ties} ties");
        assert!(bins.tiles.iter().filter(|l| l.len() > 20).count() > 4);
    }

    #[test]
    fn behind_the_camera_is_invisible_and_front_occludes_back() {
        let g = Gaussians {
            means: vec![[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 3.0]],
            scales: vec![[0.2; 3]; 3],
            quats: vec![[1.0, 0.0, 0.0, 0.0]; 3],
            opacities: vec![0.99; 3],
            colors: Colors::Rgb(vec![[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
        };
        let (p, r) = render(&g, &camera(), &Settings::default());
        assert!(!p.visible(0) && p.visible(1) && p.visible(2));
        let centre = 16 * 32 + 16;
        assert!(r.rgb[centre][0] > 0.9 && r.rgb[centre][1] < 0.05);
    }
}
