//! Scoring a model against a capture's (or a photo set's) views: PSNR and
//! SSIM, whole and masked (object ∩ accumulation, gripper excluded), and
//! LPIPS from a user-supplied network, as the paper's "Results" report them.

use std::path::{Path, PathBuf};

use anyhow::Result;
use serde::{Deserialize, Serialize};

use omniscan_splat::backend::{Backend, Renderer};
use omniscan_splat::evaluation::Evaluation;
use omniscan_splat::views::{View, split_held_out_from};

use crate::Progress;
use crate::settings::default_from_flags;
use crate::views::{ArmSet, Merge, view_source};

/// Everything `eval` can be told besides the model and the views.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct EvalSettings {
    /// Where to render: cpu (the reference, whose figures `train`'s report repeats to the digit), gpu (any Vulkan/Metal/DX12 device, software ones included) or auto (a real GPU when there is one); a GPU's figures agree with the CPU's to about 1e-4 relative.
    #[arg(long, default_value = "cpu")]
    pub backend: Backend,
    #[arg(long, value_enum, default_value = "left")]
    pub arm: ArmSet,
    #[command(flatten)]
    #[serde(flatten)]
    pub merge: Merge,
    /// Shrink images by this integer factor before comparing.
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// Compare only the views that training with this --hold-out-every held out (the n-th, the 2n-th, ...); 0: every view.
    #[arg(long, default_value_t = 0)]
    pub held_out_every: usize,
    /// The first held-out view's index, as training's --hold-out-first (default: n-1).
    #[arg(long)]
    pub held_out_first: Option<usize>,
    /// An LPIPS network exported to ONNX (two `[1,3,H,W]` inputs in `[-1,1]`, one distance out) for the `lpips` metrics; needs ONNX Runtime (--onnx-runtime or ORT_DYLIB_PATH).
    #[arg(long)]
    pub lpips: Option<PathBuf>,
    /// ONNX Runtime's shared library for --lpips (default: $ORT_DYLIB_PATH, else python3's onnxruntime package).
    #[arg(long)]
    pub onnx_runtime: Option<PathBuf>,
    /// Also write, per view, the photo (object pixels) beside the render as PNG into this directory.
    #[arg(long)]
    pub renders: Option<PathBuf>,
    /// Fit each scored view's pose to the model before scoring it (test-time pose fitting, as `train --refine-poses` scores its held-out views), for views whose recorded poses carry calibration error; the report lists the corrections. Runs on the CPU.
    #[arg(long)]
    pub fit_poses: bool,
    /// Adam steps per view with --fit-poses.
    #[arg(long, default_value_t = omniscan_splat::pose::FIT_STEPS)]
    pub pose_fit_steps: usize,
}

default_from_flags!(EvalSettings);

/// [`Evaluation`] of a model file, with the training step where the model
/// was a checkpoint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    #[serde(flatten)]
    pub evaluation: Evaluation,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub checkpoint_step: Option<usize>,
    /// With --fit-poses: each scored view's fitted correction.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub poses: Option<Vec<crate::pose_refinement::ViewPose>>,
}

/// Scores `model` (a 3DGS PLY, or a training checkpoint
/// `MODEL.ply.checkpoint.safetensors` to score a run in progress) against
/// `capture`'s views. Per-view figures carry the view's index in the set.
pub fn evaluate(
    model: &Path,
    capture: &Path,
    settings: &EvalSettings,
    progress: &dyn Progress,
) -> Result<EvalReport> {
    let is_checkpoint = model.extension().is_some_and(|e| e == "safetensors");
    let (model, checkpoint_step) = if is_checkpoint {
        let state = omniscan_splat::checkpoint::load(model)?;
        (state.splats, Some(state.step))
    } else {
        (omniscan_splat::ply::read_splats(model)?, None)
    };
    let right_to_left = settings.merge.read(settings.arm)?;
    // Scoring is evaluation, where the simulator's ground truth belongs.
    let (source, _) = view_source(
        capture,
        settings.arm,
        right_to_left,
        settings.downscale,
        true,
    )?;
    // Each compared view keeps its index in the capture, for the per-view
    // figures; only those views are read, each dropped once compared.
    let (training, held_out) = split_held_out_from(
        (0..source.len()).collect(),
        settings.held_out_every,
        settings.held_out_first,
    );
    let indices = match settings.held_out_every {
        0 => training,
        _ => held_out,
    };
    if indices.is_empty() {
        anyhow::bail!(
            "no views to score: {} has {} views, and --held-out-every {} holds out none of them",
            capture.display(),
            source.len(),
            settings.held_out_every
        );
    }
    let lpips =
        crate::train::load_lpips(settings.lpips.as_deref(), settings.onnx_runtime.as_deref())?;
    let renderer = Renderer::new(settings.backend)?;
    if renderer.is_gpu() {
        progress.note(&format!("rendering on {}", renderer.describe()));
    }
    let at_once = eval_memory_check(&source, &indices, settings.downscale, &renderer)?;
    let fitting = settings
        .fit_poses
        .then(|| PoseFitting::new(&source, &indices, settings.pose_fit_steps))
        .transpose()?;
    progress.start("evaluating", indices.len() as u64, "views");
    let mut evaluation = crate::memory::with_threads(at_once, || {
        omniscan_splat::evaluation::evaluate_views(
            &model,
            &renderer,
            indices.len(),
            |i| {
                let view = source.load(indices[i])?;
                match &fitting {
                    Some(fitting) => fitting.fitted(&model, i, view),
                    None => Ok(view),
                }
                .map(std::borrow::Cow::Owned)
            },
            lpips.as_ref(),
            |i, v, rgb| {
                progress.advance();
                match &settings.renders {
                    Some(dir) => Ok(write_pair(dir, i, v, rgb)?),
                    None => Ok(()),
                }
            },
        )
    })??;
    progress.finish();
    for (figures, &index) in evaluation.per_view.iter_mut().zip(&indices) {
        figures.view = index;
    }
    Ok(EvalReport {
        evaluation,
        checkpoint_step,
        poses: fitting.map(|f| f.report(&source, &indices)),
    })
}

