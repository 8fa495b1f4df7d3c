//! `omniscan mask` and `omniscan bench mask`: gripper and object masks for a
//! capture (kinematic gripper masks, the paper's object pipeline), measured
//! against the simulator's ground truth.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::ValueEnum;
use rayon::prelude::*;
use serde_json::json;

use omniscan_core::capture::Capture;
use omniscan_mask::pipeline::{
    FrameScore, FrameTimings, LearnedModels, Masker, mask_frame, score_frame, summarise,
};
use omniscan_mask::plane::iou;
use omniscan_mask::{MaskSettings, evaluate_capture, mask_capture};

/// How gripper masks are made.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum GripperMethod {
    /// Project the gripper model at the recorded pose and opening, checked against the sensor depth.
    Kinematic,
    /// The paper's learned segmentation: a U-Net from `omniscan mask train-gripper` (--unet).
    Unet,
    /// The kinematic mask extended by the U-Net's pixels next to it (bent soft fingers).
    Both,
}

#[derive(clap::Args)]
pub struct MaskSettingsArgs {
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
    pub learned: LearnedArgs,
}

/// Learned backends (ONNX files run by ONNX Runtime) in place of the weight-free defaults.
#[derive(clap::Args)]
pub struct LearnedArgs {
    /// ONNX Runtime's shared library (libonnxruntime.so, in the `onnxruntime` pip wheel under onnxruntime/capi/); default: $ORT_DYLIB_PATH, else python3's onnxruntime package.
    #[arg(long)]
    pub onnx_runtime: Option<PathBuf>,
    /// A monocular depth network (ONNX; e.g. Depth Anything V2) instead of the sensor depth; relative output is put in metres on the gripper model's pixels.
    #[arg(long)]
    pub depth_model: Option<PathBuf>,
    /// What --depth-model outputs.
    #[arg(long, value_enum, default_value = "disparity")]
    pub depth_model_output: DepthOutputArg,
    /// An optical-flow network (ONNX; e.g. RAFT; two [1,3,H,W] image inputs, a [1,2,H,W] output) instead of Lucas-Kanade.
    #[arg(long)]
    pub flow_model: Option<PathBuf>,
    /// The value range --flow-model expects its images in.
    #[arg(long, value_enum, default_value = "bytes")]
    pub flow_model_input: FlowRangeArg,
    /// Segment Anything's image encoder (ONNX) for the object candidates, instead of graph segmentation.
    #[arg(long, requires = "sam_decoder")]
    pub sam_encoder: Option<PathBuf>,
    /// Segment Anything's prompt decoder (ONNX; segment-anything's export interface).
    #[arg(long, requires = "sam_encoder")]
    pub sam_decoder: Option<PathBuf>,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum DepthOutputArg {
    /// Relative inverse depth (larger is nearer), as Depth Anything V2's relative models give.
    Disparity,
    /// Metres.
    Metres,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FlowRangeArg {
    /// 0..255
    Bytes,
    /// 0..1
    Unit,
    /// -1..1
    Signed,
}

impl LearnedArgs {
    fn models(&self) -> LearnedModels {
        use omniscan_mask::depth::DepthOutput;
        use omniscan_mask::flow::FlowInputRange;
        LearnedModels {
            onnx_runtime: self.onnx_runtime.clone(),
            depth: self.depth_model.clone(),
            depth_output: match self.depth_model_output {
                DepthOutputArg::Disparity => DepthOutput::Disparity,
                DepthOutputArg::Metres => DepthOutput::Metres,
            },
            flow: self.flow_model.clone(),
            flow_range: match self.flow_model_input {
                FlowRangeArg::Bytes => FlowInputRange::Bytes,
                FlowRangeArg::Unit => FlowInputRange::Unit,
                FlowRangeArg::Signed => FlowInputRange::Signed,
            },
            sam_encoder: self.sam_encoder.clone(),
            sam_decoder: self.sam_decoder.clone(),
            ..LearnedModels::default()
        }
    }
}

impl MaskSettingsArgs {
    fn settings(&self) -> Result<MaskSettings> {
        let mut s = MaskSettings::default();
        for (name, v) in [
            ("--non-robot-threshold-mm", self.non_robot_threshold_mm),
            ("--near-margin-m", self.near_margin_m),
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
        if !(self.depth_noise_mm_at_1m.is_finite() && self.depth_noise_mm_at_1m >= 0.0) {
            bail!(
                "--depth-noise-mm-at-1m must be a non-negative number, got {}",
                self.depth_noise_mm_at_1m
            );
        }
        s.gripper.depth_noise_m_at_1m = self.depth_noise_mm_at_1m * 1e-3;
        Ok(s)
    }
}

#[derive(clap::Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct MaskArgs {
    #[command(subcommand)]
    pub command: Option<MaskCommand>,
    /// Capture directory (or its capture.json).
    #[arg(required = true)]
    pub capture: Option<PathBuf>,
    #[command(flatten)]
    pub settings: MaskSettingsArgs,
    /// Compare the masks with the simulator's ground truth (mean IoU per arm).
    #[arg(long)]
    pub eval: bool,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Subcommand)]
pub enum MaskCommand {
    /// Train the gripper U-Net on simulated captures' ground-truth gripper masks.
    TrainGripper(TrainGripperArgs),
    /// Convert a trained gripper U-Net (safetensors) to ONNX.
    ExportGripper(ExportGripperArgs),
}

#[derive(clap::Args)]
pub struct ExportGripperArgs {
    /// The network from `omniscan mask train-gripper`.
    pub network: PathBuf,
    /// Where to write the ONNX model.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(clap::Args)]
pub struct TrainGripperArgs {
    /// Simulated captures to learn from (their frames and empty-gripper frames).
    #[arg(required = true)]
    pub captures: Vec<PathBuf>,
    /// Where to write the network (safetensors).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write the network as ONNX here (input `rgb` [1,3,H,W] 0..255, output `probability`), for other tools or --unet.
    #[arg(long)]
    pub onnx: Option<PathBuf>,
    #[arg(long, default_value_t = 800)]
    pub steps: usize,
    /// Images per step.
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    #[arg(long, default_value_t = 3e-3)]
    pub learning_rate: f32,
    /// Working width of the network, pixels (a multiple of 4).
    #[arg(long, default_value_t = 160)]
    pub width: usize,
    /// Working height of the network, pixels (a multiple of 4).
    #[arg(long, default_value_t = 120)]
    pub height: usize,
    /// Use every n-th image of each capture.
    #[arg(long, default_value_t = 1)]
    pub every: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long)]
    pub json: bool,
}

