//! Gripper and object masks for every frame of a capture (the paper's
//! "Object masks": kinematic gripper masks, or its learned gripper
//! segmentation, and the object pipeline's depth, flow and non-gripper
//! scores), measured against the simulator's ground truth where asked.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use omniscan_core::capture::Capture;
use omniscan_mask::pipeline::{Evaluation, LearnedModels, MaskRunSummary, Masker};
use omniscan_mask::{MaskSettings, evaluate_capture, mask_capture};

use crate::Progress;
use crate::settings::default_from_flags;

/// How gripper masks are made.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum GripperMethod {
    /// Project the gripper model at the recorded pose and opening, checked against the sensor depth.
    #[default]
    Kinematic,
    /// The paper's learned segmentation: a U-Net from `omniscan mask train-gripper` (--unet).
    Unet,
    /// The kinematic mask extended by the U-Net's pixels next to it (bent soft fingers).
    Both,
}

/// What a depth network outputs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum DepthOutputChoice {
    /// Relative inverse depth (larger is nearer), as Depth Anything V2's relative models give.
    #[default]
    Disparity,
    /// Metres.
    Metres,
}

/// The value range a flow network expects its images in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum FlowRangeChoice {
    /// 0..255
    #[default]
    Bytes,
    /// 0..1
    Unit,
    /// -1..1
    Signed,
}

/// Learned backends (ONNX files run by ONNX Runtime) in place of the weight-free defaults.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LearnedSettings {
    /// ONNX Runtime's shared library (libonnxruntime.so, in the `onnxruntime` pip wheel under onnxruntime/capi/); default: $ORT_DYLIB_PATH, else python3's onnxruntime package.
    #[arg(long)]
    pub onnx_runtime: Option<PathBuf>,
    /// A monocular depth network (ONNX; e.g. Depth Anything V2) instead of the sensor depth; relative output is put in metres on the gripper model's pixels.
    #[arg(long)]
    pub depth_model: Option<PathBuf>,
    /// What --depth-model outputs.
    #[arg(long, value_enum, default_value = "disparity")]
    pub depth_model_output: DepthOutputChoice,
    /// An optical-flow network (ONNX; e.g. RAFT; two `[1,3,H,W]` image inputs, a `[1,2,H,W]` output) instead of Lucas-Kanade.
    #[arg(long)]
    pub flow_model: Option<PathBuf>,
    /// The value range --flow-model expects its images in.
    #[arg(long, value_enum, default_value = "bytes")]
    pub flow_model_input: FlowRangeChoice,
    /// Segment Anything's image encoder (ONNX) for the object candidates, instead of graph segmentation.
    #[arg(long, requires = "sam_decoder")]
    pub sam_encoder: Option<PathBuf>,
    /// Segment Anything's prompt decoder (ONNX; segment-anything's export interface).
    #[arg(long, requires = "sam_encoder")]
    pub sam_decoder: Option<PathBuf>,
}

default_from_flags!(LearnedSettings);

impl LearnedSettings {
    fn models(&self) -> LearnedModels {
        use omniscan_mask::depth::DepthOutput;
        use omniscan_mask::flow::FlowInputRange;
        LearnedModels {
            onnx_runtime: self.onnx_runtime.clone(),
            depth: self.depth_model.clone(),
            depth_output: match self.depth_model_output {
                DepthOutputChoice::Disparity => DepthOutput::Disparity,
                DepthOutputChoice::Metres => DepthOutput::Metres,
            },
            flow: self.flow_model.clone(),
            flow_range: match self.flow_model_input {
                FlowRangeChoice::Bytes => FlowInputRange::Bytes,
                FlowRangeChoice::Unit => FlowInputRange::Unit,
                FlowRangeChoice::Signed => FlowInputRange::Signed,
            },
            sam_encoder: self.sam_encoder.clone(),
            sam_decoder: self.sam_decoder.clone(),
            ..LearnedModels::default()
        }
    }
}

