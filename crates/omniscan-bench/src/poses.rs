//! `omniscan bench poses`: pose refinement against simulated calibration
//! error (issue 53). The same scan simulated twice, with exact recorded
//! poses and with `--noise-deg/--noise-mm` of error in each frame's
//! (`sim --pose-noise-*`), trained on one arm three ways in the same run:
//! the exact poses, the noisy poses as recorded, and the noisy poses with
//! `--refine-poses`. Held-out views are scored at their recorded poses, or
//! after test-time fitting with refinement; the refined run's report
//! compares its corrections with the simulator's true poses.
//!
//! Captures and models are kept under `--out` and reused on a second run.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde_json::json;

use omniscan_pipeline::Bars;
use omniscan_pipeline::pose_refinement::PoseSettings;
use omniscan_pipeline::train::{TrainReport, TrainSettings, train};
use omniscan_pipeline::views::ArmSet;
use omniscan_sim::SimConfig;
use omniscan_splat::backend::Backend;

#[derive(clap::Args)]
pub struct BenchArgs {
    /// Folder for the captures, models and reports (reused when run again).
    #[arg(long)]
    pub out: PathBuf,
    /// The built-in object scanned.
    #[arg(long, default_value = "remote")]
    pub object: String,
    /// RMS rotation error put into each frame's recorded gripper pose, degrees.
    #[arg(long, default_value_t = 0.5)]
    pub noise_deg: f64,
    /// RMS translation error put into each frame's recorded gripper pose, mm.
    #[arg(long, default_value_t = 1.0)]
    pub noise_mm: f64,
    /// Simulated image width and height, pixels.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Training steps of each model.
    #[arg(long, default_value_t = 3000)]
    pub steps: usize,
    /// Images are shrunk by this factor for training.
    #[arg(long, default_value_t = 2)]
    pub downscale: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Where the three trainings run: cpu, gpu (any device) or auto; off the
    /// CPU the models and reports get the backend's name as a suffix
    /// (`refined-gpu.json`), so runs on both can share --out.
    #[arg(long, default_value = "cpu")]
    pub backend: Backend,
    #[command(flatten)]
    pub poses: PoseSettings,
    #[arg(long)]
    pub json: bool,
}

fn simulated(args: &BenchArgs, dir: &Path, noisy: bool) -> Result<()> {
    if dir.join("capture.json").exists() {
        return Ok(());
    }
    let config = SimConfig {
        object: format!("builtin:{}", args.object),
        width: args.width,
        height: args.height,
        seed: args.seed,
        pose_noise_deg: if noisy { args.noise_deg } else { 0.0 },
        pose_noise_mm: if noisy { args.noise_mm } else { 0.0 },
        // Training on the simulator's masks: no empty pass needed.
        empty_pass: false,
        ..SimConfig::default()
    };
    omniscan_pipeline::simulate::simulate_config(config, dir, &Bars::new())?;
    Ok(())
}

/// A model of `capture`'s left arm (reused with its report when there).
fn trained(args: &BenchArgs, capture: &Path, name: &str, refine: bool) -> Result<TrainReport> {
    let name = match args.backend {
        Backend::Cpu => name.to_string(),
        Backend::Gpu => format!("{name}-gpu"),
        Backend::Auto => format!("{name}-auto"),
    };
    let out = args.out.join(format!("{name}.ply"));
    let report_path = args.out.join(format!("{name}.json"));
    if out.exists() && report_path.exists() {
        let text = std::fs::read_to_string(&report_path)?;
        return serde_json::from_str(&text)
            .with_context(|| format!("reading {}", report_path.display()));
    }
    eprintln!("training {name}");
    let settings = TrainSettings {
        arm: ArmSet::Left,
        steps: args.steps,
        downscale: args.downscale,
        seed: args.seed,
        use_ground_truth_masks: true,
        backend: args.backend,
        poses: PoseSettings {
            refine_poses: refine,
            ..args.poses.clone()
        },
        ..TrainSettings::default()
    };
    let report = train(capture, &out, &settings, &Bars::new())?;
    omniscan_core::io::write_atomic(&report_path, serde_json::to_vec_pretty(&report)?.as_slice())?;
    Ok(report)
}

fn db(psnr: Option<f64>) -> String {
    psnr.map_or("-".into(), |p| format!("{p:.2}"))
}

pub fn bench(args: BenchArgs) -> Result<()> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let (clean, noisy) = (args.out.join("exact"), args.out.join("noisy"));
    simulated(&args, &clean, false)?;
    simulated(&args, &noisy, true)?;
    let runs = [
        ("exact poses", trained(&args, &clean, "exact", false)?),
        (
            "noisy poses as recorded",
            trained(&args, &noisy, "noisy", false)?,
        ),
        (
            "noisy poses, --refine-poses",
            trained(&args, &noisy, "refined", true)?,
        ),
    ];
    let truth = (runs[2].1.poses.as_ref()).and_then(|p| p.against_truth);
    if args.json {
        let rows: Vec<_> = (runs.iter())
            .map(|(name, r)| {
                json!({
                    "run": name,
                    "held_out_masked_psnr_db": r.test.psnr_masked,
                    "train_masked_psnr_db": r.train.psnr_masked,
                    "seconds": r.seconds,
                })
            })
            .collect();
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({ "runs": rows, "poses_against_truth": truth }))?
        );
        return Ok(());
    }
    println!(
        "builtin:{} {}x{} (training at 1/{}), {} steps, left arm, noise {}° / {} mm per frame",
        args.object,
        args.width,
        args.height,
        args.downscale,
        args.steps,
        args.noise_deg,
        args.noise_mm
    );
    println!("| run | held-out masked PSNR (dB) | training views (dB) | seconds |");
    println!("|---|---|---|---|");
    for (name, r) in &runs {
        println!(
            "| {name} | {} | {} | {:.0} |",
            db(r.test.psnr_masked),
            db(r.train.psnr_masked),
            r.seconds
        );
    }
    if let (Some(refined), Some(exact)) = (runs[2].1.test.psnr_masked, runs[0].1.test.psnr_masked) {
        println!(
            "refined held-out PSNR minus exact poses': {:+.2} dB",
            refined - exact
        );
    }
    if let Some(t) = truth {
        println!(
            "| poses against the truth (RMS / max) | rotation (°) | translation (mm) | across the view (mm) | along the view (mm) | roll about the view (°) | tilt across it (°) |"
        );
        println!("|---|---|---|---|---|---|---|");
        let rows = [
            ("recorded", Some(t.recorded)),
            ("refined, training views", Some(t.train)),
            ("fitted, held-out views", t.held_out),
        ];
        for (name, e) in rows {
            if let Some(e) = e {
                println!(
                    "| {name} | {:.3} / {:.3} | {:.3} / {:.3} | {:.3} | {:.3} | {:.3} | {:.3} |",
                    e.rms_rotation_deg,
                    e.max_rotation_deg,
                    e.rms_translation_mm,
                    e.max_translation_mm,
                    e.rms_across_view_mm,
                    e.rms_along_view_mm,
                    e.rms_roll_deg,
                    e.rms_tilt_deg
                );
            }
        }
    }
    Ok(())
}
