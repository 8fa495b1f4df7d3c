//! Training a splat model on a capture's (or a photo set's) views with the
//! paper's masked losses ("3DGS Training"): views read and split, the
//! trainer set up from [`TrainSettings`], checkpoints written as it goes,
//! the model written and scored.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use omniscan_core::poses::ViewSet;
use omniscan_splat::Splats;
use omniscan_splat::backend::{Backend, Renderer};
use omniscan_splat::evaluation::Evaluation;
use omniscan_splat::packed::PackedView;
use omniscan_splat::ply::write_splats;
use omniscan_splat::raster::Appearance;
use omniscan_splat::train::{
    Densification, Start, TrainConfig, initial_splats, splats_from_points,
};
use omniscan_splat::trainer::{Checkpoints, Trainer, run_to_end};
use omniscan_splat::views::{ViewSource, split_held_out_from};

use crate::Progress;
use crate::pose_refinement::{PoseReport, PoseSettings, Split, at_corrected_poses, view_groups};
use crate::settings::default_from_flags;
use crate::views::{ArmSet, Merge, view_source};

/// What the splats' spherical harmonics are a function of.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum AppearanceChoice {
    /// fixed-rig for a robot's capture, view-direction for a photo set.
    #[default]
    Auto,
    /// The viewing direction in the model's frame (3DGS; lights fixed to the object).
    ViewDirection,
    /// The splat's normal in the camera's frame (camera and lights fixed, the object turned in the gripper).
    FixedRig,
}

/// How splats are added and removed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum DensificationChoice {
    #[default]
    Adaptive,
    Mcmc,
}

