//! A capture to its 360° digital twin, the paper's "3DGS Training" section
//! as one resumable function.
//!
//! Four stages:
//! 1. [`train`] the left and 2. the right arm: one model per arm, each in
//!    its gripper's frame;
//! 3. [`align`] the right model onto the left from the robot's handover
//!    estimate T_lh⁻¹·T_rh, refined by ICP and colored ICP, the better
//!    fitness winning (the paper's rule, with near-ties to the lower RMSE),
//!    then by rendering the left model into the right arm's views
//!    (`omniscan_splat::offset`: the points stop degrees short where the
//!    grippers hid the object);
//! 4. [`train`] both arms, merged by that transform, initialised from both
//!    arms' models: the twin.
//!
//! Every training uses the fixed-rig appearance (SH by the splats' normals
//! in the camera's frame): the two arms' views of one side, lit by the same
//! fixed lights from different turns, disagree by viewing direction.
//!
//! Every stage writes its output atomically and a record beside it
//! (`OUTPUT.record.json`) keyed by the content of what it was made from:
//! the capture's `capture.json`, the settings, and the bytes of the models
//! and transform it reads, never their paths. A second run reuses each
//! stage whose key is unchanged and whose output is there, and resumes an
//! interrupted training from its checkpoint; a moved output folder or
//! capture with the same bytes reuses every finished stage.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use omniscan_core::digest::Digest;
use omniscan_splat::backend::Backend;

use crate::Progress;
use crate::align::{AlignReport, AlignSettings, PoseError, align};
use crate::settings::default_from_flags;
use crate::train::{AppearanceChoice, TrainReport, TrainSettings, checkpoint_path, train};
use crate::views::{ArmSet, Merge};

/// Everything `twin` can be told besides its capture and output folder.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TwinSettings {
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
    pub backend: Backend,
    /// On a GPU: how much of the views' loss targets stays on the device, gigabytes (as `train`'s; it changes no result, so a finished stage is reused whatever it was).
    #[arg(long, default_value_t = omniscan_splat::gpu::training::DEFAULT_VIEW_MEMORY as f64 / 1e9)]
    pub gpu_view_memory_gb: f64,
    /// Train and align a simulated capture that has no masks of its own on the simulator's ground-truth masks (for experiments on training alone; the reports say so). Without it a capture needs `omniscan mask` first.
    #[arg(long)]
    pub use_ground_truth_masks: bool,
    /// Pose refinement in each of the three trainings (`train --refine-poses`).
    #[command(flatten)]
    #[serde(flatten)]
    pub poses: crate::pose_refinement::PoseSettings,
}

default_from_flags!(TwinSettings);

/// What a stage did.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StageStatus {
    Ran,
    Resumed,
    Reused,
}

/// A stage's status and report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stage<R> {
    pub status: StageStatus,
    pub report: R,
}

/// The four stages' reports.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TwinStages {
    pub left: Stage<TrainReport>,
    pub right: Stage<TrainReport>,
    pub align: Stage<AlignReport>,
    pub twin: Stage<TrainReport>,
}

/// Errors of the merge against the simulator's truth.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AlignmentError {
    pub handover_estimate: PoseError,
    pub refined: PoseError,
    /// The point registration's own transform, before the images refined it.
    pub points_only: Option<PoseError>,
}

/// What [`twin`] made; also `OUT/summary.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TwinReport {
    pub capture: PathBuf,
    pub twin: PathBuf,
    pub right_to_left: PathBuf,
    pub stages: TwinStages,
    /// Only for a capture with ground truth (a simulated one).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub alignment_error: Option<AlignmentError>,
}

/// A stage's record: the key of what it was made from, and, once it has
/// run, the digest of the output it wrote and its report.
#[derive(Serialize, Deserialize)]
struct Record<R> {
    key: String,
    output: Option<String>,
    report: Option<R>,
}

/// The digest of a file's bytes; `None` if it cannot be read.
fn file_digest(path: &Path) -> Option<String> {
    std::fs::read(path).ok().map(|bytes| Digest::of(&bytes))
}

