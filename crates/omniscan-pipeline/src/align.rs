//! Aligning a source cloud or model onto a target ("3DGS Training", the
//! merge): ICP with Open3D's semantics, colored ICP, generalized ICP, the
//! paper's rule (the better of ICP and colored ICP from the handover
//! estimate T_lh⁻¹·T_rh), global registration without an initial guess,
//! and a photometric refinement that renders the target model into the
//! right arm's views (`omniscan_splat::offset`). Also the paper's merge of
//! a capture's two depth scans, [`merge_scans`].

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use omniscan_core::geometry::{pose_difference, pose_to_rows};
use omniscan_core::{Arm, Pose};
use omniscan_register::PointCloud;
use omniscan_register::cloud::read_cloud;
use omniscan_register::global::{
    GlobalSettings, global_registration, median_spacing, refine_from_initial,
};
use omniscan_register::icp::{Criteria, Estimator, Kernel, Registration, Target, evaluate, icp};
use omniscan_register::preprocess::{estimate_normals, voxel_downsample};

use crate::settings::default_from_flags;

/// Registration methods.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Point-to-point ICP.
    Icp,
    /// Point-to-plane ICP.
    Plane,
    /// Colored ICP (needs colours on both clouds).
    Colored,
    /// Generalized ICP, plane to plane (Segal et al. 2009; Open3D's epsilon 1e-3).
    Gicp,
    /// The paper's rule: ICP and colored ICP from the initial transform, the better fitness wins (the lower RMSE within 0.02 of fitness).
    #[default]
    Auto,
    /// FPFH features, TEASER++-style and RANSAC hypotheses, refined by ICP; no initial transform needed.
    Global,
}

/// Everything `align` can be told besides its two clouds and output.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AlignSettings {
    /// Initial transform (JSON: a 4x4 matrix or {"transform": ...}); identity if absent.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// Start from this capture's handover estimate T_lh⁻¹·T_rh instead, as the paper's merge
    /// does: SOURCE is the right arm's model (or cloud), TARGET the left's, each in its gripper's
    /// frame. The transform written then goes to `omniscan train --arm both --right-to-left`.
    #[arg(long, conflicts_with = "init")]
    pub handover: Option<PathBuf>,
    #[arg(long, value_enum, default_value = "auto")]
    pub method: Method,
    /// Correspondence distance, in the clouds' units (metres for captures); default: target extent / 50.
    #[arg(long)]
    pub max_distance: Option<f64>,
    /// Voxel size for global registration, in the clouds' units; default: chosen to leave about 1200 points.
    #[arg(long)]
    pub voxel: Option<f64>,
    /// Maximum ICP iterations.
    #[arg(long, default_value_t = 30)]
    pub iterations: usize,
    /// After the point registration, refine the transform by the images (needs --handover, and
    /// TARGET a splat model): render TARGET into the capture's right-arm views and fit the rigid
    /// offset that best matches their object pixels. The views `train` holds out by default
    /// (every 8th of the merged set) are left out, so a merged model's held-out figures stay unseen.
    #[arg(long, requires = "handover")]
    pub photometric: bool,
    /// Shrink the capture's images by this integer factor for --photometric (1: full size).
    #[arg(long, default_value_t = 2)]
    pub downscale: u32,
    /// With --photometric: fit a simulated capture without masks of its own on the simulator's ground-truth masks (as `train --use-ground-truth-masks`).
    #[arg(long)]
    pub use_ground_truth_masks: bool,
}

default_from_flags!(AlignSettings);

/// What the photometric refinement found, and the point registration's
/// transform it started from (4x4 row-major).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PhotometricFit {
    #[serde(flatten)]
    pub found: omniscan_splat::offset::OffsetRefinement,
    pub from: [[f64; 4]; 4],
}

/// What [`align`] found; also the file it writes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AlignReport {
    /// Maps SOURCE into TARGET, 4x4 row-major, the clouds' units.
    pub transform: [[f64; 4]; 4],
    pub fitness: f64,
    pub inlier_rmse: f64,
    pub method: String,
    pub max_distance: f64,
    pub iterations: usize,
    pub correspondences: usize,
    pub source: PathBuf,
    pub target: PathBuf,
    pub source_points: usize,
    pub target_points: usize,
    pub seconds: f64,
    /// The method's own figures: every candidate of the paper's rule, or
    /// the global registration's features and hypotheses.
    pub details: serde_json::Value,
    pub photometric: Option<PhotometricFit>,
    pub units: String,
}

impl AlignReport {
    pub fn transform(&self) -> Result<Pose> {
        Ok(omniscan_core::geometry::pose_from_rows(&self.transform)?)
    }
}

fn with_normals(cloud: &PointCloud) -> PointCloud {
    let mut c = cloud.clone();
    if !c.has_normals() {
        let spacing = median_spacing(&c);
        estimate_normals(&mut c, (4.0 * spacing).max(1e-12), 30);
    }
    c
}

