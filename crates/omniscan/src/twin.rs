//! `omniscan twin`: a capture to its 360° digital twin, the paper's
//! "3DGS Training" section as one resumable command.
//!
//! Four stages, each the command a user would run by hand:
//! 1. `train --arm left` and 2. `train --arm right`: one model per arm, each
//!    in its gripper's frame;
//! 3. `align right.ply left.ply --handover CAPTURE --photometric`: the right
//!    model onto the left from the robot's handover estimate T_lh⁻¹·T_rh,
//!    refined by ICP and colored ICP, the better fitness winning (the
//!    paper's rule, with near-ties to the lower RMSE), then by rendering the
//!    left model into the right arm's views (`omniscan_splat::offset`:
//!    the points stop degrees short where the grippers hid the object);
//! 4. `train --arm both --right-to-left` that transform, initialised from
//!    both arms' models: the merged twin.
//!
//! Every training uses the fixed-rig appearance (SH by the splats' normals
//! in the camera's frame): the two arms' views of one side, lit by the same
//! fixed lights from different turns, disagree by viewing direction.
//!
//! Every stage writes its output atomically and a record of the command it
//! ran (`OUTPUT.record.json`); `summary.json` gathers their reports. A
//! second run reuses each stage whose record names the same command and
//! whose output is there, and resumes an interrupted training from its
//! checkpoint, so a long run stopped anywhere goes on where it stopped.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Parser;
use serde_json::{Value, json};

use omniscan_core::geometry::pose_from_rows;

use crate::registration::{AlignArgs, align_clouds};
use crate::train::{TrainArgs, train_capture};

#[derive(clap::Args)]
pub struct TwinArgs {
    /// The capture directory (both arms' scans, with masks).
    pub capture: PathBuf,
    /// Folder for the stages' models, transform and records (reused when run again).
    #[arg(long)]
    pub out: PathBuf,
    /// Training steps of each arm's model and of the merged twin.
    #[arg(long, default_value_t = 3000)]
    pub steps: usize,
    /// Shrink images by this integer factor for training (2: 640x480 → 320x240).
    #[arg(long, default_value_t = 2)]
    pub downscale: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Each training writes its whole state every N steps, to resume from if stopped (0: never).
    #[arg(long, default_value_t = 500)]
    pub checkpoint_every: usize,
    /// Where training runs: auto (a real GPU when there is one, else the CPU), cpu, or gpu.
    #[arg(long, default_value = "auto")]
    pub backend: omniscan_splat::backend::Backend,
    /// On a GPU: how much of the views' loss targets stays on the device, gigabytes (as `train`'s; it changes no result, so a finished stage is reused whatever it was).
    #[arg(long, default_value_t = omniscan_splat::gpu::training::DEFAULT_VIEW_MEMORY as f64 / 1e9)]
    pub gpu_view_memory_gb: f64,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

/// A stage's command line, parsed as the CLI parses it.
#[derive(Parser)]
struct TrainCommand {
    #[command(flatten)]
    args: TrainArgs,
}

#[derive(Parser)]
struct AlignCommand {
    #[command(flatten)]
    args: AlignArgs,
}

/// What a stage did (`ran`, `resumed` or `reused`) and its report.
struct Stage {
    status: &'static str,
    report: Value,
}

/// Runs `command` (the words after `omniscan`) unless `record` says it ran
/// to its end already and `output` is there. The record names the command
/// before it runs, so an interrupted training (`checkpoint` there) resumes
/// only under the same command; a checkpoint left by another is removed.
/// The record also holds `capture`, a digest of the capture's file: an
/// edited capture runs everything again. With `inputs_changed` (a stage it
/// reads from ran again) nothing of an earlier run is kept either. `run`
/// gets the command and whether to resume.
fn stage(
    record: &Path,
    output: &Path,
    checkpoint: Option<&Path>,
    command: &[String],
    capture: &str,
    inputs_changed: bool,
    run: impl FnOnce(&[String], bool) -> Result<Value>,
) -> Result<Stage> {
    let previous = std::fs::read_to_string(record)
        .ok()
        .and_then(|text| serde_json::from_str::<Value>(&text).ok());
    let same = !inputs_changed
        && previous
            .as_ref()
            .is_some_and(|p| p["command"] == json!(command) && p["capture"] == capture);
    if let Some(previous) = &previous
        && same
        && !previous["report"].is_null()
        && output.is_file()
    {
        return Ok(Stage {
            status: "reused",
            report: previous["report"].clone(),
        });
    }
    let resume = match checkpoint {
        Some(c) if c.is_file() && same => true,
        Some(c) if c.is_file() => {
            eprintln!(
                "removing {}: it belongs to another command or other inputs than this run's",
                c.display()
            );
            std::fs::remove_file(c).with_context(|| format!("removing {}", c.display()))?;
            false
        }
        _ => false,
    };
    let entry =
        |report: &Value| json!({ "command": command, "capture": capture, "report": report });
    omniscan_core::io::write_json_atomic(record, &entry(&Value::Null))?;
    let report = run(command, resume)?;
    omniscan_core::io::write_json_atomic(record, &entry(&report))?;
    Ok(Stage {
        status: if resume { "resumed" } else { "ran" },
        report,
    })
}

/// Where the record of the stage that writes `output` goes: beside it, `NAME.record.json`.
fn record_path(output: &Path) -> PathBuf {
    output.with_extension("record.json")
}

/// A digest of the capture's `capture.json`, to compare runs by.
fn capture_digest(capture: &omniscan_core::Capture) -> Result<String> {
    let file = capture.resolve("capture.json");
    let bytes = std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
    Ok(omniscan_core::digest::Digest::of(&bytes))
}

fn words(parts: &[&str]) -> Vec<String> {
    parts.iter().map(|s| s.to_string()).collect()
}

pub fn run(args: TwinArgs) -> Result<()> {
    let summary = build_twin(&args)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        let test = &summary["stages"]["twin"]["report"]["test"];
        println!(
            "wrote {} ({} splats); held-out views: PSNR {:.2} dB, masked PSNR {:.2} dB; right onto left by {} (fitness {:.4})",
            args.out.join("twin.ply").display(),
            summary["stages"]["twin"]["report"]["splats"],
            test["psnr"].as_f64().unwrap_or(f64::NAN),
            test["psnr_masked"].as_f64().unwrap_or(f64::NAN),
            summary["stages"]["align"]["report"]["method"]
                .as_str()
                .unwrap_or("?"),
            summary["stages"]["align"]["report"]["fitness"]
                .as_f64()
                .unwrap_or(f64::NAN),
        );
    }
    Ok(())
}

