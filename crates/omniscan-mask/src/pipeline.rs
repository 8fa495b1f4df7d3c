//! Masks for a whole capture: every frame's gripper mask (kinematic) and
//! object mask (the paper's pipeline), written as 8-bit PNGs under
//! `masks/gripper/` and `masks/object/` next to `images/`, their paths
//! recorded in `capture.json` (written atomically, after every mask is on
//! disk). Resumable: a rerun with the same settings keeps the masks already
//! written. With a simulated capture, [`evaluate_capture`] measures the masks
//! against the simulator's ground truth.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use nalgebra::Point3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use omniscan_core::capture::{Arm, Capture, Frame};
use omniscan_core::image_io::{self, RgbImage};
use omniscan_scene::gripper::GripperModel;

use crate::depth::{DepthEstimator, DepthOutput, MonocularDepth, SensorDepth};
use crate::flow::{FlowEstimator, FlowInputRange, FlowSettings, LucasKanade, OnnxFlow};
use crate::gripper::{GripperProjection, GripperSettings, KinematicGripper, LensMap, refine};
use crate::object::{ObjectInputs, ObjectSettings, object_mask};
use crate::plane::{Plane, iou};
use crate::sam::{SamProposer, SamSettings};
use crate::segment::{CandidateProposer, GraphSegmenter};
use crate::unet::{Example, GripperNet, UNet};
use crate::{MaskError, Result};

/// Where the masks go, relative to the capture directory.
pub const MASK_DIR: &str = "masks";
const SETTINGS_FILE: &str = "settings.json";

/// Every setting of the masking stage.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MaskSettings {
    /// How gripper masks are made, for the resume check: `kinematic`, or
    /// `unet:FILE` / `both:FILE` with the network's file.
    #[serde(default)]
    pub gripper_method: String,
    /// The depth, flow and candidate backends, for the resume check
    /// (`sensor`, `lucas-kanade`, `graph` by default; learned ones with their files).
    #[serde(default)]
    pub backends: String,
    pub gripper: GripperSettings,
    pub object: ObjectSettings,
    pub flow: FlowSettings,
}

/// Seconds spent per stage on one frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct FrameTimings {
    pub load_s: f64,
    /// Depth of the frame and its empty-gripper partner.
    pub depth_s: f64,
    /// The gripper masks, the projection of the gripper model included.
    pub gripper_s: f64,
    pub flow_s: f64,
    pub object_s: f64,
}

impl FrameTimings {
    pub fn total(&self) -> f64 {
        self.load_s + self.depth_s + self.gripper_s + self.flow_s + self.object_s
    }
}

/// The masks of one frame.
#[derive(Debug, Clone)]
pub struct FrameMasks {
    pub object: Plane<bool>,
    pub gripper: Plane<bool>,
    pub timings: FrameTimings,
}

/// How a frame's gripper mask is made.
pub enum GripperMethod {
    /// The projected gripper model, checked against the depth.
    Kinematic,
    /// The paper's learned segmentation alone.
    Unet(GripperNet),
    /// The kinematic mask, plus the pixels within a few pixels of it that the
    /// U-Net calls gripper (soft fingers bending outward).
    Both(GripperNet),
}

/// How far around the kinematic mask the U-Net may add pixels (`Both`), pixels.
const BOTH_REACH_PX: usize = 4;

/// The backends and settings for masking one capture.
pub struct Masker {
    pub method: GripperMethod,
    pub gripper: KinematicGripper,
    pub depth: Box<dyn DepthEstimator>,
    pub flow: Box<dyn FlowEstimator>,
    pub proposer: Box<dyn CandidateProposer>,
    pub settings: MaskSettings,
    /// The learned models' files and options, for the resume check.
    learned_files: Vec<String>,
}