/// Registers `source` (a point cloud or splat model: .ply, .pcd, .xyz) onto
/// `target`, writes the report to `out` (JSON) and returns it.
pub fn align(
    source_path: &Path,
    target_path: &Path,
    out: &Path,
    settings: &AlignSettings,
) -> Result<AlignReport> {
    let source = read_cloud(source_path)?;
    let target = read_cloud(target_path)?;
    let init = match (&settings.init, &settings.handover) {
        (Some(p), _) => crate::views::read_transform(p)?,
        (None, Some(capture)) => {
            omniscan_core::poses::handover_estimate(&omniscan_core::Capture::load(capture)?)
        }
        (None, None) => Pose::identity(),
    };
    let extent = target.extent();
    if settings.max_distance.is_none() && !(extent.is_finite() && extent > 0.0) {
        bail!(
            "{}: its {} point(s) span no distance, from which the correspondence distance is chosen: give --max-distance",
            target_path.display(),
            target.len()
        );
    }
    let max_distance = settings.max_distance.unwrap_or(extent / 50.0);
    if max_distance.is_nan() || max_distance <= 0.0 || max_distance.is_infinite() {
        bail!("--max-distance must be positive (units of the clouds), got {max_distance}");
    }
    let criteria = Criteria {
        max_iteration: settings.iterations,
        ..Criteria::default()
    };
    let start = Instant::now();
    let (method, registration, details) =
        register(&source, &target, &init, max_distance, &criteria, settings)?;
    let (registration, photometric) = match &settings.handover {
        Some(capture) if settings.photometric => {
            let from = registration.transformation;
            let (refined, fit) = refine_by_images(target_path, capture, &from, settings)?;
            // Fitness and RMSE of the transform written, not of the points' own optimum.
            let scored = evaluate(&source, &Target::new(&target), max_distance, &refined);
            let registration = Registration {
                iterations: registration.iterations,
                ..scored
            };
            (registration, Some(fit))
        }
        _ => (registration, None),
    };
    let report = AlignReport {
        transform: pose_to_rows(&registration.transformation),
        fitness: registration.fitness,
        inlier_rmse: registration.inlier_rmse,
        method,
        max_distance,
        iterations: registration.iterations,
        correspondences: registration.correspondences,
        source: source_path.to_path_buf(),
        target: target_path.to_path_buf(),
        source_points: source.len(),
        target_points: target.len(),
        seconds: start.elapsed().as_secs_f64(),
        details,
        photometric,
        units: "transform maps SOURCE into TARGET, in the clouds' own units (metres for captures)"
            .into(),
    };
    omniscan_core::io::write_json_atomic(out, &report)?;
    Ok(report)
}

/// The point registration by `settings.method`: its name, result and figures.
fn register(
    source: &PointCloud,
    target: &PointCloud,
    init: &Pose,
    max_distance: f64,
    criteria: &Criteria,
    settings: &AlignSettings,
) -> Result<(String, Registration, serde_json::Value)> {
    Ok(match settings.method {
        Method::Icp | Method::Plane | Method::Colored | Method::Gicp => {
            let estimator = match settings.method {
                Method::Icp => Estimator::PointToPoint,
                Method::Plane => Estimator::PointToPlane,
                Method::Gicp => Estimator::GENERALIZED,
                _ => Estimator::COLORED,
            };
            let t = if matches!(estimator, Estimator::PointToPoint) {
                target.clone()
            } else {
                with_normals(target)
            };
            // Generalized ICP reads the source's planes too.
            let source = if matches!(estimator, Estimator::Generalized { .. }) {
                std::borrow::Cow::Owned(with_normals(source))
            } else {
                std::borrow::Cow::Borrowed(source)
            };
            let r = icp(
                &source,
                &Target::new(&t),
                max_distance,
                init,
                estimator,
                Kernel::L2,
                criteria,
            )?;
            (estimator.name().into(), r, serde_json::json!([]))
        }
        Method::Auto => {
            let (best, all) = refine_from_initial(source, target, init, max_distance, criteria)?;
            let details = serde_json::to_value(&all)?;
            (best.method.into(), best.registration, details)
        }
        Method::Global => {
            let global = GlobalSettings {
                voxel: settings.voxel,
                ..GlobalSettings::default()
            };
            let r = global_registration(source, target, &global)?;
            let details = serde_json::json!({"voxel": r.voxel, "correspondences": r.correspondences, "clique_size": r.clique_size, "clique_exact": r.clique_exact, "hypotheses": r.candidates});
            (
                format!("global/{}", r.best.method),
                r.best.registration,
                details,
            )
        }
    })
}