/// Everything `train` can be told besides its capture and output.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrainSettings {
    #[arg(long, value_enum, default_value = "left")]
    pub arm: ArmSet,
    #[command(flatten)]
    #[serde(flatten)]
    pub merge: Merge,
    /// Training steps.
    #[arg(long, default_value_t = 3000)]
    pub steps: usize,
    /// Shrink images by this integer factor (2: 640x480 → 320x240).
    #[arg(long, default_value_t = 2)]
    pub downscale: u32,
    /// Every n-th view (the n-th, the 2n-th, ...) is held out from training and used for evaluation; 0 holds out none.
    #[arg(long, default_value_t = 8)]
    pub hold_out_every: usize,
    /// The first held-out view's index (default: n-1, so views n-1, 2n-1, ...); 0 gives the 3DGS and gsplat split (views 0, n, 2n, ...).
    #[arg(long)]
    pub hold_out_first: Option<usize>,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long, default_value_t = 3)]
    pub sh_degree: usize,
    /// How splats are added and removed: gsplat's default strategy (clone, split, prune, opacity resets) or MCMC (relocation, 5% growth per refinement up to --max-splats, opacity and scale penalties, noise on near-transparent splats).
    #[arg(long, value_enum, default_value = "adaptive")]
    pub densification: DensificationChoice,
    /// Train an antialiased model (Mip-Splatting's 2D filter with opacity compensation, gsplat's `antialiased` mode): renders stay free of aliasing when viewed smaller than trained.
    #[arg(long)]
    pub antialiased: bool,
    /// What view-dependent colour depends on. In the paper's scan the camera and the lights stay put while the gripper turns the object, so a surface's shading follows its normal in the camera's frame (fixed-rig); 3DGS's viewing direction cannot tell apart the two arms' views of one side under differently turned light, and a merged model blurs between them. fixed-rig models are marked in the PLY header; other viewers read them as ordinary models, right in their base colour.
    #[arg(long, value_enum, default_value = "auto")]
    pub appearance: AppearanceChoice,
    /// Densify by the per-pixel screen-space gradients summed in absolute value (AbsGS, gsplat's `absgrad`), so large splats over fine texture split; the default threshold becomes 0.0008. Adaptive densification only.
    #[arg(long)]
    pub absgrad: bool,
    /// The screen-space gradient (gsplat's: of the loss with respect to the splat's 2D mean in half-image units, averaged over the views that saw it) above which adaptive densification clones or splits a splat; default 0.0002, or 0.0008 with --absgrad. Lower gives more splats.
    #[arg(long)]
    pub grad_threshold: Option<f32>,
    /// Position learning rate per unit of scene extent (the splats' spread at the start), decayed to 1% over the run.
    #[arg(long, default_value_t = 1.6e-4)]
    pub position_lr: f32,
    /// Adam's learning rate for the SH bands above the DC term (view-dependent colour); the DC term's is 2.5e-3.
    #[arg(long, default_value_t = omniscan_splat::train::SH_REST_LR)]
    pub sh_rest_lr: f32,
    /// Densification stops adding splats at this many.
    #[arg(long, default_value_t = 200_000)]
    pub max_splats: usize,
    /// Initial splats from the visual hull of the masks (without --init).
    #[arg(long, default_value_t = 5000)]
    pub initial_points: usize,
    /// Start from this point cloud instead (PLY, PCD or XYZ, with colours if it has them; a 3DGS PLY gives its centres), in the views' frame: the holding gripper's for a capture, metres. A nerfstudio set's ply_file_path is its default.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// With --arm both: also start from this point cloud (or splat model) in the right gripper's
    /// frame, carried into the left's by the merge transform and joined to --init's points. The
    /// paper's merged model starts from both arms' models: --init left.ply --init-right right.ply.
    #[arg(long)]
    pub init_right: Option<PathBuf>,
    /// Write the whole training state every N steps to OUT.checkpoint.safetensors (0: never); it is removed when training ends.
    #[arg(long, default_value_t = 500)]
    pub checkpoint_every: usize,
    /// Continue an interrupted run from OUT.checkpoint.safetensors (same capture and settings); ends with the model an uninterrupted run would have given.
    #[arg(long)]
    pub resume: bool,
    /// An LPIPS network exported to ONNX (two `[1,3,H,W]` inputs in `[-1,1]`, one distance out) for the `lpips` metrics; needs ONNX Runtime (--onnx-runtime or ORT_DYLIB_PATH).
    #[arg(long)]
    pub lpips: Option<PathBuf>,
    /// ONNX Runtime's shared library for --lpips (default: $ORT_DYLIB_PATH, else python3's onnxruntime package).
    #[arg(long)]
    pub onnx_runtime: Option<PathBuf>,
    /// Where rendering and its gradients run: auto (a real GPU when there is one, else the CPU), cpu, or gpu (any device, software ones included).
    #[arg(long, default_value = "auto")]
    pub backend: Backend,
    /// Train a simulated capture that has no masks of its own on the simulator's ground-truth masks (for experiments on training alone; the report says so). Without it a capture needs `omniscan mask` first: ground truth is for evaluation.
    #[arg(long)]
    pub use_ground_truth_masks: bool,
    /// Read the views even where they need more memory than the system has available (with swap, say); without it such a set is refused before reading, naming the --downscale that fits.
    #[arg(long)]
    pub no_memory_check: bool,
    /// On a GPU: how much of the views' loss targets (20 bytes a pixel) stays on the device, gigabytes; a kept view is sent once, the others at each of their steps.
    #[arg(long, default_value_t = omniscan_splat::gpu::training::DEFAULT_VIEW_MEMORY as f64 / 1e9)]
    pub gpu_view_memory_gb: f64,
    #[command(flatten)]
    #[serde(flatten)]
    pub poses: PoseSettings,
}

default_from_flags!(TrainSettings);

/// The merge a merged model's views were brought together by.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MergedBy {
    /// Right gripper's frame in the left's, 4x4 row-major, metres.
    pub transform: [[f64; 4]; 4],
    /// The file it came from, or the handover estimate.
    pub from: String,
}

/// What a model's first splats came from: `"visual hull"` in JSON, or the
/// list of point files.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum StartedFrom {
    /// The masks' visual hull (its JSON is the words "visual hull").
    VisualHull(String),
    Points(Vec<PathBuf>),
}

impl StartedFrom {
    pub fn visual_hull() -> StartedFrom {
        StartedFrom::VisualHull("visual hull".into())
    }
}

/// The settings a model was trained with, as the trainer used them
/// (defaults resolved).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainedWith {
    pub densification: String,
    pub absolute_gradients: bool,
    pub grad_threshold: f32,
    pub antialiased: bool,
    pub appearance: String,
    pub sh_degree: usize,
    pub position_lr: f32,
    pub sh_rest_lr: f32,
    pub max_splats: usize,
    pub seed: u64,
    pub init: StartedFrom,
    pub right_to_left: Option<MergedBy>,
    /// Whether frames without masks of their own used the simulator's
    /// ground truth (`--use-ground-truth-masks`).
    #[serde(default)]
    pub ground_truth_masks: bool,
}