impl Masker {
    /// The default (weight-free) backends for `capture`. The gripper model is
    /// the YuMi meshes in `gripper_dir`, else the directory the simulator
    /// recorded in the capture, else the built-in model.
    pub fn new(
        capture: &Capture,
        gripper_dir: Option<&Path>,
        mut settings: MaskSettings,
    ) -> Result<Masker> {
        if settings.gripper_method.is_empty() {
            settings.gripper_method = "kinematic".into();
        }
        let recorded = capture
            .file
            .generator
            .as_ref()
            .and_then(|g| g.get("config"))
            .and_then(|c| c.get("gripper_dir"))
            .and_then(|d| d.as_str())
            .map(PathBuf::from);
        let model = match (&capture.file.robot, gripper_dir) {
            (Some(robot), None) => GripperModel::from_robot(robot, &capture.dir).map_err(|e| {
                MaskError::Invalid(format!(
                    "{e}\n(the robot's gripper the capture records, for kinematic masks)"
                ))
            })?,
            (Some(_), Some(dir)) => {
                return Err(MaskError::Invalid(format!(
                    "the capture records its robot's gripper ({}); --gripper-dir {} (the YuMi's meshes) does not apply",
                    capture.file.robot.as_ref().unwrap().description,
                    dir.display()
                )));
            }
            (None, dir) => match dir.map(Path::to_path_buf).or(recorded) {
                Some(dir) => GripperModel::from_yumi_dir(&dir).map_err(|e| {
                    MaskError::Invalid(format!(
                        "{e}\n(the gripper model for kinematic masks; pass --gripper-dir with the robot's gripper meshes)"
                    ))
                })?,
                None => GripperModel::builtin(),
            },
        };
        Ok(Masker {
            method: GripperMethod::Kinematic,
            gripper: KinematicGripper {
                model,
                intrinsics: *capture.intrinsics(),
                camera_to_world: capture.camera_to_world(),
                settings: settings.gripper,
                lens: capture
                    .distortion()
                    .map(|d| LensMap::new(d, capture.intrinsics())),
            },
            depth: Box::new(SensorDepth),
            flow: Box::new(LucasKanade {
                settings: settings.flow,
            }),
            proposer: Box::new(GraphSegmenter {
                settings: settings.object.segmentation,
            }),
            settings,
            learned_files: Vec::new(),
        }
        .with_backends_recorded())
    }

    /// Records the backends in use in the settings (the resume check).
    fn with_backends_recorded(mut self) -> Masker {
        self.settings.backends = format!(
            "depth={} flow={} candidates={}{}",
            self.depth.name(),
            self.flow.name(),
            self.proposer.name(),
            self.learned_files
                .iter()
                .map(|f| format!(" {f}"))
                .collect::<String>()
        );
        self
    }

    /// Replaces the weight-free backends by the learned models named in
    /// `models` (ONNX files, run by ONNX Runtime).
    pub fn with_learned(mut self, models: &LearnedModels) -> Result<Masker> {
        let runtime = models.onnx_runtime.as_deref();
        if let Some(path) = &models.depth {
            self.depth = Box::new(MonocularDepth::load(path, models.depth_output, runtime)?);
            self.learned_files.push(format!(
                "depth:{}:{:?}",
                path.display(),
                models.depth_output
            ));
        }
        if let Some(path) = &models.flow {
            self.flow = Box::new(OnnxFlow::load(path, models.flow_range, runtime)?);
            self.learned_files
                .push(format!("flow:{}:{:?}", path.display(), models.flow_range));
        }
        match (&models.sam_encoder, &models.sam_decoder) {
            (Some(encoder), Some(decoder)) => {
                self.proposer = Box::new(SamProposer::load(encoder, decoder, models.sam, runtime)?);
                self.learned_files.push(format!(
                    "sam:{}:{}:{:?}",
                    encoder.display(),
                    decoder.display(),
                    models.sam
                ));
            }
            (None, None) => {}
            _ => {
                return Err(MaskError::Invalid(
                    "SAM needs both its encoder and its decoder ONNX files".into(),
                ));
            }
        }
        Ok(self.with_backends_recorded())
    }
}

/// Learned backends to use instead of the weight-free defaults.
#[derive(Debug, Clone, PartialEq)]
pub struct LearnedModels {
    /// ONNX Runtime's library (else found as [`crate::onnx::find_runtime`] says).
    pub onnx_runtime: Option<PathBuf>,
    /// A monocular depth network, replacing the sensor depth.
    pub depth: Option<PathBuf>,
    pub depth_output: DepthOutput,
    /// An optical-flow network, replacing Lucas-Kanade.
    pub flow: Option<PathBuf>,
    pub flow_range: FlowInputRange,
    /// Segment Anything, replacing the graph segmentation.
    pub sam_encoder: Option<PathBuf>,
    pub sam_decoder: Option<PathBuf>,
    pub sam: SamSettings,
}

