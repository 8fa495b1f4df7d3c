//! Camera pose refinement, learned with the splats (issue 53; after
//! gsplat's `pose_opt` and BARF's joint optimisation of poses and scene).
//!
//! A real robot's recorded gripper poses carry kinematic and hand-eye
//! calibration error. Each training view gets a small rigid correction
//! `P`, applied on the model's side: the corrected world-to-camera matrix is
//! `C·V·P`, with `V` the recorded one, so `P` is what the recorded gripper
//! pose is right-multiplied by (`gripper_to_world · P`, for a single arm's
//! model, whose frame is the gripper's). Each view group (an arm) shares a
//! correction `C` on the camera's side: a hand-eye offset, the same motion
//! of the camera for all the group's views.
//!
//! Gradients come from the rasterizer's camera gradient
//! ([`crate::backward::CameraGradient`]) through the adjoint and the SO(3)
//! Jacobians; each correction steps with its own Adam moments when its view
//! is rendered (a view's moments do not decay while other views train), and
//! an L2 pull toward the recorded pose keeps the common motion of all views,
//! which the model could take up as well, near zero. Held-out views fit
//! their own correction against the frozen model ([`fit_view`]) before
//! they are scored: test-time pose fitting.

use nalgebra::{Isometry3, Matrix3, Matrix4, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::SplatError;
use crate::backward::{CameraGradient, Wanted, backward_binned};
use crate::raster::{Camera, bin_tiles, project, rasterize_binned};
use crate::train::{TrainConfig, step_loss};
use crate::view::TrainingView;

/// Test-time pose fitting's Adam steps per view, unless told otherwise.
pub const FIT_STEPS: usize = 100;

/// How poses are refined; part of [`TrainConfig`] (and so of a
/// checkpoint's fingerprint).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseConfig {
    /// Adam's rate for the corrections' rotations, radians per step; decayed
    /// to 1% over the run.
    pub rotation_lr: f64,
    /// Adam's rate for their translations, per unit of scene extent;
    /// decayed to 1% over the run.
    pub translation_lr: f64,
    /// Weight of the pull toward the recorded pose: `λ/2 (|ω|² + |v/extent|²)`
    /// per correction, ω in radians.
    pub regularisation: f64,
    /// The rate of each view group's shared camera-side correction, as a
    /// fraction of the views' (it steps at every step, a view's only when
    /// the view is drawn); 0: none.
    pub group_rate: f64,
    /// Poses stay as recorded until this step, while the first splats take shape.
    pub from_step: usize,
}

impl Default for PoseConfig {
    fn default() -> Self {
        PoseConfig {
            rotation_lr: 2e-3,
            translation_lr: 5e-3,
            regularisation: 1e-4,
            group_rate: 0.1,
            from_step: 100,
        }
    }
}

/// A rigid correction: a rotation (axis times angle, radians) and then a
/// translation (metres).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Correction {
    pub rotation_rad: [f64; 3],
    pub translation_m: [f64; 3],
}

impl Correction {
    pub fn isometry(&self) -> Isometry3<f64> {
        Isometry3::new(
            Vector3::from(self.translation_m),
            Vector3::from(self.rotation_rad),
        )
    }

    /// The correction of `pose`.
    pub fn of(pose: &Isometry3<f64>) -> Correction {
        Correction {
            rotation_rad: pose.rotation.scaled_axis().into(),
            translation_m: pose.translation.vector.into(),
        }
    }

    pub fn angle_deg(&self) -> f64 {
        Vector3::from(self.rotation_rad).norm().to_degrees()
    }

    pub fn offset_mm(&self) -> f64 {
        Vector3::from(self.translation_m).norm() * 1e3
    }

    #[cfg(test)]
    fn params(&self) -> [f64; 6] {
        let (w, v) = (self.rotation_rad, self.translation_m);
        [w[0], w[1], w[2], v[0], v[1], v[2]]
    }

    #[cfg(test)]
    fn from_params(p: &[f64; 6]) -> Correction {
        Correction {
            rotation_rad: [p[0], p[1], p[2]],
            translation_m: [p[3], p[4], p[5]],
        }
    }
}