fn train_gripper(args: TrainGripperArgs) -> Result<()> {
    use omniscan_mask::unet::{TrainSettings, UNet, train};
    if args.steps == 0 || args.batch == 0 || args.every == 0 {
        bail!("--steps, --batch and --every must be at least 1");
    }
    if !(args.learning_rate.is_finite() && args.learning_rate > 0.0) {
        bail!("--learning-rate must be a positive number");
    }
    let mut net = UNet::new(args.width, args.height, [8, 16, 32], args.seed)?;
    let captures = args
        .captures
        .iter()
        .map(|c| Capture::load(c))
        .collect::<std::result::Result<Vec<_>, _>>()?;
    let (examples, held_out) =
        omniscan_mask::pipeline::gripper_training_set(&net, &captures, args.every)?;
    eprintln!(
        "training on {} images, {} held out, at {}x{}",
        examples.len(),
        held_out.len(),
        args.width,
        args.height
    );
    let settings = TrainSettings {
        steps: args.steps,
        batch: args.batch,
        learning_rate: args.learning_rate,
        seed: args.seed,
    };
    let bar = indicatif::ProgressBar::new(args.steps as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "training [{bar:40}] {pos}/{len} steps, {msg} ({eta})",
        )
        .unwrap()
        .progress_chars("=> "),
    );
    let start = Instant::now();
    let final_loss = train(&mut net, &examples, &settings, &|step, loss| {
        bar.set_position(step as u64);
        bar.set_message(format!("loss {loss:.4}"));
    })?;
    bar.finish_and_clear();
    let seconds = start.elapsed().as_secs_f64();
    net.save(&args.out)?;
    if let Some(onnx) = &args.onnx {
        omniscan_core::io::write_atomic(onnx, &net.to_onnx())
            .with_context(|| format!("writing {}", onnx.display()))?;
    }
    let ious: Vec<f64> = held_out
        .par_iter()
        .map(|(image, truth)| iou(&net.mask(image), truth))
        .collect();
    let mean_iou = ious.iter().sum::<f64>() / ious.len().max(1) as f64;
    let min_iou = ious.iter().cloned().fold(1.0, f64::min);
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({
                "out": args.out, "training_images": examples.len(), "held_out_images": held_out.len(),
                "final_loss": final_loss, "held_out_gripper_miou": mean_iou, "held_out_min_iou": min_iou,
                "seconds": seconds, "settings": settings,
            }))?
        );
    } else {
        println!(
            "wrote {}: final loss {final_loss:.4}; held-out gripper mIoU {mean_iou:.4} (lowest {min_iou:.3}) over {} images; {seconds:.0} s",
            args.out.display(),
            held_out.len()
        );
    }
    Ok(())
}

