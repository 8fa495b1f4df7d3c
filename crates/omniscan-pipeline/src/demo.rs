//! The whole pipeline on a built-in object, as `omniscan demo` runs it: a
//! simulated scan with a little slip at handover, masks, the paper's merge
//! of the two arms, a nerfstudio export and a first twin.

use std::path::{Path, PathBuf};

use anyhow::Result;
use serde::Serialize;

use omniscan_core::capture::{Capture, CaptureSummary};
use omniscan_core::nerfstudio::{ExportOptions, export_nerfstudio};
use omniscan_core::poses::ViewSet;
use omniscan_sim::SimConfig;
use omniscan_splat::backend::Renderer;
use omniscan_splat::evaluation::Evaluation;
use omniscan_splat::ply::write_splats;
use omniscan_splat::raster::Appearance;
use omniscan_splat::train::{TrainConfig, initial_splats};
use omniscan_splat::trainer::train;
use omniscan_splat::views::{split_held_out, views_from_capture};

use crate::Progress;
use crate::align::{MergeReport, merge_scans};

/// Training steps of the demo's twin: enough to show a recognisable model
/// in seconds on the CPU; `omniscan train` or `twin` give full quality.
pub const DEMO_STEPS: usize = 600;
/// The demo trains at a quarter of the capture's size (160x120).
pub const DEMO_DOWNSCALE: u32 = 4;

/// The demo's masks against ground truth.
#[derive(Clone, Debug, Serialize)]
pub struct DemoMasks {
    pub object_miou: omniscan_mask::pipeline::PerArm,
    pub gripper_miou: omniscan_mask::pipeline::PerArm,
    pub object_min_iou: f64,
    pub gripper_min_iou: f64,
    pub seconds: f64,
}

/// The demo's first twin.
#[derive(Clone, Debug, Serialize)]
pub struct DemoTwin {
    pub model: PathBuf,
    pub splats: usize,
    pub steps: usize,
    /// On the held-out views (every 8th).
    pub test: Evaluation,
}

/// What the demo made.
#[derive(Clone, Debug, Serialize)]
pub struct DemoReport {
    pub capture: PathBuf,
    pub summary: CaptureSummary,
    pub masks: DemoMasks,
    pub merge: MergeReport,
    pub nerfstudio: PathBuf,
    pub twin: DemoTwin,
    /// Seconds the simulation took.
    pub seconds: f64,
    /// The twin in the browser viewer (one HTML file).
    pub view_page: PathBuf,
    /// This report as a page: the figures, pictures and the twin in 3D.
    pub report_page: PathBuf,
}

/// Runs the demo on `object` (a `builtin:NAME`) into `out`.
pub fn demo(object: &str, out: &Path, progress: &dyn Progress) -> Result<DemoReport> {
    let capture_dir = out.join("capture");
    // A little slip at handover, as on the real robot, gives the merge step work to do.
    let config = SimConfig {
        object: object.into(),
        slip_deg: 3.0,
        slip_mm: 2.0,
        ..SimConfig::default()
    };
    progress.note(&format!(
        "1/6 simulating a bimanual scan of {} into {}",
        config.object,
        capture_dir.display()
    ));
    let simulated = crate::simulate::simulate_config(config, &capture_dir, progress)?;
    progress.note(&format!(
        "    {} frames + {} empty-gripper frames in {:.1} s",
        simulated.frames, simulated.empty_frames, simulated.seconds
    ));
    progress.note("2/6 validating the capture");
    let summary = Capture::load(&capture_dir)?.summary();
    progress.note(&format!(
        "    {}x{}, {} left, {} right, {} empty frames, ground truth: {}",
        summary.width,
        summary.height,
        summary.left_frames,
        summary.right_frames,
        summary.empty_frames,
        summary.ground_truth
    ));
    progress.note(
        "3/6 masking every frame: kinematic gripper masks, object masks by the paper's scores",
    );
    let masks = mask(&capture_dir, progress)?;
    let capture = Capture::load(&capture_dir)?;
    progress.note(
        "4/6 merging the scans: right depth cloud onto the left from T_lh⁻¹·T_rh, refined by ICP and colored ICP",
    );
    let merge = merge_scans(&capture)?;
    if let (Some(before), Some(after)) = (merge.handover_error, merge.refined_error) {
        progress.note(&format!(
            "    handover estimate off by {:.2}° / {:.2} mm; after {} {:.3}° / {:.2} mm (fitness {:.3})",
            before.deg, before.mm, merge.method, after.deg, after.mm, merge.fitness
        ));
    }
    progress.note("5/6 exporting both arms, merged with the refined transform, for nerfstudio");
    let right_to_left = omniscan_core::geometry::pose_from_rows(&merge.right_to_left)?;
    let export = export_nerfstudio(
        &capture,
        &out.join("nerfstudio"),
        ExportOptions {
            views: ViewSet::Merged { right_to_left },
            masks: true,
        },
    )?;
    progress.note(&format!(
        "6/6 training the merged splat model on both arms ({DEMO_STEPS} steps at 160x120 on the CPU; use `omniscan twin` for full quality)"
    ));
    // The demo's own masks: ground truth is only what they are scored against.
    let twin = train_merged(
        &capture,
        right_to_left,
        &out.join("twin.ply"),
        (DEMO_STEPS, DEMO_DOWNSCALE, false),
        progress,
    )?;
    let mut report = DemoReport {
        capture: capture_dir,
        summary,
        masks,
        merge,
        nerfstudio: export.transforms,
        twin,
        seconds: simulated.seconds,
        view_page: out.join("view.html"),
        report_page: out.join("report.html"),
    };
    progress.note("    writing view.html (the twin in 3D) and report.html");
    let model = omniscan_splat::ply::read_splats(&report.twin.model)?;
    omniscan_view::write_view(
        &report.view_page,
        "omniscan demo: the first twin",
        &[omniscan_view::ViewerModel {
            name: "twin".into(),
            splats: &model,
            markers: Vec::new(),
        }],
    )?;
    report.report_page = crate::reports::write_demo_report(out, &report)?;
    Ok(report)
}