/// The corrections learned: one per view (model side), one per group
/// (camera side).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseCorrections {
    pub views: Vec<Correction>,
    pub groups: Vec<Correction>,
    /// The point, in the model's frame, that the views' corrections are
    /// learned as rotations about ([`rotation_centre`]), metres.
    pub centre_m: [f64; 3],
}

/// The point nearest all the cameras' optical axes (least squares), where
/// they look: the object. A view's correction is learned as a rotation
/// about it and a translation, nearly independent in their effect on the
/// image, where a rotation about the gripper's origin a few centimetres
/// away moves the object as much as a translation does. The origin if the
/// axes do not fix a point (all parallel).
pub fn rotation_centre<'a>(cameras: impl IntoIterator<Item = &'a Camera<f32>>) -> [f64; 3] {
    let mut a = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for camera in cameras {
        let v = &camera.viewmat;
        let centre = Vector3::from(crate::raster::viewmat_centre(v)).map(f64::from);
        // The optical axis: the camera's z axis, the third row of R.
        let axis = Vector3::new(v[2][0], v[2][1], v[2][2])
            .map(f64::from)
            .normalize();
        let off_axis = Matrix3::identity() - axis * axis.transpose();
        a += off_axis;
        b += off_axis * centre;
    }
    match a.try_inverse() {
        Some(inverse) if a.determinant().abs() > 1e-9 => (inverse * b).into(),
        _ => [0.0; 3],
    }
}

/// `camera` corrected: world-to-camera `C·V·P`.
pub fn corrected(camera: &Camera<f32>, group: &Correction, view: &Correction) -> Camera<f32> {
    let v = Matrix4::from_fn(|r, c| camera.viewmat[r][c] as f64);
    let m = group.isometry().to_homogeneous() * v * view.isometry().to_homogeneous();
    Camera {
        viewmat: std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)] as f32)),
        ..*camera
    }
}

fn hat(w: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -w.z, w.y, w.z, 0.0, -w.x, -w.y, w.x, 0.0)
}

/// SO(3)'s left Jacobian: exp(φ + δ) ≈ exp(J_l(φ)·δ)·exp(φ).
fn left_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let (a, b) = if theta < 1e-4 {
        (
            0.5 - theta * theta / 24.0,
            1.0 / 6.0 - theta * theta / 120.0,
        )
    } else {
        let t2 = theta * theta;
        (
            (1.0 - theta.cos()) / t2,
            (theta - theta.sin()) / (t2 * theta),
        )
    };
    let k = hat(phi);
    Matrix3::identity() + a * k + b * k * k
}

/// The gradients of the two corrections' parameters (rotation, then
/// translation) given the camera gradient `g` at the corrected
/// world-to-camera `full = C·V·P`.
fn parameter_gradients(
    g: &CameraGradient,
    full: &Matrix4<f64>,
    group: &Correction,
    view: &Correction,
) -> ([f64; 6], [f64; 6]) {
    let (g_v, g_w) = (Vector3::from(g.translation), Vector3::from(g.rotation));
    // The view's: a local motion P·exp(δ) is exp(Ad_F δ)·F on the camera side.
    let r_f = full.fixed_view::<3, 3>(0, 0).into_owned();
    let t_f = full.fixed_view::<3, 1>(0, 3).into_owned();
    let d_local_v = r_f.transpose() * g_v;
    let d_local_w = r_f.transpose() * (g_w + g_v.cross(&t_f));
    // Through the parameters: P = (exp(ω), v), P·exp(δ) = (exp(ω)exp(δω), v + exp(ω)δv),
    // and exp(ω + dω) ≈ exp(ω)·exp(J_r(ω)dω) with J_r(ω) = J_l(−ω).
    let w_p = Vector3::from(view.rotation_rad);
    let r_p = Rotation3::new(w_p);
    let d_view_w = left_jacobian(&-w_p).transpose() * d_local_w;
    let d_view_v = r_p * d_local_v;
    // The group's: exp(δ)·C = (exp(δω)exp(ω), exp(δω)v + δv).
    let (w_c, v_c) = (
        Vector3::from(group.rotation_rad),
        Vector3::from(group.translation_m),
    );
    let d_group_w = left_jacobian(&w_c).transpose() * (g_w + g_v.cross(&v_c));
    let six = |w: Vector3<f64>, v: Vector3<f64>| [w.x, w.y, w.z, v.x, v.y, v.z];
    (six(d_view_w, d_view_v), six(d_group_w, g_v))
}