impl Default for LearnedModels {
    fn default() -> Self {
        LearnedModels {
            onnx_runtime: None,
            depth: None,
            depth_output: DepthOutput::Disparity,
            flow: None,
            flow_range: FlowInputRange::Bytes,
            sam_encoder: None,
            sam_decoder: None,
            sam: SamSettings::default(),
        }
    }
}

impl Masker {
    /// Uses a trained U-Net (`both`: to extend the kinematic mask; else alone),
    /// read from `path` (our safetensors file, or an `.onnx` export run by
    /// ONNX Runtime found as [`crate::onnx::find_runtime`] says).
    pub fn with_unet(mut self, path: &Path, both: bool, runtime: Option<&Path>) -> Result<Masker> {
        let net = GripperNet::load(path, runtime)?;
        self.settings.gripper_method =
            format!("{}:{}", if both { "both" } else { "unet" }, path.display());
        self.method = if both {
            GripperMethod::Both(net)
        } else {
            GripperMethod::Unet(net)
        };
        Ok(self)
    }
}

fn frame_label(capture: &Capture, index: usize) -> String {
    format!(
        "frames[{index}] ({})",
        capture
            .resolve(&capture.file.frames[index].file_path)
            .display()
    )
}

/// The empty-gripper frame at the same pose as frame `index`: the same arm
/// and trajectory position, else the same position in the arm's list.
fn empty_partner(capture: &Capture, index: usize) -> Result<&Frame> {
    let frame = &capture.file.frames[index];
    let empties: Vec<&Frame> = capture
        .file
        .empty_frames
        .iter()
        .filter(|f| f.arm == frame.arm)
        .collect();
    if let Some(t) = frame.trajectory
        && let Some(e) = empties.iter().find(|e| {
            e.trajectory.is_some_and(|u| {
                u.wrist_index == t.wrist_index && u.latitude_index == t.latitude_index
            })
        })
    {
        return Ok(e);
    }
    let position = capture
        .arm_frames(frame.arm)
        .position(|(i, _)| i == index)
        .unwrap_or(0);
    empties.get(position).copied().ok_or_else(|| {
        MaskError::Invalid(format!(
            "{}: no empty-gripper frame of the {} arm at this pose; the object mask's non-robot score needs the empty pass (capture.json `empty_frames`)",
            frame_label(capture, index),
            frame.arm
        ))
    })
}

/// The neighbouring frame of the same arm used for the motion test.
fn neighbour(capture: &Capture, index: usize) -> Option<usize> {
    let arm: Vec<usize> = capture
        .arm_frames(capture.file.frames[index].arm)
        .map(|(i, _)| i)
        .collect();
    let position = arm.iter().position(|&i| i == index)?;
    arm.get(position + 1)
        .or_else(|| position.checked_sub(1).and_then(|p| arm.get(p)))
        .copied()
}