/// What [`train`] made and how well it fits.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainReport {
    /// The model written (3DGS PLY).
    pub model: PathBuf,
    pub splats: usize,
    pub steps: usize,
    pub seconds: f64,
    pub train_views: usize,
    pub test_views: usize,
    pub settings: TrainedWith,
    /// On the held-out views.
    pub test: Evaluation,
    /// On the views it trained on: tells underfitting from poor
    /// generalisation (LPIPS left to the held-out views: it is the slow one).
    pub train: Evaluation,
    /// With --refine-poses: the corrections learned, and the held-out views'
    /// fitted ones (both evaluations above are at the corrected poses).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub poses: Option<PoseReport>,
}

/// The checkpoint beside an output model: `OUT.checkpoint.safetensors`.
pub fn checkpoint_path(out: &Path) -> PathBuf {
    let mut name = out.as_os_str().to_owned();
    name.push(".checkpoint.safetensors");
    PathBuf::from(name)
}

/// Trains a model on `capture`'s views (a capture directory, or a
/// calibrated photo set: a nerfstudio `transforms.json` or a `cameras.json`),
/// writes it to `out` and scores it.
pub fn train(
    capture: &Path,
    out: &Path,
    settings: &TrainSettings,
    progress: &dyn Progress,
) -> Result<TrainReport> {
    validate(settings)?;
    omniscan_splat::ply::ModelFormat::writable(out)?;
    let _lock = omniscan_core::lock::OutputLock::file(out, "train")?;
    let loaded = load_views(capture, settings, progress)?;
    let (train_views, test_views) = split_held_out_from(
        loaded.views,
        settings.hold_out_every,
        settings.hold_out_first,
    );
    let (train_indices, test_indices) = split_held_out_from(
        (0..loaded.source.len()).collect(),
        settings.hold_out_every,
        settings.hold_out_first,
    );
    let (groups, group_names) = view_groups(&loaded.source);
    let train_groups: Vec<usize> = train_indices.iter().map(|&i| groups[i]).collect();
    let start = Instant::now();
    let config = trainer_config(settings)?;
    let renderer = training_renderer(settings, progress)?;
    let init = initial_points(settings, &loaded.source, progress);
    let checkpoint = checkpoint_path(out);
    let start_from = if settings.resume {
        resume_from(
            &checkpoint,
            loaded.appearance,
            settings.antialiased,
            progress,
        )?
    } else {
        let mut splats = initial(settings, &init, loaded.merged_by, &train_views)?;
        splats.antialiased = settings.antialiased;
        splats.appearance = loaded.appearance;
        Start::Fresh(splats)
    };
    let mut trainer = Trainer::new(&train_views, start_from, &config, &renderer)?
        .with_pose_groups(&train_groups)?;
    run_with_progress(&mut trainer, settings, &checkpoint, progress)?;
    let learned = trainer.pose_corrections();
    let model = trainer.finish()?;
    progress.finish();
    write_splats(out, &model)?;
    if checkpoint.is_file() {
        std::fs::remove_file(&checkpoint)
            .with_context(|| format!("removing {}", checkpoint.display()))?;
    }
    let lpips = load_lpips(settings.lpips.as_deref(), settings.onnx_runtime.as_deref())?;
    // With pose refinement every view is scored at its corrected pose, a
    // held-out view's fitted against the model first.
    let (train_views, test_views, poses) = match learned {
        None => (train_views, test_views, None),
        Some(learned) => {
            let split = Split {
                train: &train_indices,
                held_out: &test_indices,
                groups: &groups,
                group_names: &group_names,
            };
            let fitting = (&config, settings.poses.pose_fit_steps);
            let (train_views, test_views, report) = at_corrected_poses(
                (&model, &loaded.source),
                &split,
                (train_views, test_views),
                &learned,
                fitting,
                progress,
            )?;
            (train_views, test_views, Some(report))
        }
    };
    let test = omniscan_splat::evaluation::evaluate(&model, &test_views, lpips.as_ref())?;
    // The same figures on the views it trained on tell underfitting from
    // poor generalisation: on DTU scan37 after 3000 steps the held-out views'
    // 24 dB looked like overfitting until the training views' own 27 dB
    // showed the model had not yet fitted them either.
    let fit = omniscan_splat::evaluation::evaluate(&model, &train_views, None)?;
    Ok(TrainReport {
        model: out.to_path_buf(),
        splats: model.len(),
        steps: settings.steps,
        seconds: start.elapsed().as_secs_f64(),
        train_views: train_views.len(),
        test_views: test_views.len(),
        settings: trained_with(settings, &config, &model, &init, loaded.merged_by),
        test,
        train: fit,
        poses,
    })
}