fn mask(capture_dir: &Path, progress: &dyn Progress) -> Result<DemoMasks> {
    let report = crate::mask::mask(
        capture_dir,
        &crate::mask::MaskingSettings::default(),
        true,
        progress,
    )?;
    let evaluation = report.evaluation.expect("asked for");
    let masks = DemoMasks {
        object_miou: evaluation.object_miou,
        gripper_miou: evaluation.gripper_miou,
        object_min_iou: evaluation.object_min_iou,
        gripper_min_iou: evaluation.gripper_min_iou,
        seconds: report.masking.seconds,
    };
    let f = |v: Option<f64>| v.unwrap_or(f64::NAN);
    progress.note(&format!(
        "    {:.1} s; against ground truth: object mIoU {:.4} / {:.4}, gripper mIoU {:.4} / {:.4} (left / right)",
        masks.seconds,
        f(masks.object_miou.left),
        f(masks.object_miou.right),
        f(masks.gripper_miou.left),
        f(masks.gripper_miou.right)
    ));
    Ok(masks)
}

/// The demo's training: the merged model on both arms' views (right frames
/// brought into the left frame by `right_to_left`) for `steps` at
/// `downscale` (frames without masks on the simulator's ground truth only
/// with `ground_truth_masks`), every 8th view held out, on the CPU reference
/// so that its figures are the same on every machine.
pub fn train_merged(
    capture: &Capture,
    right_to_left: omniscan_core::Pose,
    out: &Path,
    (steps, downscale, ground_truth_masks): (usize, u32, bool),
    progress: &dyn Progress,
) -> Result<DemoTwin> {
    let all = views_from_capture(
        capture,
        ViewSet::Merged { right_to_left },
        downscale,
        ground_truth_masks,
    )?;
    let (train_views, test_views) = split_held_out(all, 8);
    // A robot's capture: the camera and lights stay, the object turns.
    let init = omniscan_splat::Splats {
        appearance: Appearance::FixedRig,
        ..initial_splats(&train_views, 4000, 3, 0)?
    };
    let config = TrainConfig {
        sh_interval: steps / 4,
        ..TrainConfig::with_steps(steps)
    };
    progress.start("training", steps as u64, "steps");
    let model = train(
        &train_views,
        init,
        &config,
        &Renderer::Cpu,
        &mut |step, _, _| progress.set(step as u64),
    )?;
    progress.finish();
    write_splats(out, &model)?;
    let test = omniscan_splat::evaluation::evaluate(&model, &test_views, None)?;
    progress.note(&format!(
        "    {} splats; held-out views: PSNR {:.2} dB, masked PSNR {:.2} dB",
        model.len(),
        test.psnr.unwrap_or(f64::NAN),
        test.psnr_masked.unwrap_or(f64::NAN)
    ));
    Ok(DemoTwin {
        model: out.to_path_buf(),
        splats: model.len(),
        steps,
        test,
    })
}