/// Test-time pose fitting of the scored views: each view's correction,
/// found as it is read (views are read on several threads).
struct PoseFitting {
    config: omniscan_splat::train::TrainConfig,
    centre: [f64; 3],
    steps: usize,
    fitted: std::sync::Mutex<Vec<omniscan_splat::pose::Correction>>,
}

impl PoseFitting {
    fn new(
        source: &omniscan_splat::views::ViewSource,
        indices: &[usize],
        steps: usize,
    ) -> Result<PoseFitting> {
        let cameras = (indices.iter())
            .map(|&i| source.camera(i).map(|(_, c)| c))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(PoseFitting {
            // Training's loss weights, and the refinement's rates.
            config: omniscan_splat::train::TrainConfig {
                pose: Some(Default::default()),
                ..omniscan_splat::train::TrainConfig::with_steps(steps)
            },
            centre: omniscan_splat::pose::rotation_centre(&cameras),
            steps,
            fitted: std::sync::Mutex::new(vec![Default::default(); indices.len()]),
        })
    }

    /// `view` (the `i`-th scored) at its fitted pose.
    fn fitted(
        &self,
        model: &omniscan_splat::Splats,
        i: usize,
        mut view: View,
    ) -> Result<View, omniscan_splat::SplatError> {
        use omniscan_splat::pose::{Correction, corrected, fit_view};
        let none = Correction::default();
        let c = fit_view(model, &view, &none, self.centre, &self.config, self.steps)?;
        view.camera = corrected(&view.camera, &none, &c);
        self.fitted.lock().expect("no thread panicked holding it")[i] = c;
        Ok(view)
    }

    fn report(
        self,
        source: &omniscan_splat::views::ViewSource,
        indices: &[usize],
    ) -> Vec<crate::pose_refinement::ViewPose> {
        let fitted = self
            .fitted
            .into_inner()
            .expect("no thread panicked holding it");
        crate::pose_refinement::view_poses(source, indices, &fitted)
    }
}

/// How many views may be scored at once in the memory available, or an
/// error naming the --downscale at which the largest fits.
fn eval_memory_check(
    source: &omniscan_splat::views::ViewSource,
    indices: &[usize],
    downscale: u32,
    renderer: &Renderer,
) -> Result<usize> {
    use crate::memory::{EVAL_BYTES_PER_PIXEL, READ_BYTES_PER_PIXEL};
    let mut largest = (0, 0);
    for &i in indices {
        let (_, c) = source.camera(i)?;
        if u64::from(c.width) * u64::from(c.height) > largest.0 * largest.1 {
            largest = (u64::from(c.width), u64::from(c.height));
        }
    }
    let d = u64::from(downscale.max(1));
    let full = largest.0 * largest.1 * d * d;
    let need = |d: u64| full * READ_BYTES_PER_PIXEL + full / (d * d) * EVAL_BYTES_PER_PIXEL;
    let wanted = if renderer.is_gpu() {
        1
    } else {
        rayon::current_num_threads()
    };
    crate::memory::views_at_once(
        &format!(
            "scoring a {}x{} view (read at {}x{})",
            largest.0,
            largest.1,
            largest.0 * d,
            largest.1 * d
        ),
        need(d),
        wanted,
        crate::memory::available(),
        |available| match (d..=16 * d).find(|&d| need(d) <= available) {
            Some(fits) => format!("--downscale {fits} fits"),
            None => "its images are too large to read on this machine at any --downscale".into(),
        },
    )
}

/// The photo's object pixels beside the render, as `view_NNN.png`.
fn write_pair(dir: &Path, i: usize, v: &View, rgb: &[[f32; 3]]) -> omniscan_core::Result<()> {
    let byte = |x: f32| (x.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    let (w, h) = (v.camera.width as usize, v.camera.height as usize);
    let mut data = Vec::with_capacity(2 * w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            data.extend(v.image[p].map(|c| byte(c * v.object[p])));
        }
        for x in 0..w {
            data.extend(rgb[y * w + x].map(byte));
        }
    }
    omniscan_core::image_io::write_rgb(
        &dir.join(format!("view_{i:03}.png")),
        &omniscan_core::image_io::RgbImage {
            width: 2 * w as u32,
            height: h as u32,
            data,
        },
    )
}
