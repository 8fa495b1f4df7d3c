//! Pose refinement in training (issue 53): its flags, the view groups (a
//! capture's arms share a camera-side correction), test-time pose fitting
//! of the held-out views, and the report of the corrections, compared with
//! a simulated capture's true gripper poses where it has them
//! (`sim --pose-noise-deg/--pose-noise-mm`). The algorithm is
//! [`omniscan_splat::pose`]'s.

use anyhow::{Result, bail};
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

use omniscan_core::Arm;
use omniscan_splat::Splats;
use omniscan_splat::packed::PackedView;
use omniscan_splat::pose::{Correction, PoseConfig, PoseCorrections, corrected, fit_view};
use omniscan_splat::train::TrainConfig;
use omniscan_splat::views::ViewSource;

use crate::Progress;
use crate::settings::default_from_flags;

/// `train`'s (and `twin`'s) pose refinement flags.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PoseSettings {
    /// Learn a small correction of each view's recorded pose with the splats (and one camera-side correction per arm: its hand-eye offset), pulled toward the recorded pose; held-out views fit their own against the trained model before they are scored (test-time pose fitting), and the report gives the corrections. For real robots' calibration error. docs/train.md
    #[arg(long)]
    pub refine_poses: bool,
    /// Adam's rate for the corrections' rotations, radians per step (decayed to 1% over the run).
    #[arg(long, default_value_t = PoseConfig::default().rotation_lr)]
    pub pose_rotation_lr_rad: f64,
    /// Adam's rate for the corrections' translations, per unit of scene extent per step (decayed to 1%).
    #[arg(long, default_value_t = PoseConfig::default().translation_lr)]
    pub pose_translation_lr: f64,
    /// Weight of the pull toward the recorded poses: λ/2·(|ω|² + |t/extent|²) per correction, ω in radians.
    #[arg(long, default_value_t = PoseConfig::default().regularisation)]
    pub pose_regularisation: f64,
    /// The rate of each arm's shared camera-side correction (hand-eye offset), as a fraction of the views' rates (it steps at every step, a view's correction only when that view is drawn); 0: none.
    #[arg(long, default_value_t = PoseConfig::default().group_rate)]
    pub pose_arm_rate: f64,
    /// Poses stay as recorded for this many steps, while the first splats take shape.
    #[arg(long, default_value_t = PoseConfig::default().from_step)]
    pub pose_from_step: usize,
    /// Test-time pose fitting: Adam steps per held-out view.
    #[arg(long, default_value_t = omniscan_splat::pose::FIT_STEPS)]
    pub pose_fit_steps: usize,
}

default_from_flags!(PoseSettings);

impl PoseSettings {
    /// The trainer's pose configuration, `None` without --refine-poses.
    pub fn config(&self) -> Result<Option<PoseConfig>> {
        if !self.refine_poses {
            return Ok(None);
        }
        for (flag, value) in [
            ("--pose-rotation-lr-rad", self.pose_rotation_lr_rad),
            ("--pose-translation-lr", self.pose_translation_lr),
            ("--pose-regularisation", self.pose_regularisation),
            ("--pose-arm-rate", self.pose_arm_rate),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                bail!("{flag} must be a finite number, 0 or more, got {value}");
            }
        }
        Ok(Some(PoseConfig {
            rotation_lr: self.pose_rotation_lr_rad,
            translation_lr: self.pose_translation_lr,
            regularisation: self.pose_regularisation,
            group_rate: self.pose_arm_rate,
            from_step: self.pose_from_step,
        }))
    }
}

/// Each view's group, and the groups' names: a capture's arms (views of
/// both arms: left 0, right 1), or one group for a photo set.
pub fn view_groups(source: &ViewSource) -> (Vec<usize>, Vec<String>) {
    let Some((_, views)) = source.capture_views() else {
        return (vec![0; source.len()], vec!["all views".into()]);
    };
    let both = views.iter().any(|v| v.arm != views[0].arm);
    if !both {
        let arm = views.first().map_or(Arm::Left, |v| v.arm);
        return (vec![0; views.len()], vec![arm.name().into()]);
    }
    let group = |arm: Arm| usize::from(arm == Arm::Right);
    (
        views.iter().map(|v| group(v.arm)).collect(),
        vec!["left".into(), "right".into()],
    )
}

/// One view's correction: the recorded pose is corrected to
/// `gripper_to_world · correction` (in the model's frame: the gripper's for
/// one arm's model, the left gripper's for a merged one).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewPose {
    /// The view's index in the view set (as `eval`'s per-view figures).
    pub view: usize,
    /// The capture's frame it is (`frames[frame]`), for a capture.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frame: Option<usize>,
    pub rotation_deg: f64,
    pub translation_mm: f64,
    pub correction: Correction,
}

/// A group's camera-side correction: the camera's world-to-camera matrix
/// left-multiplied by it (a hand-eye offset).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GroupPose {
    /// The arm, or "all views".
    pub group: String,
    pub rotation_deg: f64,
    pub translation_mm: f64,
    pub correction: Correction,
}