/// Computes the masks of frame `index` (nothing is written).
pub fn mask_frame(masker: &Masker, capture: &Capture, index: usize) -> Result<FrameMasks> {
    let start = Instant::now();
    let frame = capture.file.frames.get(index).ok_or_else(|| {
        MaskError::Invalid(format!(
            "frame {index} does not exist ({} frames)",
            capture.file.frames.len()
        ))
    })?;
    let size = (capture.intrinsics().width, capture.intrinsics().height);
    let image_path = capture.resolve(&frame.file_path);
    let image = image_io::read_rgb(&image_path)?;
    crate::check_size(
        &image_path,
        image.width as usize,
        image.height as usize,
        size,
    )?;
    let empty = empty_partner(capture, index)?;
    let read_image = |f: &Frame| -> Result<RgbImage> {
        let path = capture.resolve(&f.file_path);
        let img = image_io::read_rgb(&path)?;
        crate::check_size(&path, img.width as usize, img.height as usize, size)?;
        Ok(img)
    };
    let unet_only = matches!(masker.method, GripperMethod::Unet(_));
    let empty_image = if masker.depth.reads_image() || unet_only {
        Some(read_image(empty)?)
    } else {
        None
    };
    let next: Option<RgbImage> = match neighbour(capture, index) {
        Some(j) => Some(read_image(&capture.file.frames[j])?),
        None => None,
    };
    let opening = frame.gripper_opening_m.ok_or_else(|| {
        MaskError::Invalid(format!(
            "{}: no gripper_opening_m; the kinematic gripper mask needs the finger opening",
            frame_label(capture, index)
        ))
    })?;
    let load_s = start.elapsed().as_secs_f64();

    // The gripper model seen from the camera: the kinematic mask, and the
    // metric anchor of a relative depth network.
    let t = Instant::now();
    let gripper_to_world = frame.gripper_to_world.0;
    let uses_model = !unet_only || masker.depth.needs_anchor();
    let projection = uses_model.then(|| masker.gripper.project(&gripper_to_world, opening));
    let empty_projection = uses_model.then(|| {
        masker.gripper.project(
            &empty.gripper_to_world.0,
            empty.gripper_opening_m.unwrap_or(0.0),
        )
    });
    let projection_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    fn anchor<'a>(masker: &Masker, p: &'a Option<GripperProjection>) -> Option<&'a Plane<f32>> {
        p.as_ref()
            .filter(|_| masker.depth.needs_anchor())
            .map(|p| &p.depth_m)
    }
    let label = |f: &Frame| capture.resolve(&f.file_path).display().to_string();
    let depth = masker
        .depth
        .depth_m(capture, frame, &image, anchor(masker, &projection))
        .map_err(|e| MaskError::Invalid(format!("{}: depth: {e}", label(frame))))?;
    // A depth role that does not read images is given this frame's.
    let empty_depth = masker
        .depth
        .depth_m(
            capture,
            empty,
            empty_image.as_ref().unwrap_or(&image),
            anchor(masker, &empty_projection),
        )
        .map_err(|e| MaskError::Invalid(format!("{}: depth: {e}", label(empty))))?;
    let depth_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let kinematic = |p: &GripperProjection| refine(p, &image, &depth, &masker.gripper.settings);
    let empty_kinematic = || empty_projection.as_ref().map(|p| p.mask.clone());
    let (gripper, empty_gripper) = match (&masker.method, &projection) {
        (GripperMethod::Unet(net), _) => {
            let empty_image = empty_image.as_ref().unwrap_or(&image);
            (net.mask(&image)?, Some(net.mask(empty_image)?))
        }
        (GripperMethod::Kinematic, Some(p)) => (kinematic(p), empty_kinematic()),
        (_, None) => {
            return Err(MaskError::Invalid(
                "internal error: the gripper model was not projected".into(),
            ));
        }
        (GripperMethod::Both(net), Some(p)) => {
            let base = kinematic(p);
            let reach = base.dilate(BOTH_REACH_PX);
            let learned = net.mask(&image)?;
            let data = (0..base.len())
                .map(|i| base.data[i] || (learned.data[i] && reach.data[i]))
                .collect();
            (
                Plane {
                    width: base.width,
                    height: base.height,
                    data,
                },
                empty_kinematic(),
            )
        }
    };
    let gripper_s = projection_s + t.elapsed().as_secs_f64();

    let t = Instant::now();
    let (w, h) = (image.width as usize, image.height as usize);
    let moving = match &next {
        Some(next) => masker
            .flow
            .flow(&image, next)?
            .moving(masker.settings.object.min_flow_px),
        // A single frame: nothing to compare with, so everything may move.
        None => Plane::filled(w, h, true),
    };
    let flow_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let tool = capture.camera_to_world().inverse() * (gripper_to_world * Point3::origin());
    let inputs = ObjectInputs {
        image: &image,
        depth_m: &depth,
        empty_depth_m: &empty_depth,
        gripper: &gripper,
        empty_gripper: empty_gripper.as_ref(),
        moving: &moving,
        tool_depth_m: tool.z as f32,
    };
    let object = object_mask(&inputs, masker.proposer.as_ref(), &masker.settings.object)?;
    let object_s = t.elapsed().as_secs_f64();
    Ok(FrameMasks {
        object: object.mask,
        gripper,
        timings: FrameTimings {
            load_s,
            depth_s,
            gripper_s,
            flow_s,
            object_s,
        },
    })
}