/// The masker for `capture` with the gripper method and learned backends the
/// options name.
fn masker_for(
    capture: &Capture,
    args: &MaskSettingsArgs,
    settings: MaskSettings,
) -> Result<Masker> {
    let masker = Masker::new(capture, args.gripper_dir.as_deref(), settings)?
        .with_learned(&args.learned.models())?;
    let runtime = args.learned.onnx_runtime.as_deref();
    Ok(match (args.gripper, args.unet.as_deref()) {
        (GripperMethod::Kinematic, None) => masker,
        (GripperMethod::Kinematic, Some(_)) => {
            bail!("--unet is used only with --gripper unet or --gripper both")
        }
        (_, None) => {
            bail!("--gripper unet|both needs --unet FILE (from `omniscan mask train-gripper`)")
        }
        (method, Some(file)) => masker.with_unet(file, method == GripperMethod::Both, runtime)?,
    })
}

pub fn run(args: MaskArgs) -> Result<()> {
    match args.command {
        Some(MaskCommand::TrainGripper(train_args)) => return train_gripper(train_args),
        Some(MaskCommand::ExportGripper(export)) => {
            let net = omniscan_mask::unet::UNet::load(&export.network)?;
            omniscan_core::io::write_atomic(&export.out, &net.to_onnx())
                .with_context(|| format!("writing {}", export.out.display()))?;
            println!("wrote {}", export.out.display());
            return Ok(());
        }
        None => {}
    }
    let capture_path = args.capture.context("a capture directory is required")?;
    let mut capture = Capture::load_unchecked(&capture_path)?;
    // The frames' masks are what this command makes: ones capture.json names
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
    let masker = masker_for(&capture, &args.settings, args.settings.settings()?)?;
    let bar = crate::progress_bar(capture.file.frames.len(), "masking", "frames");
    let summary = mask_capture(&mut capture, &masker, &|done, _| {
        bar.set_position(done as u64)
    })
    .with_context(|| format!("masking {} failed", capture.dir.display()))?;
    bar.finish_and_clear();
    let evaluation = if args.eval {
        Some(evaluate_capture(&capture)?)
    } else {
        None
    };
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({ "masking": summary, "evaluation": evaluation }))?
        );
    } else {
        println!(
            "{} frames masked ({} computed, {} kept from an earlier run) in {:.1} s; masks in {}",
            summary.frames,
            summary.computed,
            summary.resumed,
            summary.seconds,
            capture
                .dir
                .join(omniscan_mask::pipeline::MASK_DIR)
                .display()
        );
        if let Some(e) = evaluation {
            let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.4}"));
            println!(
                "object mIoU: left {}, right {} (lowest frame {:.3}); gripper mIoU: left {}, right {} (lowest frame {:.3})",
                f(e.object_miou.left),
                f(e.object_miou.right),
                e.object_min_iou,
                f(e.gripper_miou.left),
                f(e.gripper_miou.right),
                e.gripper_min_iou
            );
        }
    }
    Ok(())
}

#[derive(clap::Args)]
pub struct BenchArgs {
    /// Simulated captures to mask (each a directory with capture.json and ground truth).
    #[arg(required = true)]
    pub captures: Vec<PathBuf>,
    /// Mask only every n-th frame of each capture.
    #[arg(long, default_value_t = 1)]
    pub every: usize,
    /// Perturb every recorded gripper pose by this translation (random direction, per frame), millimetres: a robot's calibration error.
    #[arg(long, default_value_t = 0.0)]
    pub pose_error_mm: f64,
    /// Perturb every recorded gripper pose by this rotation (random axis, per frame), degrees.
    #[arg(long, default_value_t = 0.0)]
    pub pose_error_deg: f64,
    /// Seed of the pose perturbations.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub settings: MaskSettingsArgs,
    #[arg(long)]
    pub json: bool,
}

/// Moves every recorded gripper pose by `mm` and `deg` in seeded random
/// directions, as an uncalibrated robot would report them.
fn perturb_poses(capture: &mut Capture, mm: f64, deg: f64, seed: u64) {
    use nalgebra::{Translation3, Unit, UnitQuaternion};
    use rand::SeedableRng;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut unit = move || omniscan_core::geometry::random_unit_vector(&mut rng);
    let frames = capture
        .file
        .frames
        .iter_mut()
        .chain(capture.file.empty_frames.iter_mut());
    for frame in frames {
        let error = nalgebra::Isometry3::from_parts(
            Translation3::from(unit() * mm * 1e-3),
            UnitQuaternion::from_axis_angle(&Unit::new_normalize(unit()), deg.to_radians()),
        );
        frame.gripper_to_world.0 *= error;
    }
}

