//! Capture format v1: a directory with `capture.json` and image files, as
//! written by the scan simulator or a real rig (`docs/capture-format.md`).
//!
//! [`Capture::load`] parses and validates everything a later stage relies on
//! (versions, matrices, image presence, sizes and pixel formats) and reports
//! every problem with the file it concerns, not just the first.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::Intrinsics;
use crate::error::{CoreError, Result};
use crate::geometry::{Pose, RigidTransform};

/// The capture format version this build reads and writes.
pub const CAPTURE_VERSION: u32 = 1;
/// File name of the capture description inside a capture directory.
pub const CAPTURE_FILE: &str = "capture.json";

/// Which arm holds the object.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Arm {
    Left,
    Right,
}

impl Arm {
    pub fn name(self) -> &'static str {
        match self {
            Arm::Left => "left",
            Arm::Right => "right",
        }
    }
    pub fn other(self) -> Arm {
        match self {
            Arm::Left => Arm::Right,
            Arm::Right => Arm::Left,
        }
    }
}

impl std::fmt::Display for Arm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Arm {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "left" => Ok(Arm::Left),
            "right" => Ok(Arm::Right),
            other => Err(format!("unknown arm `{other}`, expected `left` or `right`")),
        }
    }
}

/// The fixed camera: intrinsics (pixels) and its pose T_c (camera to world).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CameraSpec {
    #[serde(flatten)]
    pub intrinsics: Intrinsics,
    /// T_c: camera-to-world, OpenCV camera axes, metres.
    pub camera_to_world: RigidTransform,
    /// The lens's distortion (the images are as the lens saw them); absent
    /// for a pinhole camera, as the simulator renders. Stages that need a
    /// pinhole resample each image as they read it ([`crate::lens`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distortion: Option<crate::lens::Distortion>,
}

/// Gripper poses at the moment of handover.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Handover {
    /// T_lh: left gripper to world at handover.
    pub left_gripper_to_world: RigidTransform,
    /// T_rh: right gripper to world at handover.
    pub right_gripper_to_world: RigidTransform,
}

/// Ground-truth files of a simulated frame.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameGroundTruth {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub object_mask_path: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gripper_mask_path: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_path: Option<String>,
    /// The true gripper pose, where the recorded `gripper_to_world` carries
    /// a simulated calibration error (`sim --pose-noise-deg/--pose-noise-mm`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gripper_to_world: Option<RigidTransform>,
}

/// Where a frame sits on the scan trajectory.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryIndex {
    /// Index of the wrist angle (longitude), 0-based.
    pub wrist_index: u32,
    /// Index of the latitude, 0-based.
    pub latitude_index: u32,
    /// Wrist angle about the gripper's z-axis, radians.
    pub wrist_angle_rad: f64,
    /// Latitude of the camera direction above the gripper's equator, radians.
    pub latitude_rad: f64,
}

/// One image of the scan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Frame {
    /// RGB image, relative to the capture directory.
    pub file_path: String,
    /// The arm that holds the object (or, for empty frames, the scanning arm).
    pub arm: Arm,
    /// T_i: pose of the holding gripper (its TCP frame) in the world, metres.
    pub gripper_to_world: RigidTransform,
    /// Sensor depth, 16-bit PNG in millimetres.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_path: Option<String>,
    /// Object mask from the masking stage (8-bit PNG, 255 = object).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub object_mask_path: Option<String>,
    /// Gripper mask from the masking stage (8-bit PNG, 255 = gripper).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gripper_mask_path: Option<String>,
    /// Opening between the finger pads when the image was taken, metres.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gripper_opening_m: Option<f64>,
    /// Position on the scan trajectory, when known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trajectory: Option<TrajectoryIndex>,
    /// Ground truth, simulated captures only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gt: Option<FrameGroundTruth>,
}

impl Frame {
    /// Every file the frame names, with its key in `capture.json`.
    pub fn named_paths(&self) -> impl Iterator<Item = (&'static str, &str)> {
        let gt = self.gt.as_ref();
        [
            ("file_path", Some(&self.file_path)),
            ("depth_path", self.depth_path.as_ref()),
            ("object_mask_path", self.object_mask_path.as_ref()),
            ("gripper_mask_path", self.gripper_mask_path.as_ref()),
            (
                "gt.object_mask_path",
                gt.and_then(|g| g.object_mask_path.as_ref()),
            ),
            (
                "gt.gripper_mask_path",
                gt.and_then(|g| g.gripper_mask_path.as_ref()),
            ),
            ("gt.depth_path", gt.and_then(|g| g.depth_path.as_ref())),
        ]
        .into_iter()
        .filter_map(|(key, path)| path.map(|p| (key, p.as_str())))
    }
}

/// Capture-level ground truth recorded by the simulator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaptureGroundTruth {
    /// True pose of the object in the left gripper (object to left-gripper frame).
    pub object_to_left_gripper: RigidTransform,
    /// True pose of the object in the right gripper after handover (object to right-gripper frame).
    pub object_to_right_gripper: RigidTransform,
    /// True transform from the right gripper's frame to the left gripper's frame
    /// for the object (what T_lh⁻¹·T_rh estimates): maps points of the right
    /// scan's reconstruction into the left scan's.
    pub right_to_left: RigidTransform,
    /// Everything else the simulator knows (object, grasps, slip, defect...).
    #[serde(flatten)]
    pub extra: serde_json::Map<String, serde_json::Value>,
}