/// A capture's views as training reads them.
struct LoadedViews {
    source: ViewSource,
    views: Vec<PackedView>,
    /// The merge the views were brought together by (both arms).
    merged_by: Option<omniscan_core::Pose>,
    appearance: Appearance,
}

/// Reads the views `settings` pick from `capture`, after checking that
/// they fit in memory and that `--init-right` has both arms to start.
fn load_views(
    capture: &Path,
    settings: &TrainSettings,
    progress: &dyn Progress,
) -> Result<LoadedViews> {
    let right_to_left = settings.merge.read(settings.arm)?;
    if let Some(path) = &settings.init_right
        && !matches!(settings.arm, ArmSet::Both)
    {
        bail!(
            "--init-right {}: only a model of both arms (--arm both) starts from the right arm's points",
            path.display()
        );
    }
    let (source, view_set) = view_source(
        capture,
        settings.arm,
        right_to_left,
        settings.downscale,
        settings.use_ground_truth_masks,
    )?;
    if !settings.no_memory_check {
        check_view_memory(&source, settings.downscale, crate::memory::available())?;
    }
    let merged_by = match view_set {
        Some(ViewSet::Merged { right_to_left }) => Some(right_to_left),
        _ => None,
    };
    if settings.init_right.is_some() && merged_by.is_none() {
        bail!("--init-right needs a capture's views of both arms");
    }
    progress.start("reading", source.len() as u64, "views");
    let views = source.load_packed_each(&(0..source.len()).collect::<Vec<_>>(), &|| {
        progress.advance()
    })?;
    progress.finish();
    let appearance = match settings.appearance {
        AppearanceChoice::Auto if view_set.is_some() => Appearance::FixedRig,
        AppearanceChoice::Auto | AppearanceChoice::ViewDirection => Appearance::ViewDirection,
        AppearanceChoice::FixedRig => Appearance::FixedRig,
    };
    Ok(LoadedViews {
        source,
        views,
        merged_by,
        appearance,
    })
}

/// The points a fresh model starts from: `--init`, else a nerfstudio set's
/// own (`ply_file_path`, as nerfstudio does), else none.
fn initial_points(
    settings: &TrainSettings,
    source: &ViewSource,
    progress: &dyn Progress,
) -> Option<PathBuf> {
    if settings.init.is_some() {
        return settings.init.clone();
    }
    let points = source.initial_points().map(PathBuf::from)?;
    progress.note(&format!(
        "starting from the photo set's points {} (its ply_file_path)",
        points.display()
    ));
    Some(points)
}

/// Runs `trainer` to its last step, checkpointing into `checkpoint` and
/// showing the loss and the PSNR averaged over the last 20 steps.
fn run_with_progress(
    trainer: &mut Trainer<'_, PackedView>,
    settings: &TrainSettings,
    checkpoint: &Path,
    progress: &dyn Progress,
) -> Result<()> {
    let mut save = |state: &omniscan_splat::train::TrainState| {
        omniscan_splat::checkpoint::save(state, checkpoint)
    };
    progress.start("training", settings.steps as u64, "steps");
    let mut recent = std::collections::VecDeque::new();
    run_to_end(
        trainer,
        Some(Checkpoints {
            every: settings.checkpoint_every,
            save: &mut save,
        }),
        &mut |step, loss, psnr| {
            recent.push_back(psnr);
            if recent.len() > 20 {
                recent.pop_front();
            }
            if step % 10 == 0 {
                progress.message(&format!(
                    "loss {loss:.4}, PSNR {:.2} dB",
                    recent.iter().sum::<f64>() / recent.len() as f64
                ));
            }
            progress.set(step as u64);
        },
    )?;
    Ok(())
}