/// `--photometric`: the point registration's right-to-left transform
/// refined by rendering the left arm's model (`model`) into the right arm's
/// training views (see `omniscan_splat::offset`).
fn refine_by_images(
    model: &Path,
    capture_path: &Path,
    right_to_left: &Pose,
    settings: &AlignSettings,
) -> Result<(Pose, PhotometricFit)> {
    use omniscan_core::poses::{ViewSet, camera_views};
    use omniscan_splat::views::{ViewSource, split_held_out};
    let model = omniscan_splat::ply::read_splats(model)
        .context("--photometric renders TARGET, which must be a splat model")?;
    let capture = omniscan_core::Capture::load(capture_path)?;
    let set = ViewSet::Merged {
        right_to_left: *right_to_left,
    };
    let arms: Vec<Arm> = camera_views(&capture, set).iter().map(|v| v.arm).collect();
    // Only the right arm's training views are fitted, so only they are read.
    let (training, _) = split_held_out(arms.into_iter().enumerate().collect(), 8);
    let indices: Vec<usize> = training
        .into_iter()
        .filter(|(_, arm)| *arm == Arm::Right)
        .map(|(i, _)| i)
        .collect();
    let right = ViewSource::from_capture(&capture, set, settings.downscale)
        .and_then(|source| {
            source
                .with_ground_truth_masks(settings.use_ground_truth_masks)
                .load_each(&indices)
        })
        .with_context(|| format!("--photometric: the views of {}", capture_path.display()))?;
    if right.is_empty() {
        bail!(
            "--photometric: {} has no right-arm views to fit",
            capture_path.display()
        );
    }
    let found = omniscan_splat::offset::refine_offset(
        &model,
        &right,
        &omniscan_splat::offset::OffsetConfig::default(),
    )
    .context("--photometric")?;
    let offset = found.offset;
    let fit = PhotometricFit {
        found,
        from: pose_to_rows(right_to_left),
    };
    // The views saw the model through V·R2L⁻¹·D: the right-to-left transform is D⁻¹·R2L.
    Ok((offset.inverse() * right_to_left, fit))
}

/// One candidate of the paper's merge rule and its error against the truth.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MergeCandidate {
    pub method: String,
    pub fitness: f64,
    pub inlier_rmse: f64,
    /// Rotation error against the simulator's truth, degrees; `None` without ground truth.
    pub error_deg: Option<f64>,
}

/// Angle (degrees) and distance (millimetres) between two transforms.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseError {
    pub deg: f64,
    pub mm: f64,
}

impl PoseError {
    pub fn between(a: &Pose, b: &Pose) -> PoseError {
        let (angle, distance) = pose_difference(a, b);
        PoseError {
            deg: angle.to_degrees(),
            mm: distance * 1e3,
        }
    }
}

/// What [`merge_scans`] found.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MergeReport {
    /// The right gripper's frame in the left's, 4x4 row-major, metres.
    pub right_to_left: [[f64; 4]; 4],
    pub method: String,
    pub fitness: f64,
    pub inlier_rmse_m: f64,
    /// Points of the right and the left cloud.
    pub points: [usize; 2],
    pub candidates: Vec<MergeCandidate>,
    /// Errors against the simulator's truth of the handover estimate and
    /// of the result; `None` without ground truth.
    pub handover_error: Option<PoseError>,
    pub refined_error: Option<PoseError>,
}

/// The paper's merge step on a capture's depth: object clouds of both arms
/// in their grippers' frames, the right one aligned onto the left from the
/// handover estimate by the better of ICP and colored ICP. With ground truth,
/// reports the error before and after.
pub fn merge_scans(capture: &omniscan_core::Capture) -> Result<MergeReport> {
    use omniscan_register::capture_cloud::object_cloud;
    let voxel = 0.001;
    let left = voxel_downsample(&object_cloud(capture, Arm::Left, 4, 2)?, voxel);
    let right = voxel_downsample(&object_cloud(capture, Arm::Right, 4, 2)?, voxel);
    let init = omniscan_core::poses::handover_estimate(capture);
    let (best, all) = refine_from_initial(
        &right,
        &left,
        &init,
        0.006,
        &Criteria {
            max_iteration: 50,
            ..Criteria::default()
        },
    )?;
    let truth = capture.file.gt.as_ref().map(|gt| gt.right_to_left.0);
    let error = |pose: &Pose| truth.map(|t| PoseError::between(pose, &t));
    Ok(MergeReport {
        right_to_left: pose_to_rows(&best.registration.transformation),
        method: best.method.into(),
        fitness: best.registration.fitness,
        inlier_rmse_m: best.registration.inlier_rmse,
        points: [right.len(), left.len()],
        candidates: all
            .iter()
            .map(|c| MergeCandidate {
                method: c.method.into(),
                fitness: c.registration.fitness,
                inlier_rmse: c.registration.inlier_rmse,
                error_deg: error(&c.registration.transformation).map(|e| e.deg),
            })
            .collect(),
        handover_error: error(&init),
        refined_error: error(&best.registration.transformation),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A target with no extent has no default correspondence distance: the
    /// refusal names the file and the flag to give, not a flag never passed
    /// "got 0".
    #[test]
    fn a_target_without_extent_asks_for_a_correspondence_distance() {
        let dir = tempfile::tempdir().unwrap();
        let (source, target) = (dir.path().join("s.xyz"), dir.path().join("t.xyz"));
        std::fs::write(&source, "0 0 0\n0.01 0 0\n0 0.01 0\n").unwrap();
        std::fs::write(&target, "0 0 0\n").unwrap();
        let out = dir.path().join("t.json");
        let err = align(&source, &target, &out, &AlignSettings::default())
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("t.xyz: its 1 point(s) span no distance"),
            "{err}"
        );
        assert!(err.contains("give --max-distance"), "{err}");
        assert!(!out.exists());
    }
}