const BETA1: f64 = 0.9;
const BETA2: f64 = 0.999;
const EPSILON: f64 = 1e-15;

/// One correction's parameters and Adam moments.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Learned {
    pub params: [f64; 6],
    pub m: [f64; 6],
    pub v: [f64; 6],
    /// Adam steps taken (bias correction counts these, not the run's steps).
    pub steps: u32,
}

impl Learned {
    /// The correction, its parameters being a rotation about `centre` and
    /// then a translation: x ↦ R(x − c) + c + u.
    pub fn correction(&self, centre: &Vector3<f64>) -> Correction {
        let rotation = Rotation3::new(Vector3::new(self.params[0], self.params[1], self.params[2]));
        let u = Vector3::new(self.params[3], self.params[4], self.params[5]);
        Correction {
            rotation_rad: [self.params[0], self.params[1], self.params[2]],
            translation_m: (centre - rotation * centre + u).into(),
        }
    }

    /// `d` (the gradient of the correction's rotation and translation) as
    /// the gradient of the parameters: with t = c − R(ω)c + u, dt/dω =
    /// (Rc)^·J_l(ω), so dL/dω = dL/dω|ₜ − J_lᵀ·((Rc) × dL/dt).
    fn about_centre(&self, d: [f64; 6], centre: &Vector3<f64>) -> [f64; 6] {
        let w = Vector3::new(self.params[0], self.params[1], self.params[2]);
        let rc = Rotation3::new(w) * centre;
        let d_t = Vector3::new(d[3], d[4], d[5]);
        let d_w = Vector3::new(d[0], d[1], d[2]) - left_jacobian(&w).transpose() * rc.cross(&d_t);
        [d_w.x, d_w.y, d_w.z, d[3], d[4], d[5]]
    }

    /// One Adam step on `grad` plus the pull toward zero; `rates`: rotation
    /// (rad) and translation (m) rates, `scale`: the scene extent (m).
    ///
    /// The second moment is shared by the three coordinates of the rotation
    /// and by those of the translation (Adam by blocks): per-coordinate
    /// Adam takes a full step along any axis, however faint its gradient,
    /// so the motions one camera hardly sees (along its axis, a tilt of a
    /// small object) walked about at the rate of those it sees; by blocks,
    /// each moves in proportion to how much the images say about it.
    fn step(&mut self, grad: &[f64; 6], rates: (f64, f64), regularisation: f64, scale: f64) {
        self.steps += 1;
        let t = self.steps as i32;
        let (c1, c2) = (1.0 - BETA1.powi(t), 1.0 - BETA2.powi(t));
        for block in [0, 3] {
            let (rate, unit) = match block {
                0 => (rates.0, 1.0),
                // A translation steps per unit of scene extent.
                _ => (rates.1, scale),
            };
            let g: [f64; 3] = std::array::from_fn(|a| {
                let k = block + a;
                (grad[k] + regularisation * self.params[k] / (unit * unit)) * unit
            });
            let squared = g.iter().map(|x| x * x).sum::<f64>() / 3.0;
            for (a, g) in g.iter().enumerate() {
                let k = block + a;
                self.m[k] = BETA1 * self.m[k] + (1.0 - BETA1) * g;
                self.v[k] = BETA2 * self.v[k] + (1.0 - BETA2) * squared;
                let step = rate * (self.m[k] / c1) / ((self.v[k] / c2).sqrt() + EPSILON);
                self.params[k] -= step * unit;
            }
        }
    }
}

/// The refinement's whole state, as a checkpoint keeps it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PoseState {
    pub views: Vec<Learned>,
    pub groups: Vec<Learned>,
}

impl PoseState {
    pub fn new(views: usize, groups: usize) -> PoseState {
        PoseState {
            views: vec![Learned::default(); views],
            groups: vec![Learned::default(); groups],
        }
    }

    /// The corrections, the views' learned about `centre`.
    pub fn corrections(&self, centre: [f64; 3]) -> PoseCorrections {
        let c = Vector3::from(centre);
        PoseCorrections {
            views: self.views.iter().map(|l| l.correction(&c)).collect(),
            groups: (self.groups.iter())
                .map(|l| l.correction(&Vector3::zeros()))
                .collect(),
            centre_m: centre,
        }
    }