/// How far poses are from a simulated capture's truth, up to the motion
/// common to all training views (which the model can take up): RMS over
/// the views of the rotation (degrees) and translation (mm) left.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseErrors {
    pub rms_rotation_deg: f64,
    pub rms_translation_mm: f64,
    pub max_rotation_deg: f64,
    pub max_translation_mm: f64,
    /// The translation's part across the view (perpendicular to the
    /// camera's optical axis), which moves the object in the image.
    pub rms_across_view_mm: f64,
    /// Its part along the optical axis, which only scales the object's
    /// image by a tiny amount and is hardly seen from one camera.
    pub rms_along_view_mm: f64,
    /// The rotation's part about the optical axis, which turns the object's
    /// image.
    pub rms_roll_deg: f64,
    /// Its part about axes across the view, which turns the object toward
    /// or away from the camera: hardly seen on a small, distant object.
    pub rms_tilt_deg: f64,
}

/// The recorded and the corrected poses against the truth.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AgainstTruth {
    /// The recorded poses of the training views (the calibration error).
    pub recorded: PoseErrors,
    /// The training views' corrected poses.
    pub train: PoseErrors,
    /// The held-out views' poses after test-time fitting.
    pub held_out: Option<PoseErrors>,
}

/// What pose refinement learned.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseReport {
    pub groups: Vec<GroupPose>,
    pub train: Vec<ViewPose>,
    /// Fitted at test time against the trained model.
    pub held_out: Vec<ViewPose>,
    /// Only for a simulated capture whose frames know their true poses.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub against_truth: Option<AgainstTruth>,
}

/// A trained model's views at their corrected poses, the held-out ones
/// fitted against the model first (`fitting`: the training configuration
/// and the Adam steps per view), and the report of the corrections.
pub fn at_corrected_poses(
    (model, source): (&Splats, &ViewSource),
    split: &Split<'_>,
    (train_views, test_views): (Vec<PackedView>, Vec<PackedView>),
    learned: &PoseCorrections,
    (config, steps): (&TrainConfig, usize),
    progress: &dyn Progress,
) -> Result<(Vec<PackedView>, Vec<PackedView>, PoseReport)> {
    let groups_of = |views: &[usize]| views.iter().map(|&i| split.groups[i]).collect::<Vec<_>>();
    let (train_groups, test_groups) = (groups_of(split.train), groups_of(split.held_out));
    let fitted = fit_held_out(
        model,
        &test_views,
        &test_groups,
        learned,
        config,
        steps,
        progress,
    )?;
    Ok((
        corrected_views(&train_views, &train_groups, &learned.views, learned),
        corrected_views(&test_views, &test_groups, &fitted, learned),
        report(source, split, learned, &fitted),
    ))
}

/// Test-time pose fitting: each held-out view's correction against the
/// frozen `model`, from its group's camera-side correction.
fn fit_held_out(
    model: &Splats,
    views: &[PackedView],
    groups: &[usize],
    learned: &PoseCorrections,
    config: &TrainConfig,
    steps: usize,
    progress: &dyn Progress,
) -> Result<Vec<Correction>> {
    progress.start("fitting held-out poses", views.len() as u64, "views");
    let fitted = views
        .iter()
        .zip(groups)
        .map(|(view, &g)| {
            let c = fit_view(
                model,
                view,
                &learned.groups[g],
                learned.centre_m,
                config,
                steps,
            )?;
            progress.advance();
            Ok(c)
        })
        .collect::<Result<Vec<_>>>();
    progress.finish();
    fitted
}

/// `views` seen through their corrections (`views[i]` by `corrections[i]`
/// and its group's).
fn corrected_views(
    views: &[PackedView],
    groups: &[usize],
    corrections: &[Correction],
    learned: &PoseCorrections,
) -> Vec<PackedView> {
    views
        .iter()
        .zip(groups.iter().zip(corrections))
        .map(|(view, (&g, c))| {
            let mut v = view.clone();
            v.camera = corrected(&view.camera, &learned.groups[g], c);
            v
        })
        .collect()
}

/// The view set's split: which views (indices into the set) were trained on
/// and which held out, with their groups.
pub struct Split<'a> {
    pub train: &'a [usize],
    pub held_out: &'a [usize],
    pub groups: &'a [usize],
    pub group_names: &'a [String],
}

/// The report of `learned` (training views) and `fitted` (held-out).
fn report(
    source: &ViewSource,
    split: &Split<'_>,
    learned: &PoseCorrections,
    fitted: &[Correction],
) -> PoseReport {
    PoseReport {
        groups: (learned.groups.iter().zip(split.group_names))
            .map(|(c, name)| GroupPose {
                group: name.clone(),
                rotation_deg: c.angle_deg(),
                translation_mm: c.offset_mm(),
                correction: *c,
            })
            .collect(),
        train: view_poses(source, split.train, &learned.views),
        held_out: view_poses(source, split.held_out, fitted),
        against_truth: against_truth(source, split, learned, fitted),
    }
}

