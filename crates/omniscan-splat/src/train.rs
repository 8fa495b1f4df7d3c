//! The masked 3DGS trainer (paper, "3DGS Training" and "Supporting
//! In-Gripper Datasets") on the CPU reference rasterizer.
//!
//! Loss per view, with w = 1 − gripper mask (the gripper-agnostic weighting:
//! every per-pixel term is zero on gripper pixels and means are taken over
//! the remaining pixels):
//!   L = (1 − λ)·Σw|Ĉ − Î|/Σw + λ·(1 − SSIM_w(Ĉ, Î)) + β·Σw|A − M|/Σw,
//! where Ĉ is the render composited over a random background colour, Î the
//! photo with its non-object pixels replaced by that same colour (so the
//! model cannot use the background), A the rendered accumulation and M the
//! object mask (the paper's object opacity loss). λ = 0.2.
//!
//! Optimiser: Adam per parameter group with gsplat's learning rates (means
//! scaled by the scene extent and decayed to 1% over the run), except the
//! higher SH bands' ([`SH_REST_LR`]). Densification
//! follows gsplat's default strategy: the mean screen-space gradient (or,
//! with `absolute_gradients`, AbsGS's sum of per-pixel absolute gradients,
//! Ye et al. 2024) picks
//! splats to clone (small) or split (large), transparent splats are pruned,
//! opacities are reset periodically, with a hard cap on the count. The SH
//! degree grows by one every `sh_interval` steps. Initialisation without a
//! point cloud: points sampled in the space the cameras see, kept where every
//! view's object (or gripper) mask agrees (a visual hull).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::metrics::{ImageView, psnr, weighted_ssim_and_gradient};
use crate::raster::Camera;
use crate::sh::{C0, coefficients};
use crate::view::{TrainingView, View};
use crate::{SplatError, Splats};

/// Training settings.
#[derive(Debug, Clone, Copy)]
pub struct TrainConfig {
    pub steps: usize,
    pub seed: u64,
    pub max_sh_degree: usize,
    pub sh_interval: usize,
    pub lambda_ssim: f32,
    pub lambda_opacity: f32,
    pub densify_from: usize,
    pub densify_until: usize,
    pub densify_every: usize,
    pub grad_threshold: f32,
    /// Densify by the per-pixel 2D mean gradients summed in absolute value
    /// (AbsGS, Ye et al. 2024; gsplat's `absgrad`) rather than by their
    /// sum, in which opposite pulls across a large splat cancel: that
    /// splat then never splits, and fine texture under it stays blurred.
    pub absolute_gradients: bool,
    pub reset_every: usize,
    pub max_splats: usize,
    pub initial_points: usize,
    pub densification: Densification,
    /// Position learning rate per unit of scene extent at the start (it
    /// decays to 1% over the run); gsplat's 1.6e-4.
    pub position_lr: f32,
    /// Adam's rate for the SH bands above the DC term (view-dependent
    /// colour); the DC term's is 2.5e-3.
    pub sh_rest_lr: f32,
    /// Learn a correction of each view's camera pose with the splats
    /// ([`crate::pose`]); `None`: the poses are taken as recorded.
    pub pose: Option<crate::pose::PoseConfig>,
}

/// How splats are added and removed during training.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Densification {
    /// gsplat's default strategy: clone, split, prune, periodic opacity
    /// resets, between `densify_from` and `densify_until`.
    Adaptive,
    /// 3DGS as Markov chain Monte Carlo ([`crate::mcmc`]): relocation of
    /// dead splats, 5% growth per refinement up to `max_splats`, opacity and
    /// scale penalties, noise on near-transparent splats. A fresh start
    /// sets every splat to opacity 0.5 and a tenth of its size.
    Mcmc,
}

/// Adam's rate for the SH DC term (gsplat's).
pub const SH_DC_LR: f32 = 2.5e-3;

/// Adam's rates for the groups without a schedule or an option (gsplat's):
/// log-scales, quaternions and opacity logits.
pub const LOG_SCALES_LR: f32 = 5e-3;
pub const QUATS_LR: f32 = 1e-3;
pub const OPACITIES_LR: f32 = 5e-2;

/// The default Adam rate of the SH bands above DC: the DC term's own, not
/// gsplat's twentieth of it. At a twentieth the bands, grown one degree
/// per 1000 steps, stay too small in a 3000-step run to follow the
/// view-dependent shading of metal and of lights that move with the camera.
/// Held-out masked PSNR, 3000 steps (a twentieth → this rate): simulated
/// flashlight, left arm 28.8 → 30.2 dB (seed 1: 28.6 → 30.1), both arms
/// 26.8 → 27.9; remote 34.0 → 33.9; DTU scan37 (antialiased, 200x150)
/// 23.6 → 24.4, and 25.0 → 25.1 after 10,000 steps. A single arm's
/// whole-image PSNR falls by about 2 dB, all of it under the gripper,
/// which no view of that arm sees and the paper's metric leaves out (the
/// merged model, which sees it from the other arm, keeps 37.6 dB).
pub const SH_REST_LR: f32 = SH_DC_LR;