    /// Refuses a state whose numbers are not finite.
    pub fn validate(&self) -> Result<(), SplatError> {
        let finite = |l: &Learned| {
            l.params
                .iter()
                .chain(&l.m)
                .chain(&l.v)
                .all(|x| x.is_finite())
        };
        if !self.views.iter().chain(&self.groups).all(finite) {
            return Err(SplatError::Invalid(
                "the pose corrections hold numbers that are not finite".into(),
            ));
        }
        Ok(())
    }
}

/// Pose refinement in a training run: the state and which group each
/// view is in.
#[derive(Debug, Clone)]
pub(crate) struct PoseRefiner {
    pub config: PoseConfig,
    pub state: PoseState,
    pub group_of: Vec<usize>,
    /// What the views' corrections rotate about ([`rotation_centre`]).
    pub centre: Vector3<f64>,
}

impl PoseRefiner {
    /// View `index`'s camera under its corrections.
    pub fn camera(&self, index: usize, camera: &Camera<f32>) -> Camera<f32> {
        let group = self.state.groups[self.group_of[index]].correction(&Vector3::zeros());
        corrected(
            camera,
            &group,
            &self.state.views[index].correction(&self.centre),
        )
    }

    /// Steps view `index`'s corrections (and its group's) by the camera
    /// gradient `g` of the step's loss, rendered at `corrected` (the view's
    /// camera under its corrections, [`PoseRefiner::camera`]).
    pub fn step(
        &mut self,
        index: usize,
        corrected: &Camera<f32>,
        g: &CameraGradient,
        step: usize,
        steps: usize,
        extent: f64,
    ) {
        // A render with no splats in sight gives no gradient to follow; one
        // that is not finite would spoil the corrections for good.
        let finite = g
            .translation
            .iter()
            .chain(&g.rotation)
            .all(|x| x.is_finite());
        if step < self.config.from_step || !finite {
            return;
        }
        let decay = 0.01f64.powf(step as f64 / steps.max(1) as f64);
        let rates = (
            self.config.rotation_lr * decay,
            self.config.translation_lr * decay,
        );
        let group_index = self.group_of[index];
        let group = self.state.groups[group_index].correction(&Vector3::zeros());
        let view = self.state.views[index].correction(&self.centre);
        let full = Matrix4::from_fn(|r, c| corrected.viewmat[r][c] as f64);
        let (d_view, d_group) = parameter_gradients(g, &full, &group, &view);
        let d_view = self.state.views[index].about_centre(d_view, &self.centre);
        let lambda = self.config.regularisation;
        self.state.views[index].step(&d_view, rates, lambda, extent);
        if self.config.group_rate > 0.0 {
            let scale = self.config.group_rate;
            let group_rates = (rates.0 * scale, rates.1 * scale);
            // The camera's motion along its own axis is left alone: from
            // one camera it looks like a change of the object's scale, which
            // the splats take up, and the offset drifted millimetres along
            // it in the benchmark (docs/results.md).
            let mut d_group = d_group;
            d_group[5] = 0.0;
            self.state.groups[group_index].step(&d_group, group_rates, lambda, extent);
        }
    }
}