/// The stage whose output is `output`: reused when its record has `key`
/// and a report and the output has the bytes it wrote; resumed from `checkpoint` when
/// the record has `key` (an interrupted run of the same stage); run
/// otherwise, after removing a checkpoint left by other inputs. `run` gets
/// whether to resume.
fn stage<R: Serialize + serde::de::DeserializeOwned>(
    output: &Path,
    checkpoint: Option<&Path>,
    key: &str,
    progress: &dyn Progress,
    run: impl FnOnce(bool) -> Result<R>,
) -> Result<Stage<R>> {
    let record = output.with_extension("record.json");
    let previous = std::fs::read_to_string(&record)
        .ok()
        .and_then(|text| serde_json::from_str::<Record<R>>(&text).ok())
        .filter(|p| p.key == key);
    let name = output.file_name().unwrap_or_default().to_string_lossy();
    let same_inputs = previous.is_some();
    if let Some(Record {
        output: Some(digest),
        report: Some(report),
        ..
    }) = previous
        && file_digest(output).as_ref() == Some(&digest)
    {
        progress.note(&format!("reused {name} (unchanged)"));
        return Ok(Stage {
            status: StageStatus::Reused,
            report,
        });
    }
    let resume = match checkpoint {
        Some(c) if c.is_file() && same_inputs => true,
        Some(c) if c.is_file() => {
            progress.note(&format!(
                "removing {}: it belongs to other inputs or settings than this run's",
                c.display()
            ));
            std::fs::remove_file(c).with_context(|| format!("removing {}", c.display()))?;
            false
        }
        _ => false,
    };
    let running = Record::<R> {
        key: key.into(),
        output: None,
        report: None,
    };
    omniscan_core::io::write_json_atomic(&record, &running)?;
    progress.note(&format!(
        "{} {name}",
        if resume { "resuming" } else { "making" }
    ));
    let report = run(resume)?;
    let done = Record {
        key: key.to_string(),
        output: Some(
            file_digest(output).with_context(|| format!("reading {} back", output.display()))?,
        ),
        report: Some(&report),
    };
    omniscan_core::io::write_json_atomic(&record, &done)?;
    Ok(Stage {
        status: if resume {
            StageStatus::Resumed
        } else {
            StageStatus::Ran
        },
        report,
    })
}

/// The key of a stage: its kind, its settings (as JSON, paths inside the
/// output folder named relative to it) and the digests of its input files.
fn stage_key(kind: &str, settings: &impl Serialize, inputs: &[&Path]) -> Result<String> {
    let mut digest = Digest::default();
    digest.add(kind.as_bytes());
    digest.add(&serde_json::to_vec(settings)?);
    for input in inputs {
        let bytes = std::fs::read(input).with_context(|| format!("reading {}", input.display()))?;
        // A JSON input (capture.json, the transform) is known by what it
        // says: `mask` writes capture.json back with its poses moved in the
        // last bits, which must not make the twin again.
        let bytes = match input.extension().is_some_and(|e| e == "json") {
            true => match serde_json::from_slice::<serde_json::Value>(&bytes) {
                Ok(v) => omniscan_core::digest::stable_json(v)
                    .to_string()
                    .into_bytes(),
                Err(_) => bytes,
            },
            false => bytes,
        };
        digest.add(&(bytes.len() as u64).to_le_bytes());
        digest.add(&bytes);
    }
    Ok(digest.hex())
}

/// Builds the twin of `capture` in `out` (created if missing; finished
/// stages reused), writes `OUT/summary.json` and returns it.
pub fn twin(
    capture_path: &Path,
    out: &Path,
    settings: &TwinSettings,
    progress: &dyn Progress,
) -> Result<TwinReport> {
    let capture = omniscan_core::Capture::load(capture_path)?;
    let capture_file = capture.resolve(omniscan_core::capture::CAPTURE_FILE);
    let _lock = omniscan_core::lock::OutputLock::folder(out, "twin")?;
    let (left, right) = (out.join("left.ply"), out.join("right.ply"));
    let transform = out.join("right_to_left.json");
    let twin = out.join("twin.ply");

    let left_stage = train_stage(
        capture_path,
        &capture_file,
        &left,
        ArmSet::Left,
        None,
        settings,
        progress,
    )?;
    let right_stage = train_stage(
        capture_path,
        &capture_file,
        &right,
        ArmSet::Right,
        None,
        settings,
        progress,
    )?;

    let align_settings = AlignSettings {
        handover: Some(capture_path.to_path_buf()),
        photometric: true,
        downscale: settings.downscale,
        use_ground_truth_masks: settings.use_ground_truth_masks,
        ..AlignSettings::default()
    };
    let align_key = stage_key(
        "align",
        &AlignSettings {
            handover: None,
            ..align_settings.clone()
        },
        &[&capture_file, &right, &left],
    )?;
    let mut align_stage = stage(&transform, None, &align_key, progress, |_| {
        align(&right, &left, &transform, &align_settings)
    })?;
    align_stage.report.source = right.clone();
    align_stage.report.target = left.clone();

    let merged = MergedInputs {
        transform: &transform,
        init_left: &left,
        init_right: &right,
    };
    let twin_stage = train_stage(
        capture_path,
        &capture_file,
        &twin,
        ArmSet::Both,
        Some(merged),
        settings,
        progress,
    )?;
    let alignment_error = alignment_error(&capture, &align_stage.report)?;
    let report = TwinReport {
        capture: capture_path.to_path_buf(),
        twin,
        right_to_left: transform,
        stages: TwinStages {
            left: left_stage,
            right: right_stage,
            align: align_stage,
            twin: twin_stage,
        },
        alignment_error,
    };
    omniscan_core::io::write_json_atomic(&out.join("summary.json"), &report)?;
    crate::reports::write_twin_report(out, &report, settings)?;
    Ok(report)
}