/// The robot whose gripper a capture shows, from its description file
/// (`sim --robot-urdf`, `import ros2 --robot-urdf`), so that every stage
/// uses the same gripper geometry. Absent: the ABB YuMi.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotSpec {
    /// The robot's description: a URDF, or a MuJoCo MJCF file (absolute,
    /// or relative to the capture folder); told apart by their root element.
    pub description: String,
    /// The link whose subtree is the gripper.
    pub gripper_root: String,
    /// The tool (TCP) frame: a link fixed to the gripper root...
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tcp_link: Option<String>,
    /// ...or an offset from the gripper root's origin in its axes, metres.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tcp_offset_m: Option<[f64; 3]>,
}

/// A capture as stored in `capture.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaptureFile {
    pub version: u32,
    pub camera: CameraSpec,
    pub handover: Handover,
    pub frames: Vec<Frame>,
    pub empty_frames: Vec<Frame>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gt: Option<CaptureGroundTruth>,
    /// The robot's gripper, when it is not the YuMi.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robot: Option<RobotSpec>,
    /// Free-form description of what produced the capture.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub generator: Option<serde_json::Value>,
}

/// A loaded, validated capture with the directory its paths are relative to.
#[derive(Debug, Clone)]
pub struct Capture {
    pub dir: PathBuf,
    pub file: CaptureFile,
}

/// Summary printed by `omniscan validate`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CaptureSummary {
    pub version: u32,
    pub left_frames: usize,
    pub right_frames: usize,
    pub empty_frames: usize,
    pub width: u32,
    pub height: u32,
    pub ground_truth: bool,
    pub depth: bool,
    pub object_masks: usize,
    pub gripper_masks: usize,
}

/// What kind of pixels an image file must hold.
#[derive(Debug, Clone, Copy, PartialEq)]
enum ImageKind {
    Rgb,
    Mask,
    Depth,
}

impl Capture {
    /// Resolves `path` (a capture directory or its `capture.json`) to the JSON file.
    pub fn json_path(path: &Path) -> PathBuf {
        if path.is_dir() {
            path.join(CAPTURE_FILE)
        } else {
            path.to_path_buf()
        }
    }

    /// Reads and validates a capture, checking every referenced image.
    pub fn load(path: &Path) -> Result<Capture> {
        let capture = Self::load_unchecked(path)?;
        capture.validate()?;
        Ok(capture)
    }

    /// Reads `capture.json` and checks its structure, but not the image files.
    pub fn load_unchecked(path: &Path) -> Result<Capture> {
        let json = Self::json_path(path);
        if !json.exists() {
            return Err(CoreError::parse(
                &json,
                "no such file: a capture is a directory holding capture.json (see docs/capture-format.md)",
            ));
        }
        let file: CaptureFile = crate::io::read_json(&json)?;
        let dir = json
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_else(|| PathBuf::from("."));
        let capture = Capture { dir, file };
        let problems = capture.structural_problems();
        if !problems.is_empty() {
            return Err(CoreError::InvalidCapture {
                path: json,
                problems,
            });
        }
        Ok(capture)
    }

    /// The path of a file named in the capture.
    pub fn resolve(&self, relative: &str) -> PathBuf {
        self.dir.join(relative)
    }

    pub fn intrinsics(&self) -> &Intrinsics {
        &self.file.camera.intrinsics
    }

    /// The lens's distortion, `None` for a pinhole camera.
    pub fn distortion(&self) -> Option<&crate::lens::Distortion> {
        self.file.camera.distortion.as_ref()
    }

    /// T_c, camera to world.
    pub fn camera_to_world(&self) -> Pose {
        self.file.camera.camera_to_world.0
    }

    /// The frames held by one arm, with their indices in `frames`.
    pub fn arm_frames(&self, arm: Arm) -> impl Iterator<Item = (usize, &Frame)> {
        self.file
            .frames
            .iter()
            .enumerate()
            .filter(move |(_, f)| f.arm == arm)
    }

    pub fn summary(&self) -> CaptureSummary {
        let frames = &self.file.frames;
        CaptureSummary {
            version: self.file.version,
            left_frames: frames.iter().filter(|f| f.arm == Arm::Left).count(),
            right_frames: frames.iter().filter(|f| f.arm == Arm::Right).count(),
            empty_frames: self.file.empty_frames.len(),
            width: self.file.camera.intrinsics.width,
            height: self.file.camera.intrinsics.height,
            ground_truth: self.file.gt.is_some(),
            depth: !frames.is_empty() && frames.iter().all(|f| f.depth_path.is_some()),
            object_masks: frames
                .iter()
                .filter(|f| f.object_mask_path.is_some())
                .count(),
            gripper_masks: frames
                .iter()
                .filter(|f| f.gripper_mask_path.is_some())
                .count(),
        }
    }