/// The four stages; returns the summary also written to `OUT/summary.json`.
pub fn build_twin(args: &TwinArgs) -> Result<Value> {
    let capture = omniscan_core::Capture::load(&args.capture)?;
    let digest = capture_digest(&capture)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let path = |name: &str| args.out.join(name);
    let text = |p: &Path| p.to_string_lossy().into_owned();
    let (capture_path, steps, downscale, seed, every) = (
        text(&args.capture),
        args.steps.to_string(),
        args.downscale.to_string(),
        args.seed.to_string(),
        args.checkpoint_every.to_string(),
    );
    let backend = serde_json::to_value(args.backend)?
        .as_str()
        .unwrap_or("auto")
        .to_string();
    let train = |arm: &str, out: &Path, extra: &[String], inputs_changed: bool| -> Result<Stage> {
        let mut command = words(&["train", &capture_path, "--arm", arm, "--out"]);
        command.push(text(out));
        command.extend(words(&[
            "--steps",
            &steps,
            "--downscale",
            &downscale,
            "--seed",
            &seed,
            "--backend",
            &backend,
            "--checkpoint-every",
            &every,
            // Spelt out, so that a directory made before the setting
            // existed (3DGS's view direction) is remade, not reused.
            "--appearance",
            "fixed-rig",
        ]));
        command.extend_from_slice(extra);
        let mut checkpoint = out.as_os_str().to_owned();
        checkpoint.push(".checkpoint.safetensors");
        let checkpoint = PathBuf::from(checkpoint);
        let record = record_path(out);
        stage(
            &record,
            out,
            Some(&checkpoint),
            &command,
            &digest,
            inputs_changed,
            |command, resume| {
                let mut parsed = TrainCommand::try_parse_from(command)?.args;
                parsed.resume = resume;
                parsed.gpu_view_memory_gb = args.gpu_view_memory_gb;
                if resume {
                    eprintln!("{arm}: resuming from {}", checkpoint.display());
                } else {
                    eprintln!("{arm}: training {}", out.display());
                }
                train_capture(&parsed)
            },
        )
    };
    let (left, right) = (path("left.ply"), path("right.ply"));
    let left_stage = train("left", &left, &[], false)?;
    let right_stage = train("right", &right, &[], false)?;
    let models_changed = left_stage.status != "reused" || right_stage.status != "reused";
    let transform = path("right_to_left.json");
    let mut command = words(&["align"]);
    command.extend([
        text(&right),
        text(&left),
        "--handover".into(),
        capture_path.clone(),
        "--photometric".into(),
        "--downscale".into(),
        downscale.clone(),
    ]);
    command.extend(["--out".into(), text(&transform)]);
    let align_stage = stage(
        &record_path(&transform),
        &transform,
        None,
        &command,
        &digest,
        models_changed,
        |command, _| {
            eprintln!("aligning the right model onto the left");
            align_clouds(&AlignCommand::try_parse_from(command)?.args)
        },
    )?;
    let twin = path("twin.ply");
    let twin_stage = train(
        "both",
        &twin,
        &[
            "--right-to-left".into(),
            text(&transform),
            "--init".into(),
            text(&left),
            "--init-right".into(),
            text(&right),
        ],
        models_changed || align_stage.status != "reused",
    )?;
    let mut summary = json!({
        "capture": args.capture,
        "twin": twin,
        "right_to_left": transform,
        "stages": {},
    });
    for (name, s) in [
        ("left", left_stage),
        ("right", right_stage),
        ("align", align_stage),
        ("twin", twin_stage),
    ] {
        summary["stages"][name] = json!({ "status": s.status, "report": s.report });
    }
    // A simulated capture knows the true transform: how far the handover
    // estimate and the refined one are from it.
    if let Some(gt) = &capture.file.gt {
        let estimate = omniscan_core::poses::handover_estimate(&capture);
        let refined = crate::registration::read_transform(&transform)?;
        let error = |pose: &omniscan_core::Pose| {
            let (angle, distance) =
                omniscan_core::geometry::pose_difference(pose, &gt.right_to_left.0);
            json!({ "deg": angle.to_degrees(), "mm": distance * 1e3 })
        };
        summary["alignment_error"] = json!({
            "handover_estimate": error(&estimate),
            "refined": error(&refined),
        });
        // The point registration's own transform, before the images refined it.
        let from = &summary["stages"]["align"]["report"]["photometric"]["from"];
        if let Ok(rows) = serde_json::from_value::<[[f64; 4]; 4]>(from.clone()) {
            summary["alignment_error"]["points_only"] = error(&pose_from_rows(&rows)?);
        }
    }
    omniscan_core::io::write_json_atomic(&path("summary.json"), &summary)?;
    Ok(summary)
}