/// Everything `mask` can be told besides the capture.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MaskingSettings {
    /// Gripper mask method.
    #[arg(long, value_enum, default_value = "kinematic")]
    pub gripper: GripperMethod,
    /// The trained gripper U-Net for --gripper unet|both: our safetensors file, or an .onnx export (run by ONNX Runtime).
    #[arg(long)]
    pub unet: Option<PathBuf>,
    /// Directory with the robot's gripper meshes (default: the one recorded by the simulator, else the built-in model).
    #[arg(long)]
    pub gripper_dir: Option<PathBuf>,
    /// Smallest mean depth change against the empty-gripper pass for an object candidate (S_NR), millimetres.
    #[arg(long, default_value_t = 8.0)]
    pub non_robot_threshold_mm: f32,
    /// Smallest share of an object candidate outside the gripper mask (S_NG; the paper's 0.89).
    #[arg(long, default_value_t = 0.89)]
    pub non_gripper_threshold: f32,
    /// Foreground depth limit beyond the gripper's tool point, metres.
    #[arg(long, default_value_t = 0.15)]
    pub near_margin_m: f32,
    /// Depth sensor noise at 1 m, millimetres (grows with distance squared); sets how far in front of a finger something must be to hide it.
    #[arg(long, default_value_t = 2.0)]
    pub depth_noise_mm_at_1m: f32,
    /// Grow gripper masks by up to this many pixels where depth and colour continue the gripper (bent soft fingers).
    #[arg(long, default_value_t = 0)]
    pub grow_px: usize,
    #[command(flatten)]
    #[serde(flatten)]
    pub learned: LearnedSettings,
}

default_from_flags!(MaskingSettings);

impl MaskingSettings {
    /// The mask crate's settings, after checking each value.
    pub fn resolve(&self) -> Result<MaskSettings> {
        let mut s = MaskSettings::default();
        for (name, v) in [
            ("--non-robot-threshold-mm", self.non_robot_threshold_mm),
            ("--near-margin-m", self.near_margin_m),
            ("--depth-noise-mm-at-1m", self.depth_noise_mm_at_1m),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                bail!("{name} must be a non-negative number, got {v}");
            }
        }
        if !(0.0..=1.0).contains(&self.non_gripper_threshold) {
            bail!(
                "--non-gripper-threshold must be between 0 and 1, got {}",
                self.non_gripper_threshold
            );
        }
        s.object.non_robot_threshold_m = self.non_robot_threshold_mm * 1e-3;
        s.object.non_gripper_threshold = self.non_gripper_threshold;
        s.object.near_margin_m = self.near_margin_m;
        s.gripper.grow_px = self.grow_px;
        s.gripper.depth_noise_m_at_1m = self.depth_noise_mm_at_1m * 1e-3;
        Ok(s)
    }

    /// The masker for `capture` with the gripper method and learned
    /// backends these settings name.
    pub fn masker(&self, capture: &Capture) -> Result<Masker> {
        let masker = Masker::new(capture, self.gripper_dir.as_deref(), self.resolve()?)?
            .with_learned(&self.learned.models())?;
        let runtime = self.learned.onnx_runtime.as_deref();
        Ok(match (self.gripper, self.unet.as_deref()) {
            (GripperMethod::Kinematic, None) => masker,
            (GripperMethod::Kinematic, Some(_)) => {
                bail!("--unet is used only with --gripper unet or --gripper both")
            }
            (_, None) => {
                bail!("--gripper unet|both needs --unet FILE (from `omniscan mask train-gripper`)")
            }
            (method, Some(file)) => {
                masker.with_unet(file, method == GripperMethod::Both, runtime)?
            }
        })
    }
}

/// What [`mask`] did, and the masks against ground truth where asked.
#[derive(Clone, Debug, Serialize)]
pub struct MaskReport {
    pub masking: MaskRunSummary,
    pub evaluation: Option<Evaluation>,
    /// Where the masks are.
    #[serde(skip)]
    pub mask_dir: PathBuf,
}

/// Masks every frame of the capture at `capture_path`, writes the PNGs and
/// records them in its `capture.json`; with `evaluate`, scores them against
/// the simulator's ground truth.
pub fn mask(
    capture_path: &Path,
    settings: &MaskingSettings,
    evaluate: bool,
    progress: &dyn Progress,
) -> Result<MaskReport> {
    let mut capture = Capture::load_unchecked(capture_path)?;
    let _lock = omniscan_core::lock::OutputLock::folder(&capture.dir, "mask")?;
    // The frames' masks are what this stage makes: ones capture.json names
    // but that are gone (deleted to make them again) are made again, where
    // validating them first refused to run.
    let dir = capture.dir.clone();
    for frame in &mut capture.file.frames {
        for mask in [&mut frame.object_mask_path, &mut frame.gripper_mask_path] {
            if mask.as_ref().is_some_and(|m| !dir.join(m).exists()) {
                *mask = None;
            }
        }
    }
    capture.validate()?;
    let masker = settings.masker(&capture)?;
    progress.start("masking", capture.file.frames.len() as u64, "frames");
    let masking = mask_capture(&mut capture, &masker, &|done, _| progress.set(done as u64))
        .with_context(|| format!("masking {} failed", capture.dir.display()))?;
    progress.finish();
    let evaluation = if evaluate {
        Some(evaluate_capture(&capture)?)
    } else {
        None
    };
    Ok(MaskReport {
        masking,
        evaluation,
        mask_dir: capture.dir.join(omniscan_mask::pipeline::MASK_DIR),
    })
}