/// What a masking run did.
#[derive(Debug, Clone, Serialize)]
pub struct MaskRunSummary {
    pub frames: usize,
    pub computed: usize,
    pub resumed: usize,
    pub seconds: f64,
    /// Mean seconds per computed frame, per stage.
    pub mean_timings: FrameTimings,
}

fn mask_paths(frame: &Frame) -> (String, String) {
    let stem = Path::new(&frame.file_path)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| frame.file_path.replace('/', "_"));
    (
        format!("{MASK_DIR}/object/{stem}.png"),
        format!("{MASK_DIR}/gripper/{stem}.png"),
    )
}

/// What a capture's masks were made from: the settings, and a digest of
/// the capture's inputs (see [`input_digest`]). A mask is kept from an
/// earlier run only under the same record.
#[derive(Debug, PartialEq, Serialize, Deserialize)]
struct MaskRecord {
    settings: MaskSettings,
    inputs: String,
}

/// A digest of everything masking reads: the capture file (the masks'
/// own paths left out, since masking writes them; numbers to 12 digits,
/// see [`omniscan_core::digest::stable_json`]) and the bytes of every
/// frame's and empty frame's image and depth map. An edited image or depth
/// map, or a moved pose, makes every mask again.
fn input_digest(capture: &Capture) -> Result<String> {
    let mut file = capture.file.clone();
    for frame in &mut file.frames {
        frame.object_mask_path = None;
        frame.gripper_mask_path = None;
    }
    let mut digest = omniscan_core::digest::Digest::default();
    let json = serde_json::to_value(&file).expect("a capture serialises");
    digest.add(
        omniscan_core::digest::stable_json(json)
            .to_string()
            .as_bytes(),
    );
    for frame in file.frames.iter().chain(&file.empty_frames) {
        for rel in std::iter::once(&frame.file_path).chain(&frame.depth_path) {
            let path = capture.resolve(rel);
            let bytes = std::fs::read(&path).map_err(|e| omniscan_core::CoreError::io(&path, e))?;
            digest.add(&(bytes.len() as u64).to_le_bytes());
            digest.add(&bytes);
        }
    }
    Ok(digest.hex())
}

/// Whether every mask at `paths` is there and decodes to the camera's size
/// (an output cut short or emptied is made again, not kept).
fn decodes_at(paths: &[&Path], capture: &Capture) -> bool {
    let k = capture.intrinsics();
    paths
        .iter()
        .all(|p| image_io::read_mask(p).is_ok_and(|m| (m.width, m.height) == (k.width, k.height)))
}

