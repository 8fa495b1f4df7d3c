//! `omniscan mask train-gripper` and `export-gripper`: the paper's learned
//! gripper segmentation, a U-Net trained on simulated captures' ground
//! truth, and its ONNX export.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use rayon::prelude::*;
use serde_json::json;

use omniscan_core::capture::Capture;
use omniscan_mask::plane::iou;

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
    /// Also write the network as ONNX here (input `rgb`, `[1,3,H,W]` in 0..255; output `probability`), for other tools or --unet.
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

/// Runs a gripper subcommand of `omniscan mask`.
pub fn run(command: MaskCommand) -> Result<()> {
    match command {
        MaskCommand::TrainGripper(args) => train_gripper(args),
        MaskCommand::ExportGripper(export) => {
            let net = omniscan_mask::unet::UNet::load(&export.network)?;
            omniscan_core::io::write_atomic(&export.out, &net.to_onnx())
                .with_context(|| format!("writing {}", export.out.display()))?;
            println!("wrote {}", export.out.display());
            Ok(())
        }
    }
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