/// Test-time pose fitting: the correction that best fits `view`'s pixels to
/// the frozen `model`, starting from the recorded pose with `group`'s
/// camera-side correction, learned about `centre` as in training,
/// `iterations` Adam steps at `config`'s refinement rates (decayed to 1%),
/// the training loss on a black background.
pub fn fit_view(
    model: &crate::Splats,
    view: &impl TrainingView,
    group: &Correction,
    centre: [f64; 3],
    config: &TrainConfig,
    iterations: usize,
) -> Result<Correction, SplatError> {
    let centre = Vector3::from(centre);
    let pose = config.pose.unwrap_or_default();
    let extent = f64::from(crate::trainer::extent(model));
    let mut scratch = None;
    let pixels = view.pixels_in(&mut scratch);
    let g = model.gaussians_up_to::<f32>(model.sh_degree);
    let background = [0.0; 3];
    let settings = model.render_settings(background);
    let mut learned = Learned::default();
    for i in 0..iterations {
        let camera = corrected(&pixels.camera, group, &learned.correction(&centre));
        let p = project(&g, &camera, &settings);
        let bins = bin_tiles(&p, camera.width, camera.height);
        let r = rasterize_binned(&bins, camera.width, camera.height, background);
        let loss = step_loss(pixels, &r, background, config);
        let (_, gradient) = backward_binned(
            &g,
            &camera,
            &settings,
            &p,
            &bins,
            &loss.d_rgb,
            &loss.d_alpha,
            Wanted {
                absolute: false,
                camera: true,
            },
        );
        if !(gradient.translation.iter().chain(&gradient.rotation)).all(|x| x.is_finite()) {
            return Err(SplatError::Invalid(
                "test-time pose fitting met a gradient that is not finite".into(),
            ));
        }
        let full = Matrix4::from_fn(|r, c| camera.viewmat[r][c] as f64);
        let (d_view, _) =
            parameter_gradients(&gradient, &full, group, &learned.correction(&centre));
        let d_view = learned.about_centre(d_view, &centre);
        let decay = 0.01f64.powf(i as f64 / iterations.max(1) as f64);
        let rates = (pose.rotation_lr * decay, pose.translation_lr * decay);
        learned.step(&d_view, rates, pose.regularisation, extent);
    }
    Ok(learned.correction(&centre))
}