impl TrainConfig {
    pub fn with_steps(steps: usize) -> TrainConfig {
        TrainConfig {
            steps,
            seed: 0,
            max_sh_degree: 3,
            sh_interval: 1000,
            lambda_ssim: 0.2,
            lambda_opacity: 1.0,
            densify_from: 300.min(steps / 4),
            densify_until: steps / 2,
            densify_every: 100,
            grad_threshold: 0.0002,
            absolute_gradients: false,
            reset_every: 3000,
            max_splats: 200_000,
            initial_points: 5000,
            densification: Densification::Adaptive,
            position_lr: 1.6e-4,
            sh_rest_lr: SH_REST_LR,
            pose: None,
        }
    }

    /// MCMC densification with gsplat's schedule: refinements from step
    /// 500 until five sixths of the run.
    pub fn mcmc(steps: usize) -> TrainConfig {
        TrainConfig {
            densify_until: steps * 5 / 6,
            densification: Densification::Mcmc,
            ..TrainConfig::with_steps(steps)
        }
    }

    /// Densification by absolute gradients, with gsplat's threshold for
    /// them (0.0008: absolute sums run larger than the plain sum).
    pub fn with_absolute_gradients(self) -> TrainConfig {
        TrainConfig {
            absolute_gradients: true,
            grad_threshold: 0.0008,
            ..self
        }
    }
}

/// The visual-hull initialisation described in the module docs: `count`
/// points sampled in a cube around the origin (where a capture's gripper
/// frame and most photo sets put the object), half as wide as 0.35 times the
/// farthest camera's distance; or, where the cameras look at a point more
/// than a quarter of that distance from the origin (a COLMAP world, whose
/// origin is often the first camera), around that point. A point only one
/// camera sees passes every other view's mask, so a cube away from the object
/// is not empty but full of such points: the choice is made before sampling.
pub fn initial_splats(
    views: &[impl TrainingView],
    count: usize,
    max_sh_degree: usize,
    seed: u64,
) -> Result<Splats, SplatError> {
    if views.is_empty() {
        return Err(SplatError::Invalid("no training views".into()));
    }
    let origin = [0.0f32; 3];
    let centre = match cameras_look_at(views) {
        Some(p) if distance(p, origin) > 0.25 * farthest_camera(views, origin) => p,
        _ => origin,
    };
    let half = 0.35 * farthest_camera(views, centre);
    let (points, colours) = visual_hull(views, centre, half, count, seed);
    if points.len() < 10 {
        return Err(SplatError::Invalid(format!(
            "the object masks agree on too little space to start from: check the masks and camera poses (the object was looked for within {half} of ({}, {}, {}): {}, within 0.35 times the farthest camera's distance)",
            centre[0],
            centre[1],
            centre[2],
            if centre == origin {
                "the origin"
            } else {
                "the point the cameras look at"
            }
        )));
    }
    splats_from_points(&points, &colours, max_sh_degree)
}