/// `corrections[k]` as view `views[k]`'s entry of a report.
pub fn view_poses(
    source: &ViewSource,
    views: &[usize],
    corrections: &[Correction],
) -> Vec<ViewPose> {
    let frames = source.capture_views().map(|(_, v)| v);
    (views.iter().zip(corrections))
        .map(|(&view, c)| ViewPose {
            view,
            frame: frames.map(|f| f[view].frame_index),
            rotation_deg: c.angle_deg(),
            translation_mm: c.offset_mm(),
            correction: *c,
        })
        .collect()
}

/// The corrections' errors against a simulated capture's true gripper poses.
fn against_truth(
    source: &ViewSource,
    split: &Split<'_>,
    learned: &PoseCorrections,
    fitted: &[Correction],
) -> Option<AgainstTruth> {
    let (capture, views) = source.capture_views()?;
    let camera = capture.camera_to_world();
    // Each view's true model-side correction, and the one it has: the
    // group's camera-side correction carried to the model's side,
    // V⁻¹·C·V·P (V the recorded world-to-camera).
    let truth_and_effective = |view: usize, group: &Correction, own: &Correction| {
        let v = &views[view];
        let frame = &capture.file.frames[v.frame_index];
        let recorded = frame.gripper_to_world.0;
        let truth = frame.gt.as_ref()?.gripper_to_world.as_ref()?.0;
        // The model's frame from the gripper's (a merged model's right arm).
        let to_model = v.camera_to_object * camera.inverse() * recorded;
        let true_correction = to_model * recorded.inverse() * truth * to_model.inverse();
        let world_to_camera = v.camera_to_object.inverse();
        let effective =
            world_to_camera.inverse() * group.isometry() * world_to_camera * own.isometry();
        Some((true_correction, effective, world_to_camera.rotation))
    };
    let pairs = |indices: &[usize], own: &[Correction], zero: bool| {
        (indices.iter().zip(own))
            .map(|(&view, c)| {
                let group = &learned.groups[split.groups[view]];
                let (group, c) = if zero {
                    (&Correction::default(), &Correction::default())
                } else {
                    (group, c)
                };
                truth_and_effective(view, group, c)
            })
            .collect::<Option<Vec<_>>>()
    };
    let recorded = pairs(split.train, &learned.views, true)?;
    let trained = pairs(split.train, &learned.views, false)?;
    let held_out = pairs(split.held_out, fitted, false)?;
    let (train_errors, common) = errors_up_to_common(&trained);
    Some(AgainstTruth {
        recorded: errors_up_to_common(&recorded).0,
        train: train_errors,
        held_out: (!held_out.is_empty()).then(|| errors(&held_out, &common)),
    })
}

/// A view's true correction, the one it has, and its camera's rotation.
type Pair = (
    Isometry3<f64>,
    Isometry3<f64>,
    nalgebra::UnitQuaternion<f64>,
);

/// Each view's residual truth⁻¹·effective, which the common motion G of the
/// model's frame makes G for all views: the residuals' errors after G's
/// inverse, G their mean.
fn errors_up_to_common(pairs: &[Pair]) -> (PoseErrors, Isometry3<f64>) {
    let residuals: Vec<Correction> = pairs
        .iter()
        .map(|(t, e, _)| Correction::of(&(t.inverse() * e)))
        .collect();
    let common = omniscan_splat::pose::mean_motion(&residuals);
    (errors(pairs, &common), common)
}

/// The errors left in `pairs` after the common motion `common`.
fn errors(pairs: &[Pair], common: &Isometry3<f64>) -> PoseErrors {
    // Each view's rotation left (°), translation left (mm), that
    // translation across and along its camera's view, and the rotation
    // about the view's axis and across it (°).
    let left: Vec<[f64; 6]> = pairs
        .iter()
        .map(|(t, e, camera)| {
            let d = t.inverse() * e * common.inverse();
            let seen = camera * d.translation.vector * 1e3;
            let turn = (camera * d.rotation.scaled_axis()).map(f64::to_degrees);
            [
                d.rotation.angle().to_degrees(),
                seen.norm(),
                seen.xy().norm(),
                seen.z.abs(),
                turn.z.abs(),
                turn.xy().norm(),
            ]
        })
        .collect();
    let n = left.len().max(1) as f64;
    let rms = |k: usize| (left.iter().map(|x| x[k].powi(2)).sum::<f64>() / n).sqrt();
    let max = |k: usize| left.iter().map(|x| x[k]).fold(0.0, f64::max);
    PoseErrors {
        rms_rotation_deg: rms(0),
        rms_translation_mm: rms(1),
        max_rotation_deg: max(0),
        max_translation_mm: max(1),
        rms_across_view_mm: rms(2),
        rms_along_view_mm: rms(3),
        rms_roll_deg: rms(4),
        rms_tilt_deg: rms(5),
    }
}