/// Masks every frame of `capture`, writes the PNGs and records their paths in
/// `capture.json`. `progress(done, total)` is called after each frame.
pub fn mask_capture(
    capture: &mut Capture,
    masker: &Masker,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<MaskRunSummary> {
    let start = Instant::now();
    let dir = capture.dir.join(MASK_DIR);
    std::fs::create_dir_all(dir.join("object"))
        .and_then(|_| std::fs::create_dir_all(dir.join("gripper")))
        .map_err(|e| omniscan_core::CoreError::io(&dir, e))?;
    let marker = dir.join(SETTINGS_FILE);
    let record = MaskRecord {
        settings: masker.settings.clone(),
        inputs: input_digest(capture)?,
    };
    let previous = omniscan_core::io::read_json::<MaskRecord>(&marker);
    let same_inputs = previous.ok().as_ref() == Some(&record);
    omniscan_core::io::write_json_atomic(&marker, &record)?;

    let total = capture.file.frames.len();
    let done = AtomicUsize::new(0);
    let paths: Vec<(String, String)> = capture.file.frames.iter().map(mask_paths).collect();
    let results: Vec<Result<Option<FrameTimings>>> = (0..total)
        .into_par_iter()
        .map(|i| {
            let (object_rel, gripper_rel) = &paths[i];
            let (object_path, gripper_path) =
                (capture.resolve(object_rel), capture.resolve(gripper_rel));
            let result = if same_inputs && decodes_at(&[&object_path, &gripper_path], capture) {
                Ok(None)
            } else {
                mask_frame(masker, capture, i).and_then(|m| {
                    image_io::write_mask(&gripper_path, &m.gripper.to_mask())?;
                    image_io::write_mask(&object_path, &m.object.to_mask())?;
                    Ok(Some(m.timings))
                })
            };
            progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
            result
        })
        .collect();
    let mut timings = Vec::new();
    let mut resumed = 0;
    for r in results {
        match r? {
            Some(t) => timings.push(t),
            None => resumed += 1,
        }
    }
    for (frame, (object_rel, gripper_rel)) in capture.file.frames.iter_mut().zip(paths) {
        frame.object_mask_path = Some(object_rel);
        frame.gripper_mask_path = Some(gripper_rel);
    }
    capture.save()?;
    let n = timings.len().max(1) as f64;
    let mean = |f: fn(&FrameTimings) -> f64| timings.iter().map(f).sum::<f64>() / n;
    Ok(MaskRunSummary {
        frames: total,
        computed: timings.len(),
        resumed,
        seconds: start.elapsed().as_secs_f64(),
        mean_timings: FrameTimings {
            load_s: mean(|t| t.load_s),
            depth_s: mean(|t| t.depth_s),
            gripper_s: mean(|t| t.gripper_s),
            flow_s: mean(|t| t.flow_s),
            object_s: mean(|t| t.object_s),
        },
    })
}

/// Mean IoU of one mask kind, per arm.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct PerArm {
    pub left: Option<f64>,
    pub right: Option<f64>,
}

/// One frame's IoUs against ground truth.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FrameScore {
    pub frame: usize,
    pub file: String,
    pub arm: Arm,
    pub object_iou: f64,
    pub gripper_iou: f64,
    /// Ground-truth object pixels (0 = the object is hidden).
    pub object_pixels: usize,
}

/// Masks against the simulator's ground truth.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Evaluation {
    pub object_miou: PerArm,
    pub gripper_miou: PerArm,
    pub object_min_iou: f64,
    pub gripper_min_iou: f64,
    pub frames: usize,
    /// The five frames with the lowest object IoU and the five with the lowest gripper IoU.
    pub worst_object: Vec<FrameScore>,
    pub worst_gripper: Vec<FrameScore>,
}

/// Compares the masks recorded in `capture.json` with the ground truth.
pub fn evaluate_capture(capture: &Capture) -> Result<Evaluation> {
    let scores: Vec<FrameScore> = (0..capture.file.frames.len())
        .into_par_iter()
        .map(|i| -> Result<FrameScore> {
            let frame = &capture.file.frames[i];
            let read = |rel: Option<&String>, what: &str| -> Result<Plane<bool>> {
                let rel = rel.ok_or_else(|| {
                    MaskError::Invalid(format!("{}: no {what}", frame_label(capture, i)))
                })?;
                Ok(Plane::from_mask(&image_io::read_mask(
                    &capture.resolve(rel),
                )?))
            };
            let object = read(
                frame.object_mask_path.as_ref(),
                "object_mask_path (run the masking first)",
            )?;
            let gripper = read(
                frame.gripper_mask_path.as_ref(),
                "gripper_mask_path (run the masking first)",
            )?;
            score_frame(capture, i, &object, &gripper)
        })
        .collect::<Result<_>>()?;
    Ok(summarise(&scores))
}

