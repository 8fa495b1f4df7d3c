//! Which views a stage reads: one arm's frames of a capture, both arms
//! merged into the left gripper's frame (by the handover estimate
//! T_lh⁻¹·T_rh or a refined transform), or a calibrated photo set.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use omniscan_core::Pose;
use omniscan_core::capture::{Arm, Capture};
use omniscan_core::geometry::pose_from_rows;
use omniscan_core::poses::ViewSet;
use omniscan_splat::views::ViewSource;

/// The arms whose frames a stage reads.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ArmSet {
    #[default]
    Left,
    Right,
    /// Both arms in the left gripper's frame, merged with the handover estimate T_lh⁻¹·T_rh (or --right-to-left).
    Both,
}

impl ArmSet {
    /// The capture's frames these arms stand for, and the frame they are in:
    /// both arms merged by `right_to_left` (the right gripper's frame in the
    /// left's) where given, else by the robot's handover estimate.
    pub fn view_set(self, capture: &Capture, right_to_left: Option<Pose>) -> ViewSet {
        match (self, right_to_left) {
            (ArmSet::Left, _) => ViewSet::Arm(Arm::Left),
            (ArmSet::Right, _) => ViewSet::Arm(Arm::Right),
            (ArmSet::Both, Some(right_to_left)) => ViewSet::Merged { right_to_left },
            (ArmSet::Both, None) => ViewSet::merged_from_handover(capture),
        }
    }
}

/// The transform that replaces the handover estimate in a merged view set.
#[derive(clap::Args, Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Merge {
    /// With --arm both: the right gripper's frame in the left's, in place of the handover
    /// estimate T_lh⁻¹·T_rh. A JSON file from `omniscan align` (its `transform`) or a bare 4x4
    /// row-major matrix, metres. The paper's merged model uses the handover estimate refined by
    /// aligning the right arm's model onto the left's (`omniscan align right.ply left.ply
    /// --handover CAPTURE`).
    #[arg(long)]
    pub right_to_left: Option<PathBuf>,
}

impl Merge {
    /// The transform the file names; refused unless `arm` is both.
    pub fn read(&self, arm: ArmSet) -> Result<Option<Pose>> {
        match (&self.right_to_left, arm) {
            (None, _) => Ok(None),
            (Some(path), ArmSet::Both) => Ok(Some(read_transform(path)?)),
            (Some(path), _) => bail!(
                "--right-to-left {}: only views of both arms (--arm both) are merged",
                path.display()
            ),
        }
    }
}

/// Reads a transform file: `{"transform": 4x4}` or a bare 4x4 row-major array.
pub fn read_transform(path: &Path) -> Result<Pose> {
    let v: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?,
    )
    .with_context(|| format!("{} is not JSON", path.display()))?;
    let m = v.get("transform").unwrap_or(&v);
    let rows: [[f64; 4]; 4] = serde_json::from_value(m.clone()).with_context(|| {
        format!(
            "{}: expected a 4x4 matrix (or {{\"transform\": 4x4}})",
            path.display()
        )
    })?;
    pose_from_rows(&rows).with_context(|| format!("{}: transform", path.display()))
}

/// The photo set `path` names: a JSON file other than a capture's, or a
/// directory holding a `transforms.json` and no capture.
pub fn photo_set_file(path: &Path) -> Option<PathBuf> {
    let capture_file = omniscan_core::capture::CAPTURE_FILE;
    let nerfstudio = path.join("transforms.json");
    if path.extension().is_some_and(|e| e == "json") && !path.ends_with(capture_file) {
        Some(path.to_path_buf())
    } else if path.is_dir() && !path.join(capture_file).exists() && nerfstudio.is_file() {
        Some(nerfstudio)
    } else {
        None
    }
}

/// The views of a capture (one arm, or both merged at the handover or by
/// `right_to_left`) and the set they are, or of a calibrated photo set
/// (a `transforms.json`, a directory holding one and no capture, or a
/// `cameras.json`; no set: it has no arms), not yet read. A capture's
/// frames without masks of their own use the simulator's ground truth only
/// with `ground_truth_masks`.
pub fn view_source(
    path: &Path,
    arm: ArmSet,
    right_to_left: Option<Pose>,
    downscale: u32,
    ground_truth_masks: bool,
) -> Result<(ViewSource, Option<ViewSet>)> {
    if let Some(photo_set) = photo_set_file(path) {
        let photo_set = photo_set.as_path();
        if right_to_left.is_some() {
            bail!(
                "--right-to-left: {} is a photo set, whose views have no arms to merge",
                photo_set.display()
            );
        }
        return Ok((ViewSource::from_photo_set(photo_set, downscale)?, None));
    }
    let capture = Capture::load(path)?;
    let set = arm.view_set(&capture, right_to_left);
    Ok((
        ViewSource::from_capture(&capture, set, downscale)?
            .with_ground_truth_masks(ground_truth_masks),
        Some(set),
    ))
}