    fn structural_problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        let f = &self.file;
        if f.version != CAPTURE_VERSION {
            problems.push(format!(
                "version {} is not supported (this build reads version {CAPTURE_VERSION})",
                f.version
            ));
        }
        if let Err(e) = f.camera.intrinsics.validate() {
            problems.push(e);
        } else if let Some(d) = &f.camera.distortion
            && let Err(e) = crate::lens::check_distortion(d, &f.camera.intrinsics)
        {
            problems.push(format!("camera.distortion: {e}"));
        }
        if f.frames.is_empty() {
            problems.push("`frames` is empty: the capture has no scan trajectory".into());
        }
        for (list, frames) in [("frames", &f.frames), ("empty_frames", &f.empty_frames)] {
            for (i, frame) in frames.iter().enumerate() {
                if frame.file_path.trim().is_empty() {
                    problems.push(format!("{list}[{i}].file_path is empty"));
                }
                for (key, rel) in frame.named_paths() {
                    if let Err(e) = crate::paths::confine(&self.dir, rel) {
                        problems.push(format!("{list}[{i}].{key}: {e}"));
                    }
                }
                if let Some(o) = frame.gripper_opening_m
                    && !(o.is_finite() && o >= 0.0)
                {
                    problems.push(format!(
                        "{list}[{i}].gripper_opening_m must be >= 0 metres, found {o}"
                    ));
                }
            }
        }
        problems
    }

    /// Checks every image the capture names: present, its header readable,
    /// of the camera's size, of the right pixel format. Runs in parallel.
    pub fn validate(&self) -> Result<()> {
        self.check_images(false)
    }

    /// [`validate`](Self::validate), and every image decoded to its last
    /// pixel as well (`omniscan validate`): a truncated or damaged PNG is
    /// found here rather than by the stage that reads it.
    pub fn validate_pixels(&self) -> Result<()> {
        self.check_images(true)
    }

    fn check_images(&self, decode: bool) -> Result<()> {
        // (key, path, format, what to say when the file is missing)
        let mut checks: Vec<(String, &str, ImageKind, &str)> = Vec::new();
        for (list, frames) in [
            ("frames", &self.file.frames),
            ("empty_frames", &self.file.empty_frames),
        ] {
            for (i, frame) in frames.iter().enumerate() {
                for (key, rel) in frame.named_paths() {
                    let (kind, missing) = match key {
                        "file_path" => (ImageKind::Rgb, ""),
                        "depth_path" | "gt.depth_path" => (ImageKind::Depth, ""),
                        // A frame's own masks are `omniscan mask`'s output.
                        "object_mask_path" | "gripper_mask_path" => {
                            (ImageKind::Mask, " (`omniscan mask` makes it again)")
                        }
                        _ => (ImageKind::Mask, ""),
                    };
                    checks.push((format!("{list}[{i}].{key}"), rel, kind, missing));
                }
            }
        }
        let (w, h) = (
            self.file.camera.intrinsics.width,
            self.file.camera.intrinsics.height,
        );
        let mut problems: Vec<String> = checks
            .par_iter()
            .filter_map(|(at, rel, kind, missing)| {
                self.check_image(at, rel, *kind, missing, (w, h), decode)
                    .err()
            })
            .collect();
        problems.sort();
        if problems.is_empty() {
            Ok(())
        } else {
            Err(CoreError::InvalidCapture {
                path: self.dir.join(CAPTURE_FILE),
                problems,
            })
        }
    }

    fn check_image(
        &self,
        at: &str,
        rel: &str,
        kind: ImageKind,
        missing: &str,
        (w, h): (u32, u32),
        decode: bool,
    ) -> std::result::Result<(), String> {
        let path = self.resolve(rel);
        if !path.is_file() {
            return Err(format!("{at}: missing image {}{missing}", path.display()));
        }
        let (iw, ih, color) = crate::image_io::probe(&path).map_err(|e| format!("{at}: {e}"))?;
        if (iw, ih) != (w, h) {
            return Err(format!(
                "{at}: size mismatch: {} is {iw}x{ih} but the camera is {w}x{h}",
                path.display()
            ));
        }
        use image::ColorType;
        let ok = match kind {
            ImageKind::Rgb => matches!(color, ColorType::Rgb8 | ColorType::Rgba8 | ColorType::L8),
            ImageKind::Mask => color == ColorType::L8,
            ImageKind::Depth => color == ColorType::L16,
        };
        if !ok {
            let want = match kind {
                ImageKind::Rgb => "8-bit RGB",
                ImageKind::Mask => "8-bit greyscale mask",
                ImageKind::Depth => "16-bit greyscale depth in millimetres",
            };
            return Err(format!(
                "{at}: {} must be {want}, found {color:?}",
                path.display()
            ));
        }
        if decode {
            crate::image_io::check_decodes(&path).map_err(|e| format!("{at}: {e}"))?;
        }
        Ok(())
    }

    /// Writes `capture.json` atomically into `dir`.
    pub fn save(&self) -> Result<()> {
        crate::io::write_json_atomic(&self.dir.join(CAPTURE_FILE), &self.file)
    }
}
