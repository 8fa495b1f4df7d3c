//! `omniscan bench mask`: mask accuracy against ground truth and time per
//! frame, frame by frame (latency) and in parallel (throughput).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Result, bail};
use rayon::prelude::*;
use serde_json::json;

use omniscan_core::capture::Capture;
use omniscan_mask::pipeline::{FrameScore, FrameTimings, mask_frame, score_frame, summarise};
use omniscan_pipeline::mask::MaskingSettings;

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
    pub settings: MaskingSettings,
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
    // Bad values are refused before any capture is read.
    args.settings.resolve()?;
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
        let masker = args.settings.masker(&capture)?;
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