/// Masks captures in memory (nothing is written), timing each stage and
/// scoring against ground truth.
pub fn bench(args: BenchArgs) -> Result<()> {
    if args.every == 0 {
        bail!("--every must be at least 1");
    }
    let settings = args.settings.settings()?;
    let mut rows = Vec::new();
    for path in &args.captures {
        let mut capture = Capture::load(path)?;
        if args.pose_error_mm != 0.0 || args.pose_error_deg != 0.0 {
            perturb_poses(
                &mut capture,
                args.pose_error_mm,
                args.pose_error_deg,
                args.seed,
            );
        }
        let masker = masker_for(&capture, &args.settings, settings.clone())?;
        let frames: Vec<usize> = (0..capture.file.frames.len()).step_by(args.every).collect();
        // Latency: one frame at a time (each stage may still use both cores).
        let latency_frames: Vec<usize> = frames.iter().copied().take(10).collect();
        let start = Instant::now();
        for &i in &latency_frames {
            mask_frame(&masker, &capture, i)?;
        }
        let latency_s = start.elapsed().as_secs_f64() / latency_frames.len().max(1) as f64;
        // Throughput: frames in parallel, as `omniscan mask` runs them.
        let bar = crate::progress_bar(frames.len(), "bench mask", "frames");
        let start = Instant::now();
        let results: Vec<(FrameScore, FrameTimings)> = frames
            .par_iter()
            .map(|&i| -> Result<_> {
                let m = mask_frame(&masker, &capture, i)?;
                let score = score_frame(&capture, i, &m.object, &m.gripper)?;
                bar.inc(1);
                Ok((score, m.timings))
            })
            .collect::<Result<_>>()?;
        let throughput_s = start.elapsed().as_secs_f64() / frames.len().max(1) as f64;
        bar.finish_and_clear();
        let scores: Vec<FrameScore> = results.iter().map(|r| r.0.clone()).collect();
        let evaluation = summarise(&scores);
        let n = results.len().max(1) as f64;
        let mean = |f: fn(&FrameTimings) -> f64| results.iter().map(|r| f(&r.1)).sum::<f64>() / n;
        let object = capture
            .file
            .gt
            .as_ref()
            .and_then(|g| g.extra.get("object"))
            .and_then(|o| o.get("name"))
            .and_then(|n| n.as_str())
            .unwrap_or("?")
            .to_string();
        let (w, h) = (capture.intrinsics().width, capture.intrinsics().height);
        rows.push(json!({
            "capture": path,
            "object": object,
            "size": [w, h],
            "pose_error_mm": args.pose_error_mm,
            "pose_error_deg": args.pose_error_deg,
            "gripper_method": masker.settings.gripper_method,
            "frames": results.len(),
            "object_miou": evaluation.object_miou,
            "gripper_miou": evaluation.gripper_miou,
            "object_min_iou": evaluation.object_min_iou,
            "gripper_min_iou": evaluation.gripper_min_iou,
            "worst_object": evaluation.worst_object,
            "worst_gripper": evaluation.worst_gripper,
            "seconds_per_image_sequential": latency_s,
            "seconds_per_image_parallel": throughput_s,
            "stage_seconds": {
                "load": mean(|t| t.load_s),
                "depth": mean(|t| t.depth_s),
                "gripper": mean(|t| t.gripper_s),
                "flow": mean(|t| t.flow_s),
                "object": mean(|t| t.object_s),
            },
        }));
        if !args.json {
            let r = rows.last().unwrap();
            println!(
                "{:<22} {}x{} {:>4} frames  object mIoU L {:.4} R {:.4} (min {:.3})  gripper mIoU L {:.4} R {:.4} (min {:.3})  {:.3} s/image sequential, {:.3} s/image parallel",
                object,
                w,
                h,
                results.len(),
                r["object_miou"]["left"].as_f64().unwrap_or(0.0),
                r["object_miou"]["right"].as_f64().unwrap_or(0.0),
                r["object_min_iou"].as_f64().unwrap_or(0.0),
                r["gripper_miou"]["left"].as_f64().unwrap_or(0.0),
                r["gripper_miou"]["right"].as_f64().unwrap_or(0.0),
                r["gripper_min_iou"].as_f64().unwrap_or(0.0),
                latency_s,
                throughput_s
            );
            let worst = |list: &[FrameScore], f: fn(&FrameScore) -> f64| {
                list.iter()
                    .take(3)
                    .map(|s| format!("{} {:.3}", s.file, f(s)))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            println!(
                "    stages (s/image): load {:.3}, depth {:.3}, gripper {:.3}, flow {:.3}, object {:.3}; worst object frames: {}; worst gripper frames: {}",
                mean(|t| t.load_s),
                mean(|t| t.depth_s),
                mean(|t| t.gripper_s),
                mean(|t| t.flow_s),
                mean(|t| t.object_s),
                worst(&evaluation.worst_object, |s| s.object_iou),
                worst(&evaluation.worst_gripper, |s| s.gripper_iou)
            );
        }
    }
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({ "captures": rows }))?
        );
    }
    Ok(())
}