fn distance(a: [f32; 3], b: [f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// The distance from `centre` to the farthest camera.
fn farthest_camera(views: &[impl TrainingView], centre: [f32; 3]) -> f32 {
    views
        .iter()
        .map(|v| distance(v.camera().centre(), centre))
        .fold(0.0, f32::max)
}

/// The point nearest, in least squares, to every camera's optical axis: what
/// an orbit of cameras looks at. `None` where the axes are close to parallel
/// (cameras that all face one way fix no such point).
fn cameras_look_at(views: &[impl TrainingView]) -> Option<[f32; 3]> {
    let mut normal = nalgebra::Matrix3::<f64>::zeros();
    let mut rhs = nalgebra::Vector3::<f64>::zeros();
    for v in views {
        let m = v.camera().viewmat;
        // The optical axis is the camera's +z, the view matrix's third row.
        let axis = nalgebra::Vector3::new(m[2][0] as f64, m[2][1] as f64, m[2][2] as f64)
            .try_normalize(1e-12)?;
        let centre = nalgebra::Vector3::from(v.camera().centre().map(f64::from));
        let across = nalgebra::Matrix3::identity() - axis * axis.transpose();
        normal += across;
        rhs += across * centre;
    }
    // Each term's eigenvalues are 1, 1, 0 (0 along its axis): a smallest
    // eigenvalue near 0 means every axis runs one way.
    let smallest = normal.symmetric_eigenvalues().min();
    if smallest < 0.05 * views.len() as f64 {
        return None;
    }
    let p = normal.lu().solve(&rhs)?;
    Some([p.x as f32, p.y as f32, p.z as f32])
}

/// Where `p` lies in `camera`'s image (pixel column, row), and its depth
/// along the optical axis, if in front of the camera and inside the image.
fn project_point(camera: &Camera<f32>, p: [f32; 3]) -> Option<(usize, usize, f32)> {
    let v = camera.viewmat;
    let pc = [0, 1, 2].map(|r| v[r][0] * p[0] + v[r][1] * p[1] + v[r][2] * p[2] + v[r][3]);
    if pc[2] <= camera.near {
        return None;
    }
    let (u, w) = (
        camera.fx * pc[0] / pc[2] + camera.cx,
        camera.fy * pc[1] / pc[2] + camera.cy,
    );
    (u >= 0.0 && w >= 0.0 && u < camera.width as f32 && w < camera.height as f32)
        .then_some((u as usize, w as usize, pc[2]))
}

/// The visual hull's verdict on `p`: its mean colour in the views that see
/// it as object, or `None` where a view sees it outside the object (or in
/// front of the surface its depth saw) or most views see it as gripper.
fn hull_colour(views: &[impl TrainingView], p: [f32; 3]) -> Option<[f32; 3]> {
    let mut seen = 0;
    let mut in_image = 0;
    let mut colour = [0.0f32; 3];
    for v in views {
        let camera = v.camera();
        let Some((u, w, z)) = project_point(camera, p) else {
            continue;
        };
        let pixel = v.pixel(w * camera.width as usize + u);
        in_image += 1;
        if pixel.object < 0.5 && pixel.excluded < 0.5 {
            return None;
        }
        // Depth carves free space: a point clearly in front of the observed
        // surface is empty (the gripper's volume would otherwise survive
        // the masks, which always cover it).
        if pixel.depth > 0.0 && z < pixel.depth * 0.97 {
            return None;
        }
        if pixel.object >= 0.5 {
            seen += 1;
            for c in 0..3 {
                colour[c] += pixel.colour[c];
            }
        }
    }
    (seen > 0 && 2 * seen >= in_image).then(|| colour.map(|c| c / seen as f32))
}

/// Candidates the visual hull draws and judges on all threads at a time.
const HULL_BATCH: usize = 4096;

/// Points sampled in the cube of half-width `half` around `centre`, kept
/// where the views agree on the object ([`hull_colour`]), with their mean
/// colour in the views that see them as object; the first `count` kept among
/// at most 400·`count` candidates. Candidates are drawn in batches and judged
/// on all threads, then taken in the order drawn: the points one-by-one
/// judging would keep (the hull took 1.4 s of a 300-step training's 11 s on
/// one thread).
fn visual_hull(
    views: &[impl TrainingView],
    centre: [f32; 3],
    half: f32,
    count: usize,
    seed: u64,
) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let tries = count.saturating_mul(400);
    let mut points = Vec::new();
    let mut colours = Vec::new();
    let mut drawn = 0;
    while points.len() < count && drawn < tries {
        let batch: Vec<[f32; 3]> = (0..HULL_BATCH.min(tries - drawn))
            .map(|_| hull_candidate(&mut rng, centre, half))
            .collect();
        drawn += batch.len();
        let judged: Vec<Option<[f32; 3]>> =
            batch.par_iter().map(|&p| hull_colour(views, p)).collect();
        let kept = batch
            .into_iter()
            .zip(judged)
            .filter_map(|(p, colour)| Some((p, colour?)))
            .take(count - points.len());
        for (p, colour) in kept {
            points.push(p);
            colours.push(colour);
        }
    }
    (points, colours)
}

/// A point drawn uniformly in the cube of half-width `half` around `centre`.
fn hull_candidate(rng: &mut ChaCha8Rng, centre: [f32; 3], half: f32) -> [f32; 3] {
    let offset = [0; 3].map(|_| (rng.random::<f32>() * 2.0 - 1.0) * half);
    [0, 1, 2].map(|k| centre[k] + offset[k])
}

/// Initial splats at `points` (3DGS's initialisation from a point cloud):
/// isotropic, sized by the mean distance to the three nearest neighbours,
/// opacity 0.1, the point's colour (0..1) as the SH DC term.
pub fn splats_from_points(
    points: &[[f32; 3]],
    colours: &[[f32; 3]],
    max_sh_degree: usize,
) -> Result<Splats, SplatError> {
    if points.len() < 4 || colours.len() != points.len() {
        return Err(SplatError::Invalid(format!(
            "initial points: {} points with {} colours (at least 4 points, one colour each)",
            points.len(),
            colours.len()
        )));
    }
    if points.iter().flatten().any(|v| !v.is_finite()) {
        return Err(SplatError::Invalid(
            "initial points: NaN or infinite coordinates".into(),
        ));
    }
    // Scale each splat to the distance to its nearest neighbours.
    let tree: kiddo::ImmutableKdTree<f32, 3> = kiddo::ImmutableKdTree::new_from_slice(points)
        .map_err(|e| SplatError::Invalid(format!("initial points: cannot index them: {e:?}")))?;
    let k = coefficients(max_sh_degree);
    let mut s = Splats {
        sh_degree: max_sh_degree,
        ..Default::default()
    };
    for (p, c) in points.iter().zip(colours) {
        let r = tree
            .query(p)
            .nearest_n::<kiddo::SquaredEuclidean<f32>>(
                std::num::NonZero::<usize>::MIN.saturating_add(3),
            )
            .execute();
        let d = (r.iter().skip(1).map(|x| x.distance.sqrt()).sum::<f32>() / 3.0).max(1e-5);
        s.means.push(*p);
        s.log_scales.push([d.ln(); 3]);
        s.quats.push([1.0, 0.0, 0.0, 0.0]);
        s.opacity_logits.push((0.1f32 / 0.9).ln());
        s.sh.push(c.map(|v| (v - 0.5) / C0 as f32));
        s.sh.extend(std::iter::repeat_n([0.0; 3], k - 1));
    }
    Ok(s)
}

/// Activated parameters with only the first `degree` SH bands in use.
/// One step's loss on a render and its gradient with respect to the
/// render's colour and alpha (see the module doc), and the masked PSNR.
pub struct StepLoss {
    pub loss: f32,
    pub d_rgb: Vec<[f32; 3]>,
    pub d_alpha: Vec<f32>,
    pub psnr: f64,
}

pub fn step_loss(
    view: &View,
    r: &crate::raster::Render<f32>,
    background: [f32; 3],
    config: &TrainConfig,
) -> StepLoss {
    let (w, h) = (view.camera.width as usize, view.camera.height as usize);
    let n_px = w * h;
    // The per-pixel work in parallel, the sums in pixel order (the same
    // loss to the bit as one loop).
    let target: Vec<[f32; 3]> = (0..n_px)
        .into_par_iter()
        .map(|i| {
            let m = view.object[i];
            [0, 1, 2].map(|c| view.image[i][c] * m + background[c] * (1.0 - m))
        })
        .collect();
    let weight: Vec<f32> = view.excluded.par_iter().map(|g| 1.0 - g).collect();
    let wsum = weight.iter().sum::<f32>().max(1.0);
    let lam = config.lambda_ssim;
    let (mut d_rgb, d_alpha): (Vec<[f32; 3]>, Vec<f32>) = (0..n_px)
        .into_par_iter()
        .map(|i| {
            let d_rgb = [0, 1, 2].map(|c| {
                let d = r.rgb[i][c] - target[i][c];
                (1.0 - lam) * weight[i] * d.signum() / (3.0 * wsum)
            });
            let da = r.alpha[i] - view.object[i];
            (
                d_rgb,
                config.lambda_opacity * weight[i] * da.signum() / wsum,
            )
        })
        .unzip();
    let mut l1 = 0.0f32;
    let mut lo = 0.0f32;
    for i in 0..n_px {
        for c in 0..3 {
            l1 += weight[i] * (r.rgb[i][c] - target[i][c]).abs() / (3.0 * wsum);
        }
        lo += weight[i] * (r.alpha[i] - view.object[i]).abs() / wsum;
    }
    // The SSIM term in f32, as gsplat computes it (see `SsimFloat`).
    let ssim_weights: Vec<f32> = weight.par_iter().map(|&x| x / (3.0 * wsum)).collect();
    let rendered = ImageView {
        width: w,
        height: h,
        pixels: &r.rgb,
    };
    let wanted = ImageView {
        width: w,
        height: h,
        pixels: &target,
    };
    let (ssim, d_ssim) = weighted_ssim_and_gradient(&rendered, &wanted, &ssim_weights);
    d_rgb.par_iter_mut().zip(&d_ssim).for_each(|(d, s)| {
        for c in 0..3 {
            d[c] -= lam * s[c];
        }
    });
    let loss = (1.0 - lam) * l1 + lam * (1.0 - ssim as f32) + config.lambda_opacity * lo;
    let psnr = psnr(
        &rendered,
        &wanted,
        Some(
            &view
                .excluded
                .par_iter()
                .map(|&x| x < 0.5)
                .collect::<Vec<_>>(),
        ),
    )
    .unwrap_or(0.0);
    StepLoss {
        loss,
        d_rgb,
        d_alpha,
        psnr,
    }
}

/// Where training starts.
#[derive(Debug, Clone)]
pub enum Start {
    Fresh(Splats),
    /// From a checkpoint written by an earlier run with the same settings.
    Resume(Box<TrainState>),
}

/// Everything training needs to continue exactly where it stopped: the
/// splats, Adam's moments, the densification statistics, the view order and
/// the random generator's position.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainState {
    /// Steps done.
    pub step: usize,
    pub splats: Splats,
    /// Scene extent measured at the start (it scales the position rate).
    pub extent: f32,
    /// First and second moments of the five parameter groups.
    pub moments: [(Vec<f32>, Vec<f32>); 5],
    pub grad2d_sum: Vec<f32>,
    pub grad2d_count: Vec<u32>,
    /// Views still to visit in this epoch (taken from the back).
    pub order: Vec<usize>,
    pub rng_word_pos: u128,
    /// The settings and views the state belongs to.
    pub fingerprint: String,
    /// The pose corrections and their moments, with pose refinement.
    pub poses: Option<crate::pose::PoseState>,
}