/// IoUs of frame `index`'s masks against its ground truth.
pub fn score_frame(
    capture: &Capture,
    index: usize,
    object: &Plane<bool>,
    gripper: &Plane<bool>,
) -> Result<FrameScore> {
    let frame = &capture.file.frames[index];
    let gt = frame.gt.as_ref().ok_or_else(|| {
        MaskError::Invalid(format!(
            "{}: no ground truth; --eval needs a simulated capture",
            frame_label(capture, index)
        ))
    })?;
    let read = |rel: Option<&String>, what: &str| -> Result<Plane<bool>> {
        let rel = rel.ok_or_else(|| {
            MaskError::Invalid(format!("{}: no {what}", frame_label(capture, index)))
        })?;
        Ok(Plane::from_mask(&image_io::read_mask(
            &capture.resolve(rel),
        )?))
    };
    let object_truth = read(gt.object_mask_path.as_ref(), "gt.object_mask_path")?;
    let gripper_truth = read(gt.gripper_mask_path.as_ref(), "gt.gripper_mask_path")?;
    Ok(FrameScore {
        frame: index,
        file: frame.file_path.clone(),
        arm: frame.arm,
        object_iou: iou(object, &object_truth),
        gripper_iou: iou(gripper, &gripper_truth),
        object_pixels: object_truth.count(),
    })
}

/// Per-arm means, lowest values and worst frames of frame scores.
pub fn summarise(scores: &[FrameScore]) -> Evaluation {
    let mean = |arm: Arm, f: fn(&FrameScore) -> f64| -> Option<f64> {
        let v: Vec<f64> = scores.iter().filter(|s| s.arm == arm).map(f).collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    let worst = |f: fn(&FrameScore) -> f64| -> Vec<FrameScore> {
        let mut sorted = scores.to_vec();
        sorted.sort_by(|a, b| f(a).total_cmp(&f(b)));
        sorted.truncate(5);
        sorted
    };
    let min = |f: fn(&FrameScore) -> f64| scores.iter().map(f).fold(1.0, f64::min);
    Evaluation {
        object_miou: PerArm {
            left: mean(Arm::Left, |s| s.object_iou),
            right: mean(Arm::Right, |s| s.object_iou),
        },
        gripper_miou: PerArm {
            left: mean(Arm::Left, |s| s.gripper_iou),
            right: mean(Arm::Right, |s| s.gripper_iou),
        },
        object_min_iou: min(|s| s.object_iou),
        gripper_min_iou: min(|s| s.gripper_iou),
        frames: scores.len(),
        worst_object: worst(|s| s.object_iou),
        worst_gripper: worst(|s| s.gripper_iou),
    }
}

/// An image with its ground-truth gripper mask.
pub type LabelledImage = (RgbImage, Plane<bool>);

/// Labelled examples for the gripper U-Net from simulated captures: every
/// `every`-th frame and empty-gripper frame with its ground-truth gripper
/// mask. Frames whose index in that list is a multiple of 8 are held out and
/// returned at full size for evaluation.
pub fn gripper_training_set(
    net: &UNet,
    captures: &[Capture],
    every: usize,
) -> Result<(Vec<Example>, Vec<LabelledImage>)> {
    let mut items: Vec<(&Capture, &Frame)> = Vec::new();
    for capture in captures {
        for frame in capture
            .file
            .frames
            .iter()
            .chain(&capture.file.empty_frames)
            .step_by(every.max(1))
        {
            items.push((capture, frame));
        }
    }
    let loaded: Vec<(usize, RgbImage, Plane<bool>)> = items
        .par_iter()
        .enumerate()
        .map(|(k, (capture, frame))| -> Result<_> {
            let rel = frame
                .gt
                .as_ref()
                .and_then(|g| g.gripper_mask_path.as_ref())
                .ok_or_else(|| {
                    MaskError::file(
                        capture.resolve(&frame.file_path),
                        "no ground-truth gripper mask: training needs a simulated capture",
                    )
                })?;
            let image = image_io::read_rgb(&capture.resolve(&frame.file_path))?;
            let mask = Plane::from_mask(&image_io::read_mask(&capture.resolve(rel))?);
            if (mask.width, mask.height) != (image.width as usize, image.height as usize) {
                return Err(MaskError::file(
                    capture.resolve(rel),
                    "size differs from its image",
                ));
            }
            Ok((k, image, mask))
        })
        .collect::<Result<_>>()?;
    let mut train = Vec::new();
    let mut held_out = Vec::new();
    for (k, image, mask) in loaded {
        if k % 8 == 0 {
            held_out.push((image, mask));
        } else {
            train.push(Example::new(net, &image, &mask));
        }
    }
    Ok((train, held_out))
}