/// Refuses settings that no training can run with, naming the flag.
fn validate(settings: &TrainSettings) -> Result<()> {
    if settings.sh_degree > 3 {
        bail!("--sh-degree must be 0-3");
    }
    if settings.densification == DensificationChoice::Mcmc
        && (settings.absgrad || settings.grad_threshold.is_some())
    {
        bail!(
            "--absgrad and --grad-threshold steer adaptive densification; MCMC does not use them"
        );
    }
    if let Some(threshold) = settings.grad_threshold
        && !(threshold.is_finite() && threshold > 0.0)
    {
        bail!("--grad-threshold must be a positive number, got {threshold}");
    }
    for (flag, value) in [
        ("--position-lr", settings.position_lr),
        ("--sh-rest-lr", settings.sh_rest_lr),
    ] {
        if !(value.is_finite() && value >= 0.0) {
            bail!("{flag} must be a finite number, 0 or more, got {value}");
        }
    }
    if settings.max_splats == 0 {
        bail!("--max-splats must be at least 1");
    }
    if !(settings.gpu_view_memory_gb.is_finite() && settings.gpu_view_memory_gb >= 0.0) {
        bail!(
            "--gpu-view-memory-gb must be a finite number, 0 or more, got {}",
            settings.gpu_view_memory_gb
        );
    }
    if settings.init.is_none()
        && settings.init_right.is_none()
        && !(1..=settings.max_splats).contains(&settings.initial_points)
    {
        bail!(
            "--initial-points must be 1 to --max-splats ({}), got {}",
            settings.max_splats,
            settings.initial_points
        );
    }
    Ok(())
}

/// The trainer's configuration: the densification strategy's own defaults,
/// with the settings' choices over them.
fn trainer_config(settings: &TrainSettings) -> Result<TrainConfig> {
    let strategy = match settings.densification {
        DensificationChoice::Adaptive => TrainConfig::with_steps(settings.steps),
        DensificationChoice::Mcmc => TrainConfig::mcmc(settings.steps),
    };
    let strategy = if settings.absgrad {
        strategy.with_absolute_gradients()
    } else {
        strategy
    };
    Ok(TrainConfig {
        seed: settings.seed,
        max_sh_degree: settings.sh_degree,
        max_splats: settings.max_splats,
        position_lr: settings.position_lr,
        sh_rest_lr: settings.sh_rest_lr,
        grad_threshold: settings.grad_threshold.unwrap_or(strategy.grad_threshold),
        pose: settings.poses.config()?,
        ..strategy
    })
}

/// The renderer the settings ask for; `auto` falls back to the CPU on a
/// GPU that can render but not train.
fn training_renderer(settings: &TrainSettings, progress: &dyn Progress) -> Result<Renderer> {
    let mut renderer = match Renderer::new(settings.backend)? {
        Renderer::Gpu(gpu) if settings.backend == Backend::Auto && !gpu.can_train() => {
            progress.note(&format!(
                "{} cannot run the backward pass (no subgroup operations); training on the CPU",
                gpu.adapter()
            ));
            Renderer::Cpu
        }
        r => r,
    };
    if let Renderer::Gpu(gpu) = &mut renderer {
        gpu.set_view_memory((settings.gpu_view_memory_gb * 1e9) as u64);
    }
    progress.note(&format!("training on {}", renderer.describe()));
    Ok(renderer)
}

/// The first splats: the visual hull of the masks, or the points of
/// `init` (and --init-right's, carried into the left frame by `merged_by`).
fn initial(
    settings: &TrainSettings,
    init: &Option<PathBuf>,
    merged_by: Option<omniscan_core::Pose>,
    train_views: &[PackedView],
) -> Result<Splats> {
    if init.is_none() && settings.init_right.is_none() {
        return initial_splats(
            train_views,
            settings.initial_points,
            settings.sh_degree,
            settings.seed,
        )
        .context("initialisation");
    }
    let (mut points, mut colours) = (Vec::new(), Vec::new());
    for (path, to_views) in [(init, None), (&settings.init_right, merged_by)] {
        let Some(path) = path else { continue };
        let cloud = omniscan_register::cloud::read_cloud(path)?;
        let cloud = match to_views {
            Some(pose) => cloud.transformed(&pose),
            None => cloud,
        };
        points.extend(
            cloud
                .points
                .iter()
                .map(|p| [p.x as f32, p.y as f32, p.z as f32]),
        );
        if cloud.colors.len() == cloud.points.len() {
            colours.extend_from_slice(&cloud.colors);
        } else {
            colours.extend(std::iter::repeat_n([0.5; 3], cloud.points.len()));
        }
    }
    let named = [init, &settings.init_right]
        .into_iter()
        .flatten()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(" and ");
    if points.len() > settings.max_splats {
        bail!(
            "--init {named}: {} points, more than --max-splats {}: thin them (e.g. voxel-downsample) or raise --max-splats",
            points.len(),
            settings.max_splats
        );
    }
    splats_from_points(&points, &colours, settings.sh_degree)
        .with_context(|| format!("initialising from {named}"))
}