/// The mean of `corrections` as a rigid motion (rotation by the normalised
/// quaternion sum); the identity for none. The model can take up a motion
/// shared by all views, so corrections are compared with the truth up to
/// it: each right-multiplied by its inverse.
pub fn mean_motion(corrections: &[Correction]) -> Isometry3<f64> {
    let Some(first) = corrections.first() else {
        return Isometry3::identity();
    };
    let first = first.isometry().rotation;
    let mut q = nalgebra::Vector4::zeros();
    let mut t = Vector3::zeros();
    for c in corrections {
        let r = c.isometry().rotation;
        let sign = if r.coords.dot(&first.coords) < 0.0 {
            -1.0
        } else {
            1.0
        };
        q += r.coords * sign;
        t += Vector3::from(c.translation_m);
    }
    Isometry3::from_parts(
        Translation3::from(t / corrections.len() as f64),
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::from(q)),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn left_jacobian_matches_the_exponential() {
        let phi = Vector3::new(0.3, -0.2, 0.5);
        let delta = Vector3::new(1e-6, -2e-6, 0.5e-6);
        let exact = Rotation3::new(phi + delta) * Rotation3::new(phi).inverse();
        let predicted = Rotation3::new(left_jacobian(&phi) * delta);
        assert!((exact.scaled_axis() - predicted.scaled_axis()).norm() < 1e-11);
        assert!((left_jacobian(&(phi * 1e-6)) - Matrix3::identity()).norm() < 1e-6);
    }

    /// The parameter gradients are the camera gradient carried through
    /// `C·V·P`: checked with a linear loss in the corrected matrix's camera
    /// motion, against central differences of the parameters.
    #[test]
    fn parameter_gradients_match_central_differences() {
        let v = Isometry3::new(Vector3::new(0.1, -0.05, 0.4), Vector3::new(0.4, 1.1, -0.3))
            .to_homogeneous();
        let group = Correction {
            rotation_rad: [0.01, -0.02, 0.015],
            translation_m: [0.002, 0.001, -0.003],
        };
        let view = Correction {
            rotation_rad: [-0.02, 0.01, 0.03],
            translation_m: [-0.001, 0.004, 0.002],
        };
        // A loss whose camera gradient is `g` at `full`: L(F') = ⟨g, log(F'·F⁻¹)⟩.
        let g = CameraGradient {
            translation: [0.3, -0.7, 1.1],
            rotation: [0.5, 0.2, -0.9],
        };
        let full = |c: &Correction, p: &Correction| {
            c.isometry().to_homogeneous() * v * p.isometry().to_homogeneous()
        };
        let f0 = full(&group, &view);
        let loss = |c: &Correction, p: &Correction| {
            let m = full(c, p) * f0.try_inverse().unwrap();
            let r = Rotation3::from_matrix_unchecked(m.fixed_view::<3, 3>(0, 0).into_owned());
            let w = UnitQuaternion::from_rotation_matrix(&r).scaled_axis();
            let t = m.fixed_view::<3, 1>(0, 3).into_owned();
            // To first order the motion is u ↦ u + ω × u + t.
            (0..3)
                .map(|k| g.translation[k] * t[k] + g.rotation[k] * w[k])
                .sum::<f64>()
        };
        let (d_view, d_group) = parameter_gradients(&g, &f0, &group, &view);
        let h = 1e-7;
        for k in 0..6 {
            let nudge = |c: &Correction, e: f64| {
                let mut p = c.params();
                p[k] += e;
                Correction::from_params(&p)
            };
            let fd_view =
                (loss(&group, &nudge(&view, h)) - loss(&group, &nudge(&view, -h))) / (2.0 * h);
            let fd_group =
                (loss(&nudge(&group, h), &view) - loss(&nudge(&group, -h), &view)) / (2.0 * h);
            assert!(
                (d_view[k] - fd_view).abs() < 1e-6,
                "view {k}: {} vs {fd_view}",
                d_view[k]
            );
            assert!(
                (d_group[k] - fd_group).abs() < 1e-6,
                "group {k}: {} vs {fd_group}",
                d_group[k]
            );
        }
    }

    /// The gradient of a loss of the correction, carried to parameters
    /// that rotate about a centre, against central differences.
    #[test]
    fn centred_parameters_match_central_differences() {
        let centre = Vector3::new(0.02, -0.05, 0.3);
        let learned = Learned {
            params: [0.01, -0.03, 0.02, 0.001, -0.002, 0.004],
            ..Default::default()
        };
        // A loss of the correction's isometry: a weighted sum of its
        // rotation vector and translation.
        let weights = [0.3, -0.5, 0.8, 1.5, 0.7, -1.1];
        let loss = |l: &Learned| {
            let c = l.correction(&centre);
            let w = c.isometry().rotation.scaled_axis();
            (0..3)
                .map(|k| weights[k] * w[k] + weights[3 + k] * c.translation_m[k])
                .sum::<f64>()
        };
        let d = learned.about_centre(weights, &centre);
        let h = 1e-7;
        for k in 0..6 {
            let nudged = |e: f64| {
                let mut l = learned;
                l.params[k] += e;
                loss(&l)
            };
            let numeric = (nudged(h) - nudged(-h)) / (2.0 * h);
            assert!((d[k] - numeric).abs() < 1e-6, "{k}: {} vs {numeric}", d[k]);
        }
    }

    #[test]
    fn rotation_centre_is_where_the_cameras_look() {
        let target = Vector3::new(0.1, -0.2, 0.05);
        let cameras: Vec<Camera<f32>> = [[1.0, 0.2, 0.3], [-0.5, 1.0, 0.1], [0.2, -0.4, 1.0]]
            .iter()
            .map(|eye| {
                let eye = nalgebra::Point3::from(Vector3::from(*eye) + target);
                let view =
                    Isometry3::look_at_rh(&eye, &nalgebra::Point3::from(target), &Vector3::z());
                // look_at_rh looks down −z; OpenCV cameras look down +z.
                let flip = Isometry3::rotation(Vector3::new(std::f64::consts::PI, 0.0, 0.0));
                let m = (flip * view).to_homogeneous();
                Camera {
                    viewmat: std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)] as f32)),
                    fx: 100.0,
                    fy: 100.0,
                    cx: 50.0,
                    cy: 50.0,
                    width: 100,
                    height: 100,
                    near: 0.01,
                    far: 10.0,
                }
            })
            .collect();
        let centre = Vector3::from(rotation_centre(&cameras));
        assert!((centre - target).norm() < 1e-5, "{centre:?}");
        assert_eq!(rotation_centre(&cameras[..1]), [0.0; 3]);
    }

    /// Test-time fitting against the true model finds the error put into
    /// a view's recorded pose.
    #[test]
    fn fitting_a_view_against_the_true_model_recovers_its_pose_error() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let n = 400;
        let model = crate::Splats {
            means: (0..n)
                .map(|_| {
                    [
                        rng.random_range(-0.3..0.3),
                        rng.random_range(-0.25..0.25),
                        rng.random_range(1.8..2.2),
                    ]
                })
                .collect(),
            log_scales: (0..n)
                .map(|_| [rng.random_range(-4.0f32..-3.0); 3])
                .collect(),
            quats: vec![[1.0, 0.0, 0.0, 0.0]; n],
            opacity_logits: vec![3.0; n],
            sh_degree: 0,
            sh: (0..n)
                .map(|_| [0, 1, 2].map(|_| rng.random_range(-1.5f32..1.5)))
                .collect(),
            antialiased: false,
            appearance: Default::default(),
        };
        let true_camera = Camera {
            viewmat: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 0.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
            fx: 120.0,
            fy: 120.0,
            cx: 48.0,
            cy: 36.0,
            width: 96,
            height: 72,
            near: 0.01,
            far: 100.0,
        };
        let (_, r) = crate::raster::render(
            &model.gaussians::<f32>(),
            &true_camera,
            &model.render_settings([0.0; 3]),
        );
        let error = Correction {
            rotation_rad: [0.01, -0.015, 0.03],
            translation_m: [0.03, -0.02, 0.01],
        };
        // Recorded so that the correction `error` brings it back: V·P = V_true.
        let inverse = Correction::of(&error.isometry().inverse());
        let recorded = corrected(&true_camera, &Correction::default(), &inverse);
        let view = crate::view::View {
            camera: recorded,
            image: r.rgb.clone(),
            object: vec![1.0; r.rgb.len()],
            excluded: vec![0.0; r.rgb.len()],
            depth: Vec::new(),
        };
        let config = TrainConfig {
            pose: Some(PoseConfig::default()),
            ..TrainConfig::with_steps(100)
        };
        let centre = rotation_centre([&true_camera]);
        assert_eq!(centre, [0.0; 3], "one camera fixes no point");
        let fitted = fit_view(
            &model,
            &view,
            &Correction::default(),
            [0.0, 0.0, 2.0],
            &config,
            200,
        )
        .unwrap();
        // What a view fixes is where the model lands in its image (motion
        // along the optical axis, or a tilt against a sideways shift, hardly
        // shows): the splats' mean displacement from where the true camera
        // puts them, in pixels.
        let displacement = |c: &Correction| {
            let camera = corrected(&recorded, &Correction::default(), c);
            let pixel = |cam: &Camera<f32>, m: &[f32; 3]| {
                let v = &cam.viewmat;
                let p =
                    [0, 1, 2].map(|r| v[r][0] * m[0] + v[r][1] * m[1] + v[r][2] * m[2] + v[r][3]);
                [cam.fx * p[0] / p[2], cam.fy * p[1] / p[2]]
            };
            let sum: f32 = (model.means.iter())
                .map(|m| {
                    let (a, b) = (pixel(&camera, m), pixel(&true_camera, m));
                    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
                })
                .sum();
            sum / model.means.len() as f32
        };
        let (before, after) = (displacement(&Correction::default()), displacement(&fitted));
        assert!(
            before > 2.0 && after < 0.2 * before,
            "fitted {fitted:?} against {error:?}: {after} px from {before} px"
        );
        // The turn about the optical axis shows, and is found.
        assert!(
            (fitted.rotation_rad[2] - error.rotation_rad[2]).abs() < 0.1 * error.rotation_rad[2],
            "{fitted:?}"
        );
    }

    #[test]
    fn common_motion_is_taken_out() {
        let common = Isometry3::new(Vector3::new(0.01, 0.0, -0.02), Vector3::new(0.0, 0.05, 0.0));
        let own = [
            Correction {
                rotation_rad: [0.01, 0.0, 0.0],
                translation_m: [0.001, 0.0, 0.0],
            },
            Correction {
                rotation_rad: [-0.01, 0.0, 0.0],
                translation_m: [-0.001, 0.0, 0.0],
            },
        ];
        let moved: Vec<_> = own
            .iter()
            .map(|c| Correction::of(&(c.isometry() * common)))
            .collect();
        let inverse = mean_motion(&moved).inverse();
        for (a, b) in moved.iter().zip(&own) {
            let (rad, m) =
                omniscan_core::geometry::pose_difference(&(a.isometry() * inverse), &b.isometry());
            let (deg, mm) = (rad.to_degrees(), m * 1e3);
            assert!(deg < 1e-3 && mm < 1e-3, "{deg}° {mm} mm");
        }
    }
}