/// The merged training's inputs, made by the earlier stages.
#[derive(Clone, Copy)]
struct MergedInputs<'a> {
    transform: &'a Path,
    init_left: &'a Path,
    init_right: &'a Path,
}

/// A training stage of the twin: one arm, or both merged by `merged`'s
/// transform and started from its models.
fn train_stage(
    capture: &Path,
    capture_file: &Path,
    out: &Path,
    arm: ArmSet,
    merged: Option<MergedInputs>,
    twin: &TwinSettings,
    progress: &dyn Progress,
) -> Result<Stage<TrainReport>> {
    let mut settings = TrainSettings {
        arm,
        steps: twin.steps,
        downscale: twin.downscale,
        seed: twin.seed,
        backend: twin.backend,
        checkpoint_every: twin.checkpoint_every,
        gpu_view_memory_gb: twin.gpu_view_memory_gb,
        use_ground_truth_masks: twin.use_ground_truth_masks,
        appearance: AppearanceChoice::FixedRig,
        poses: twin.poses.clone(),
        ..TrainSettings::default()
    };
    let mut inputs = vec![capture_file];
    if let Some(m) = merged {
        settings.merge = Merge {
            right_to_left: Some(m.transform.to_path_buf()),
        };
        settings.init = Some(m.init_left.to_path_buf());
        settings.init_right = Some(m.init_right.to_path_buf());
        inputs.extend([m.transform, m.init_left, m.init_right]);
    }
    // The key knows the inputs by their bytes, so their paths stay out of
    // it, and so does what changes no result.
    let key_settings = TrainSettings {
        merge: Merge::default(),
        init: None,
        init_right: None,
        gpu_view_memory_gb: 0.0,
        ..settings.clone()
    };
    let key = stage_key("train", &key_settings, &inputs)?;
    let checkpoint = checkpoint_path(out);
    let mut stage = stage(out, Some(&checkpoint), &key, progress, |resume| {
        train(
            capture,
            out,
            &TrainSettings {
                resume,
                ..settings.clone()
            },
            progress,
        )
    })?;
    // A reused report names the files where they are now.
    stage.report.model = out.to_path_buf();
    if let (Some(m), Some(merged_by)) = (merged, stage.report.settings.right_to_left.as_mut()) {
        merged_by.from = m.transform.display().to_string();
        stage.report.settings.init = crate::train::StartedFrom::Points(vec![
            m.init_left.to_path_buf(),
            m.init_right.to_path_buf(),
        ]);
    }
    Ok(stage)
}

/// How far the handover estimate, the point registration and the refined
/// transform are from the truth, for a capture that knows it.
fn alignment_error(
    capture: &omniscan_core::Capture,
    align: &AlignReport,
) -> Result<Option<AlignmentError>> {
    let Some(gt) = &capture.file.gt else {
        return Ok(None);
    };
    let truth = gt.right_to_left.0;
    let estimate = omniscan_core::poses::handover_estimate(capture);
    let points_only = match &align.photometric {
        Some(fit) => Some(PoseError::between(
            &omniscan_core::geometry::pose_from_rows(&fit.from)?,
            &truth,
        )),
        None => None,
    };
    Ok(Some(AlignmentError {
        handover_estimate: PoseError::between(&estimate, &truth),
        refined: PoseError::between(&align.transform()?, &truth),
        points_only,
    }))
}