/// The state to go on from: the checkpoint, if it is there and its model
/// can go on as asked.
fn resume_from(
    checkpoint: &Path,
    appearance: Appearance,
    antialiased: bool,
    progress: &dyn Progress,
) -> Result<Start> {
    if !checkpoint.is_file() {
        bail!(
            "--resume: no checkpoint at {} (it is written every --checkpoint-every steps)",
            checkpoint.display()
        );
    }
    let state = omniscan_splat::checkpoint::load(checkpoint)?;
    resumable_as(&state.splats, appearance, antialiased)
        .with_context(|| format!("--resume: {}", checkpoint.display()))?;
    progress.note(&format!(
        "resuming after step {} from {}",
        state.step,
        checkpoint.display()
    ));
    Ok(Start::Resume(Box::new(state)))
}

fn trained_with(
    settings: &TrainSettings,
    config: &TrainConfig,
    model: &Splats,
    init: &Option<PathBuf>,
    merged_by: Option<omniscan_core::Pose>,
) -> TrainedWith {
    TrainedWith {
        densification: match config.densification {
            Densification::Adaptive => "adaptive",
            Densification::Mcmc => "mcmc",
        }
        .into(),
        absolute_gradients: config.absolute_gradients,
        grad_threshold: config.grad_threshold,
        antialiased: model.antialiased,
        appearance: model.appearance.name().into(),
        sh_degree: config.max_sh_degree,
        position_lr: config.position_lr,
        sh_rest_lr: config.sh_rest_lr,
        max_splats: config.max_splats,
        seed: config.seed,
        init: match (init, &settings.init_right) {
            (None, None) => StartedFrom::visual_hull(),
            (left, right) => {
                StartedFrom::Points([left, right].into_iter().flatten().cloned().collect())
            }
        },
        right_to_left: merged_by.map(|pose| MergedBy {
            transform: omniscan_core::geometry::pose_to_rows(&pose),
            from: match &settings.merge.right_to_left {
                Some(path) => path.display().to_string(),
                None => "handover estimate T_lh⁻¹·T_rh".to_string(),
            },
        }),
        ground_truth_masks: settings.use_ground_truth_masks,
    }
}

/// Refuses, before reading, views whose packed form alone needs more than
/// the memory the system has available (Linux's MemAvailable): reading them
/// would end, minutes in, in the kernel killing the run. The error names the
/// smallest --downscale at which they fit.
/// `available` is `None` where the system does not say.
fn check_view_memory(source: &ViewSource, downscale: u32, available: Option<u64>) -> Result<()> {
    let Some(available) = available else {
        return Ok(());
    };
    let downscales: Vec<u32> = (downscale..=downscale.saturating_mul(16)).collect();
    let needs = source.packed_bytes(&downscales)?;
    if needs[0] <= available {
        return Ok(());
    }
    let gb = crate::memory::gb;
    // A downscale that leaves no pixel "fits" too, and is no answer.
    let fits = match downscales
        .iter()
        .zip(&needs)
        .find(|&(_, &need)| need > 0 && need <= available)
    {
        Some((d, need)) => format!("--downscale {d} needs {:.2} GB", gb(*need)),
        None => format!("no --downscale up to {} fits", downscales.last().unwrap()),
    };
    let views = match source.len() {
        1 => "the view needs".to_string(),
        n => format!("the {n} views need"),
    };
    bail!(
        "{views} {:.2} GB of memory at --downscale {downscale} (packed, before the model), and {:.2} GB is available: {fits}; --no-memory-check reads them anyway",
        gb(needs[0]),
        gb(available)
    )
}