/// What a checkpoint must match to be resumed: the settings, the number of
/// views, and a digest of their cameras, so that a resumed run cannot go on
/// with views that moved (a merged capture's right arm under another
/// right-to-left transform, an edited capture).
pub(crate) fn fingerprint(config: &TrainConfig, views: &[impl TrainingView]) -> String {
    let mut digest = omniscan_core::digest::Digest::default();
    let mut add = |x: u32| digest.add(&x.to_le_bytes());
    for view in views {
        let c = view.camera();
        c.viewmat.iter().flatten().for_each(|v| add(v.to_bits()));
        [c.fx, c.fy, c.cx, c.cy, c.near, c.far]
            .iter()
            .for_each(|v| add(v.to_bits()));
        add(c.width);
        add(c.height);
    }
    format!("{config:?} views={} cameras={}", views.len(), digest.hex())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::Renderer;
    use crate::evaluation::{evaluate, evaluate_views};
    use crate::raster::Settings;
    use crate::trainer::{Checkpoints, train, train_resumable};

    /// Trains on the CPU without progress reports.
    fn fit(views: &[impl TrainingView], start: Splats, config: &TrainConfig) -> Splats {
        train(views, start, config, &Renderer::Cpu, &mut |_, _, _| {}).unwrap()
    }

    /// Four 48x36 views of a random scene, and a different scene to start from.
    fn problem() -> (Vec<View>, Splats) {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut random_splats = |n: usize, degree: usize| {
            let k = coefficients(degree);
            Splats {
                means: (0..n)
                    .map(|_| {
                        [
                            rng.random_range(-0.4..0.4),
                            rng.random_range(-0.3..0.3),
                            rng.random_range(1.8..2.2),
                        ]
                    })
                    .collect(),
                log_scales: (0..n)
                    .map(|_| [rng.random_range(-4.0f32..-2.5); 3])
                    .collect(),
                quats: (0..n)
                    .map(|_| [1.0, rng.random_range(-0.3..0.3), 0.0, 0.0])
                    .collect(),
                opacity_logits: (0..n).map(|_| rng.random_range(-1.0..2.0)).collect(),
                sh_degree: degree,
                sh: (0..n * k)
                    .map(|_| [0, 1, 2].map(|_| rng.random_range(-1.0f32..1.0)))
                    .collect(),
                antialiased: false,
                appearance: Default::default(),
            }
        };
        let truth = random_splats(150, 0).gaussians::<f32>();
        let start = random_splats(120, 1);
        let views = (0..4)
            .map(|i| {
                let camera = Camera {
                    viewmat: [
                        [1.0, 0.0, 0.0, 0.05 * i as f32],
                        [0.0, 1.0, 0.0, 0.0],
                        [0.0, 0.0, 1.0, 0.0],
                        [0.0, 0.0, 0.0, 1.0],
                    ],
                    fx: 50.0,
                    fy: 50.0,
                    cx: 24.0,
                    cy: 18.0,
                    width: 48,
                    height: 36,
                    near: 0.01,
                    far: 100.0,
                };
                let (_, r) = crate::raster::render(&truth, &camera, &Settings::default());
                View {
                    camera,
                    image: r.rgb.clone(),
                    object: r
                        .alpha
                        .iter()
                        .map(|&a| if a > 0.5 { 1.0 } else { 0.0 })
                        .collect(),
                    excluded: vec![0.0; r.alpha.len()],
                    depth: Vec::new(),
                }
            })
            .collect();
        (views, start)
    }

    /// Training and the visual hull read a packed view ([`crate::packed`])
    /// exactly as its floats: the same start and the same model, to the bit.
    #[test]
    fn packed_views_train_as_their_floats_do() {
        use crate::packed::PackedView;
        use omniscan_core::image_io::{Mask, RgbImage};
        let (views, start) = problem();
        let byte = |x: f32| (x.clamp(0.0, 1.0) * 255.0).round() as u8;
        for block in [1u32, 2] {
            let packed: Vec<PackedView> = views
                .iter()
                .map(|v| {
                    let (width, height) = (v.camera.width, v.camera.height);
                    let camera = Camera {
                        fx: v.camera.fx / block as f32,
                        fy: v.camera.fy / block as f32,
                        cx: v.camera.cx / block as f32,
                        cy: v.camera.cy / block as f32,
                        width: width / block,
                        height: height / block,
                        ..v.camera
                    };
                    let rgb = RgbImage {
                        width,
                        height,
                        data: v.image.iter().flat_map(|c| c.map(byte)).collect(),
                    };
                    let mask = |values: &[f32]| Mask {
                        width,
                        height,
                        data: values.iter().map(|&m| byte(m)).collect(),
                    };
                    // The left quarter is excluded, as a gripper would be.
                    let excluded: Vec<f32> = (0..v.object.len())
                        .map(|i| f32::from(u8::from(i % (width as usize) < 12)))
                        .collect();
                    PackedView::shrink(
                        camera,
                        &rgb,
                        &mask(&v.object),
                        Some(&mask(&excluded)),
                        None,
                        block,
                    )
                })
                .collect();
            let floats: Vec<View> = packed.iter().map(PackedView::unpack).collect();
            let config = TrainConfig::with_steps(30);
            assert_eq!(
                fit(&packed, start.clone(), &config),
                fit(&floats, start.clone(), &config),
                "block {block}"
            );
            assert_eq!(
                initial_splats(&packed, 300, 1, 5).unwrap(),
                initial_splats(&floats, 300, 1, 5).unwrap(),
                "block {block}"
            );
        }
    }

    /// 16 views of a ball of radius 0.1 at `centre`, from cameras on two
    /// rings of radius 1 around it, each looking at it; masks only.
    fn ball_views(centre: [f32; 3]) -> Vec<View> {
        let (width, height, focal) = (40u32, 30u32, 40.0f32);
        (0..16)
            .map(|i| {
                let azimuth = i as f32 * std::f32::consts::TAU / 8.0;
                let elevation: f32 = if i < 8 { 0.3 } else { -0.4 };
                let position = nalgebra::Vector3::new(
                    centre[0] + elevation.cos() * azimuth.cos(),
                    centre[1] + elevation.cos() * azimuth.sin(),
                    centre[2] + elevation.sin(),
                );
                let target = nalgebra::Vector3::from(centre);
                let forward = (target - position).normalize();
                let right = forward.cross(&nalgebra::Vector3::z()).normalize();
                let down = forward.cross(&right);
                let mut viewmat = [[0.0f32; 4]; 4];
                for (r, axis) in [right, down, forward].iter().enumerate() {
                    viewmat[r] = [axis.x, axis.y, axis.z, -axis.dot(&position)];
                }
                viewmat[3][3] = 1.0;
                // A pixel is on the ball where its ray passes within 0.1 of the centre.
                let object = (0..width * height)
                    .map(|p| {
                        let (u, v) = ((p % width) as f32 + 0.5, (p / width) as f32 + 0.5);
                        let ray = (forward
                            + right * ((u - width as f32 / 2.0) / focal)
                            + down * ((v - height as f32 / 2.0) / focal))
                            .normalize();
                        let to_centre = target - position;
                        let miss = (to_centre - ray * to_centre.dot(&ray)).norm();
                        f32::from(u8::from(miss < 0.1))
                    })
                    .collect();
                View {
                    camera: crate::test_support::pinhole(viewmat, focal, width, height),
                    image: vec![[0.5; 3]; (width * height) as usize],
                    object,
                    excluded: vec![0.0; (width * height) as usize],
                    depth: Vec::new(),
                }
            })
            .collect()
    }

    #[test]
    fn the_visual_hull_is_found_where_the_cameras_look() {
        for centre in [[0.0f32; 3], [3.0, -2.0, 1.0]] {
            let views = ball_views(centre);
            let looked_at = cameras_look_at(&views).unwrap();
            assert!(distance(looked_at, centre) < 1e-4, "{looked_at:?}");
            let splats = initial_splats(&views, 300, 0, 7).unwrap();
            assert_eq!(splats.means.len(), 300, "{centre:?}");
            // Every point within the ball, give or take the hull's slack.
            let farthest = splats
                .means
                .iter()
                .map(|&m| distance(m, centre))
                .fold(0.0, f32::max);
            assert!(farthest < 0.16, "{centre:?}: {farthest}");
        }
        // Cameras that all face one way fix no point.
        let mut parallel = ball_views([0.0; 3]);
        for v in &mut parallel {
            v.camera.viewmat = parallel_camera(v.camera.viewmat);
        }
        assert_eq!(cameras_look_at(&parallel), None);
    }

    #[test]
    fn the_hulls_batches_keep_the_points_one_by_one_judging_keeps() {
        let views = ball_views([0.2, -0.1, 0.05]);
        let (centre, half) = ([0.2f32, -0.1, 0.05], 0.35);
        // Enough points that the first batch runs out, and a count that a
        // batch reaches midway.
        for (count, seed) in [(2000, 3u64), (7, 4)] {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let (mut points, mut colours) = (Vec::new(), Vec::new());
            let mut tries = 0;
            while points.len() < count && tries < count * 400 {
                tries += 1;
                let p = hull_candidate(&mut rng, centre, half);
                if let Some(colour) = hull_colour(&views, p) {
                    points.push(p);
                    colours.push(colour);
                }
            }
            assert!(tries > HULL_BATCH || count < 10, "{tries} candidates");
            assert_eq!(
                visual_hull(&views, centre, half, count, seed),
                (points, colours)
            );
        }
    }

    /// A camera at the same place as `viewmat`'s, facing +y.
    fn parallel_camera(viewmat: [[f32; 4]; 4]) -> [[f32; 4]; 4] {
        let position = crate::raster::viewmat_centre(&viewmat);
        let rows = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]];
        let mut m = [[0.0f32; 4]; 4];
        for r in 0..3 {
            let t =
                -(rows[r][0] * position[0] + rows[r][1] * position[1] + rows[r][2] * position[2]);
            m[r] = [rows[r][0], rows[r][1], rows[r][2], t];
        }
        m[3][3] = 1.0;
        m
    }

    #[test]
    fn evaluation_gives_the_same_figures_on_any_number_of_threads() {
        let (views, model) = problem();
        let run = |threads: usize| {
            let seen = std::sync::Mutex::new(Vec::new());
            let report = crate::test_support::on_threads(threads, || {
                evaluate_views(
                    &model,
                    &Renderer::Cpu,
                    views.len(),
                    |i| Ok(std::borrow::Cow::Borrowed(&views[i])),
                    None,
                    |i, _, rgb| {
                        seen.lock().unwrap().push((i, rgb.to_vec()));
                        Ok(())
                    },
                )
            })
            .unwrap();
            let mut seen = seen.into_inner().unwrap();
            seen.sort_by_key(|(i, _)| *i);
            (report, seen)
        };
        let (one, renders) = run(1);
        assert_eq!(one.views, 4);
        assert!(one.psnr.unwrap().is_finite());
        // Every view rendered once, as the model renders it.
        assert_eq!(renders.len(), 4);
        for (i, rgb) in &renders {
            let (_, r) = crate::raster::render(
                &model.gaussians::<f32>(),
                &views[*i].camera,
                &model.render_settings([0.0; 3]),
            );
            assert_eq!(*rgb, r.rgb, "view {i}");
        }
        for threads in [2, 5] {
            assert_eq!(
                run(threads),
                (one.clone(), renders.clone()),
                "{threads} threads"
            );
        }
        assert_eq!(evaluate(&model, &views, None).unwrap(), one);
    }

    #[test]
    fn a_resumed_run_ends_with_the_model_of_an_uninterrupted_one() {
        // Pose refinement's corrections and moments are in the checkpoint too.
        let poses = crate::pose::PoseConfig {
            from_step: 3,
            ..Default::default()
        };
        for (densification, pose) in [
            (Densification::Adaptive, None),
            (Densification::Mcmc, None),
            (Densification::Adaptive, Some(poses)),
        ] {
            resumes_exactly(densification, pose);
        }
    }

    fn resumes_exactly(densification: Densification, pose: Option<crate::pose::PoseConfig>) {
        let (views, start) = problem();
        let config = TrainConfig {
            densify_from: 5,
            densify_every: 5,
            densify_until: 20,
            sh_interval: 8,
            reset_every: 15,
            densification,
            pose,
            ..TrainConfig::with_steps(24)
        };
        let straight = fit(&views, start.clone(), &config);
        // Stop after the checkpoint at step 12 (mid-epoch, after densification).
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("state.safetensors");
        let short = TrainConfig { ..config };
        let mut saved = 0;
        let mut save = |state: &TrainState| {
            saved += 1;
            if state.step == 12 {
                crate::checkpoint::save(state, &path)?;
            }
            Ok(())
        };
        train_resumable(
            &views,
            Start::Fresh(start.clone()),
            &short,
            &Renderer::Cpu,
            Some(Checkpoints {
                every: 4,
                save: &mut save,
            }),
            &mut |_, _, _| {},
        )
        .unwrap();
        assert_eq!(saved, 5, "checkpoints at 4, 8, 12, 16, 20");
        let state = crate::checkpoint::load(&path).unwrap();
        assert_eq!(state.step, 12);
        let mut steps = Vec::new();
        let resumed = train_resumable(
            &views,
            Start::Resume(Box::new(state.clone())),
            &config,
            &Renderer::Cpu,
            None,
            &mut |step, _, _| steps.push(step),
        )
        .unwrap();
        assert_eq!(steps.first(), Some(&13));
        assert_eq!(resumed, straight, "bit-identical to the uninterrupted run");
        // Other settings are refused, and so are views that moved, by as
        // little as a micrometre.
        let refusal = |views: &[View], config: &TrainConfig| {
            train_resumable(
                views,
                Start::Resume(Box::new(state.clone())),
                config,
                &Renderer::Cpu,
                None,
                &mut |_, _, _| {},
            )
            .unwrap_err()
            .to_string()
        };
        let err = refusal(&views, &TrainConfig { seed: 1, ..config });
        assert!(err.contains("other settings or views"), "{err}");
        let other_poses = match pose {
            Some(_) => None,
            None => Some(crate::pose::PoseConfig::default()),
        };
        let err = refusal(
            &views,
            &TrainConfig {
                pose: other_poses,
                ..config
            },
        );
        assert!(err.contains("other settings or views"), "{err}");
        let mut moved = views.clone();
        moved[0].camera.viewmat[0][3] += 1e-6;
        let err = refusal(&moved, &config);
        assert!(err.contains("other settings or views"), "{err}");
        // A checkpoint whose state no run could have reached is refused,
        // not resumed into another model.
        let resume = |state: TrainState| {
            train_resumable(
                &views,
                Start::Resume(Box::new(state)),
                &config,
                &Renderer::Cpu,
                None,
                &mut |_, _, _| {},
            )
            .unwrap_err()
            .to_string()
        };
        for extent in [0.0, -1.0, f32::NAN] {
            let err = resume(TrainState {
                extent,
                ..state.clone()
            });
            assert!(err.contains("scene extent"), "{err}");
        }
        let mut huge = state.clone();
        huge.moments[1].1[0] = f32::INFINITY;
        assert!(resume(huge).contains("Adam moments"));
    }

    /// The cap on the count holds from the first step: a start above it, or
    /// a cap of 0, is refused rather than trained on.
    #[test]
    fn a_start_above_the_cap_is_refused() {
        let (views, start) = problem();
        for cap in [0, start.len() - 1] {
            let config = TrainConfig {
                max_splats: cap,
                ..TrainConfig::with_steps(2)
            };
            let err = train(
                &views,
                start.clone(),
                &config,
                &Renderer::Cpu,
                &mut |_, _, _| {},
            )
            .unwrap_err();
            assert!(err.to_string().contains("the cap (max_splats)"), "{err}");
        }
        let config = TrainConfig {
            max_splats: start.len(),
            ..TrainConfig::with_steps(2)
        };
        assert!(train(&views, start, &config, &Renderer::Cpu, &mut |_, _, _| {}).is_ok());
    }

    /// MCMC training fits the views (its error falls well below the start's)
    /// and the count grows by 5% per refinement up to the cap.
    #[test]
    fn mcmc_fits_and_grows_to_its_cap() {
        let (views, start) = problem();
        let config = TrainConfig {
            densify_from: 20,
            densify_every: 20,
            max_splats: 140,
            ..TrainConfig::mcmc(300)
        };
        let error = |s: &Splats| -> f32 {
            let g = s.gaussians::<f32>();
            views
                .iter()
                .map(|v| {
                    let (_, r) = crate::raster::render(&g, &v.camera, &Settings::default());
                    r.rgb
                        .iter()
                        .zip(&v.image)
                        .map(|(a, b)| (0..3).map(|c| (a[c] - b[c]).abs()).sum::<f32>())
                        .sum::<f32>()
                })
                .sum()
        };
        let model = fit(&views, start.clone(), &config);
        assert_eq!(
            model.len(),
            140,
            "120 grows by 6, 6, 6 and is capped at 140"
        );
        // MCMC starts from half-opaque splats a tenth of their size.
        let mut prepared = start.clone();
        crate::mcmc::prepare(&mut prepared);
        let (before, after) = (error(&prepared), error(&model));
        assert!(
            after < 0.6 * before && after < error(&start),
            "L1 error {before} -> {after}"
        );
    }
}