/// The LPIPS network at `path`, if one is named.
pub(crate) fn load_lpips(
    path: Option<&Path>,
    runtime: Option<&Path>,
) -> Result<Option<omniscan_splat::lpips::Lpips>> {
    Ok(match path {
        Some(p) => Some(omniscan_splat::lpips::Lpips::load(p, runtime)?),
        None => None,
    })
}

/// Whether a checkpoint's model can go on as asked: its appearance and
/// footprint filter are part of the model, so a resumed run keeps them.
fn resumable_as(kept: &Splats, appearance: Appearance, antialiased: bool) -> Result<()> {
    let describe = |appearance: Appearance, antialiased: bool| {
        format!(
            "--appearance {}{}",
            appearance.name(),
            if antialiased { " --antialiased" } else { "" }
        )
    };
    if kept.appearance != appearance || kept.antialiased != antialiased {
        bail!(
            "the checkpoint was trained with {}, and this run asks for {}",
            describe(kept.appearance, kept.antialiased),
            describe(appearance, antialiased)
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_parse_and_are_the_documented_ones() {
        let s = TrainSettings::default();
        assert_eq!((s.steps, s.downscale, s.hold_out_every), (3000, 2, 8));
        assert_eq!(s.backend, Backend::Auto);
        assert_eq!(s.appearance, AppearanceChoice::Auto);
        // A settings file with one field keeps the others' defaults.
        let partial: TrainSettings = serde_json::from_str(r#"{"steps": 10}"#).unwrap();
        assert_eq!(partial, TrainSettings { steps: 10, ..s });
    }

    #[test]
    fn views_that_do_not_fit_in_memory_are_refused_naming_a_downscale_that_does() {
        use omniscan_core::image_io::{RgbImage, write_rgb};
        let dir = tempfile::tempdir().unwrap();
        // 12 rows: shrunk by 13 or more, nothing is left.
        let image = RgbImage {
            width: 64,
            height: 12,
            data: vec![90; 64 * 12 * 3],
        };
        write_rgb(&dir.path().join("0.png"), &image).unwrap();
        let set = serde_json::json!({
            "fl_x": 50.0, "fl_y": 50.0, "cx": 32.0, "cy": 6.0, "w": 64, "h": 12,
            "frames": [{
                "file_path": "0.png",
                "transform_matrix": [[1., 0., 0., 0.], [0., 1., 0., 0.], [0., 0., 1., 5.], [0., 0., 0., 1.]],
            }],
        });
        let path = dir.path().join("transforms.json");
        std::fs::write(&path, set.to_string()).unwrap();
        let source = ViewSource::from_photo_set(&path, 1).unwrap();
        // Full size without depth: 5 bytes a pixel; by 2 (32x6), 8; by 3 (21x4), 8.
        let full = 64 * 12 * 5;
        assert!(check_view_memory(&source, 1, Some(full)).is_ok());
        assert!(check_view_memory(&source, 1, None).is_ok());
        let refusal = |available| {
            check_view_memory(&source, 1, Some(available))
                .unwrap_err()
                .to_string()
        };
        let err = refusal(full - 1);
        assert!(
            err.contains("the view needs 0.00 GB of memory at --downscale 1"),
            "{err}"
        );
        assert!(err.contains("--downscale 2 needs"), "{err}");
        assert!(refusal(32 * 6 * 8 - 1).contains("--downscale 3 needs"));
        // Only downscales that leave no pixel "fit", and they are no answer.
        assert!(refusal(1).contains("no --downscale up to 16 fits"));
    }

    #[test]
    fn a_checkpoint_resumes_only_under_its_own_appearance_and_filter() {
        let kept = Splats {
            appearance: Appearance::FixedRig,
            ..Default::default()
        };
        assert!(resumable_as(&kept, Appearance::FixedRig, false).is_ok());
        let err = resumable_as(&kept, Appearance::ViewDirection, false).unwrap_err();
        assert!(
            err.to_string().contains("trained with --appearance fixed-rig, and this run asks for --appearance view-direction"),
            "{err}"
        );
        let err = resumable_as(&kept, Appearance::FixedRig, true).unwrap_err();
        assert!(
            err.to_string().ends_with("fixed-rig --antialiased"),
            "{err}"
        );
    }
}
