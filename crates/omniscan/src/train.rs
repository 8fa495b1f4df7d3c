//! `omniscan train`: fit a splat model to a capture with the masked losses.

use omniscan_splat::backend::{Backend, Renderer};
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde_json::json;

use omniscan_core::Pose;
use omniscan_core::capture::{Arm, Capture};
use omniscan_core::poses::ViewSet;
use omniscan_splat::ply::write_splats;
use omniscan_splat::raster::Appearance;
use omniscan_splat::train::{
    Checkpoints, Densification, Start, TrainConfig, initial_splats, splats_from_points, train,
    train_resumable,
};
use omniscan_splat::views::{ViewSource, split_held_out, split_held_out_from, views_from_capture};

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum ArmSet {
    Left,
    Right,
    /// Both arms in the left gripper's frame, merged with the handover estimate T_lh⁻¹·T_rh (or --right-to-left).
    Both,
}

impl ArmSet {
    /// The capture's frames these arms stand for, and the frame they are in:
    /// both arms merged by `right_to_left` (the right gripper's frame in the
    /// left's) where given, else by the robot's handover estimate.
    pub fn view_set(self, capture: &Capture, right_to_left: Option<Pose>) -> ViewSet {
        match (self, right_to_left) {
            (ArmSet::Left, _) => ViewSet::Arm(Arm::Left),
            (ArmSet::Right, _) => ViewSet::Arm(Arm::Right),
            (ArmSet::Both, Some(right_to_left)) => ViewSet::Merged { right_to_left },
            (ArmSet::Both, None) => ViewSet::merged_from_handover(capture),
        }
    }
}

/// The option that replaces the handover estimate in a merged view set.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct RightToLeftArg {
    /// With --arm both: the right gripper's frame in the left's, in place of the handover
    /// estimate T_lh⁻¹·T_rh. A JSON file from `omniscan align` (its `transform`) or a bare 4x4
    /// row-major matrix, metres. The paper's merged model uses the handover estimate refined by
    /// aligning the right arm's model onto the left's (`omniscan align right.ply left.ply
    /// --handover CAPTURE`).
    #[arg(long)]
    pub right_to_left: Option<PathBuf>,
}

impl RightToLeftArg {
    /// The transform the file names; refused unless `arm` is both.
    pub fn read(&self, arm: ArmSet) -> Result<Option<Pose>> {
        match (&self.right_to_left, arm) {
            (None, _) => Ok(None),
            (Some(path), ArmSet::Both) => Ok(Some(crate::registration::read_transform(path)?)),
            (Some(path), _) => bail!(
                "--right-to-left {}: only views of both arms (--arm both) are merged",
                path.display()
            ),
        }
    }
}

/// What the splats' spherical harmonics are a function of.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum AppearanceArg {
    /// fixed-rig for a robot's capture, view-direction for a photo set.
    Auto,
    /// The viewing direction in the model's frame (3DGS; lights fixed to the object).
    ViewDirection,
    /// The splat's normal in the camera's frame (camera and lights fixed, the object turned in the gripper).
    FixedRig,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum DensificationArg {
    Adaptive,
    Mcmc,
}

#[derive(clap::Args)]
pub struct TrainArgs {
    /// The capture directory, or a calibrated photo set: a nerfstudio transforms.json (or its directory; perspective or OPENCV_FISHEYE cameras, their lens distortion undone as the photos are read, the object near the origin or where the cameras look, mask_path as the object mask, else the image's alpha, else the whole image), or a cameras.json (file_path, mask_path, fl_x, fl_y, cx, cy in OpenCV's pixel convention, camera_to_world_opencv per frame). A frame's w, h, when given, must be its image's size, since the intrinsics are in its pixels.
    pub capture: PathBuf,
    #[arg(long, value_enum, default_value = "left")]
    pub arm: ArmSet,
    #[command(flatten)]
    pub merge: RightToLeftArg,
    /// Output model (3DGS PLY).
    #[arg(long)]
    pub out: PathBuf,
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
    pub densification: DensificationArg,
    /// Train an antialiased model (Mip-Splatting's 2D filter with opacity compensation, gsplat's `antialiased` mode): renders stay free of aliasing when viewed smaller than trained.
    #[arg(long)]
    pub antialiased: bool,
    /// What view-dependent colour depends on. In the paper's scan the camera and the lights stay put while the gripper turns the object, so a surface's shading follows its normal in the camera's frame (fixed-rig); 3DGS's viewing direction cannot tell apart the two arms' views of one side under differently turned light, and a merged model blurs between them. fixed-rig models are marked in the PLY header; other viewers read them as ordinary models, right in their base colour.
    #[arg(long, value_enum, default_value = "auto")]
    pub appearance: AppearanceArg,
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
    /// An LPIPS network exported to ONNX (two [1,3,H,W] inputs in [-1,1], one distance out) for the `lpips` metrics; needs ONNX Runtime (--onnx-runtime or ORT_DYLIB_PATH).
    #[arg(long)]
    pub lpips: Option<PathBuf>,
    /// ONNX Runtime's shared library for --lpips (default: $ORT_DYLIB_PATH, else python3's onnxruntime package).
    #[arg(long)]
    pub onnx_runtime: Option<PathBuf>,
    /// Where rendering and its gradients run: auto (a real GPU when there is one, else the CPU), cpu, or gpu (any device, software ones included).
    #[arg(long, default_value = "auto")]
    pub backend: Backend,
    /// Read the views even where they need more memory than the system has available (with swap, say); without it such a set is refused before reading, naming the --downscale that fits.
    #[arg(long)]
    pub no_memory_check: bool,
    /// On a GPU: how much of the views' loss targets (20 bytes a pixel) stays on the device, gigabytes; a kept view is sent once, the others at each of their steps.
    #[arg(long, default_value_t = omniscan_splat::gpu::training::DEFAULT_VIEW_MEMORY as f64 / 1e9)]
    pub gpu_view_memory_gb: f64,
    #[arg(long)]
    pub json: bool,
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
    let gb = |bytes: u64| bytes as f64 / 1e9;
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

/// The memory the system can give without swapping, where it says
/// (Linux's /proc/meminfo).
fn available_memory() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// The summary's words for views whose object pixels the model never covers.
const NO_MASKED_PSNR: &str = "masked PSNR none (the model covers none of their object pixels)";

pub fn run(args: TrainArgs) -> Result<()> {
    let report = train_capture(&args)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        // Without held-out views (--hold-out-every 0) there is nothing to
        // score: say so rather than print NaN.
        let eval = &report["test"];
        let held_out = match (eval["psnr"].as_f64(), eval["psnr_masked"].as_f64()) {
            (Some(psnr), Some(masked)) => {
                format!("held-out views: PSNR {psnr:.2} dB, masked PSNR {masked:.2} dB")
            }
            // Views to score, but no object pixel the model covers: say so
            // plainly, it is a failed run, not a missing figure.
            (Some(psnr), None) => format!("held-out views: PSNR {psnr:.2} dB, {NO_MASKED_PSNR}"),
            _ => "no held-out views to score".to_string(),
        };
        let scores = match report["train"]["psnr_masked"].as_f64() {
            Some(masked) => format!("{held_out}; training views: masked PSNR {masked:.2} dB"),
            None if report["train"]["views"].as_u64().is_some_and(|n| n > 0) => {
                format!("{held_out}; training views: {NO_MASKED_PSNR}")
            }
            None => held_out,
        };
        println!(
            "wrote {} ({} splats) in {:.0} s; {scores}",
            args.out.display(),
            report["splats"],
            report["seconds"].as_f64().unwrap_or(0.0),
        );
    }
    Ok(())
}

/// `omniscan train` without the printing: trains, writes the model and
/// returns the report.
pub fn train_capture(args: &TrainArgs) -> Result<serde_json::Value> {
    if args.sh_degree > 3 {
        bail!("--sh-degree must be 0-3");
    }
    if matches!(args.densification, DensificationArg::Mcmc)
        && (args.absgrad || args.grad_threshold.is_some())
    {
        bail!(
            "--absgrad and --grad-threshold steer adaptive densification; MCMC does not use them"
        );
    }
    if let Some(threshold) = args.grad_threshold
        && !(threshold.is_finite() && threshold > 0.0)
    {
        bail!("--grad-threshold must be a positive number, got {threshold}");
    }
    if !(args.position_lr.is_finite() && args.position_lr >= 0.0) {
        bail!(
            "--position-lr must be a finite number, 0 or more, got {}",
            args.position_lr
        );
    }
    if !(args.sh_rest_lr.is_finite() && args.sh_rest_lr >= 0.0) {
        bail!(
            "--sh-rest-lr must be a finite number, 0 or more, got {}",
            args.sh_rest_lr
        );
    }
    if args.max_splats == 0 {
        bail!("--max-splats must be at least 1");
    }
    if !(args.gpu_view_memory_gb.is_finite() && args.gpu_view_memory_gb >= 0.0) {
        bail!(
            "--gpu-view-memory-gb must be a finite number, 0 or more, got {}",
            args.gpu_view_memory_gb
        );
    }
    if args.init.is_none()
        && args.init_right.is_none()
        && !(1..=args.max_splats).contains(&args.initial_points)
    {
        bail!(
            "--initial-points must be 1 to --max-splats ({}), got {}",
            args.max_splats,
            args.initial_points
        );
    }
    let right_to_left = args.merge.read(args.arm)?;
    if let Some(path) = &args.init_right
        && !matches!(args.arm, ArmSet::Both)
    {
        bail!(
            "--init-right {}: only a model of both arms (--arm both) starts from the right arm's points",
            path.display()
        );
    }
    let (source, view_set) = view_source(&args.capture, args.arm, right_to_left, args.downscale)?;
    if !args.no_memory_check {
        check_view_memory(&source, args.downscale, available_memory())?;
    }
    let all = {
        let bar = crate::progress_bar(source.len(), "reading", "views");
        let all =
            source.load_packed_each(&(0..source.len()).collect::<Vec<_>>(), &|| bar.inc(1))?;
        bar.finish_and_clear();
        all
    };
    // The merge the views were brought together by, for --init-right and the report.
    let merged_by = match view_set {
        Some(ViewSet::Merged { right_to_left }) => Some(right_to_left),
        _ => None,
    };
    if args.init_right.is_some() && merged_by.is_none() {
        bail!("--init-right needs a capture's views of both arms");
    }
    let appearance = match args.appearance {
        AppearanceArg::Auto if view_set.is_some() => Appearance::FixedRig,
        AppearanceArg::Auto | AppearanceArg::ViewDirection => Appearance::ViewDirection,
        AppearanceArg::FixedRig => Appearance::FixedRig,
    };
    let (train_views, test_views) =
        split_held_out_from(all, args.hold_out_every, args.hold_out_first);
    let start = Instant::now();
    let strategy = match args.densification {
        DensificationArg::Adaptive => TrainConfig::with_steps(args.steps),
        DensificationArg::Mcmc => TrainConfig::mcmc(args.steps),
    };
    let strategy = if args.absgrad {
        strategy.with_absolute_gradients()
    } else {
        strategy
    };
    let config = TrainConfig {
        seed: args.seed,
        max_sh_degree: args.sh_degree,
        max_splats: args.max_splats,
        position_lr: args.position_lr,
        sh_rest_lr: args.sh_rest_lr,
        grad_threshold: args.grad_threshold.unwrap_or(strategy.grad_threshold),
        ..strategy
    };
    let bar = indicatif::ProgressBar::new(args.steps as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "training [{bar:40}] {pos}/{len} {msg} ({elapsed_precise}, eta {eta})",
        )
        .unwrap()
        .progress_chars("=> "),
    );
    let mut recent = Vec::new();
    let mut renderer = match Renderer::new(args.backend)? {
        // `auto` falls back to the CPU on a GPU that can render but not train.
        Renderer::Gpu(gpu) if args.backend == Backend::Auto && !gpu.can_train() => {
            eprintln!(
                "{} cannot run the backward pass (no subgroup operations); training on the CPU",
                gpu.adapter()
            );
            Renderer::Cpu
        }
        r => r,
    };
    if let Renderer::Gpu(gpu) = &mut renderer {
        gpu.set_view_memory((args.gpu_view_memory_gb * 1e9) as u64);
    }
    eprintln!("training on {}", renderer.describe());
    // A nerfstudio set's own points (`ply_file_path`) start it, as in
    // nerfstudio, unless --init names others.
    let init = args
        .init
        .clone()
        .or_else(|| source.initial_points().map(PathBuf::from));
    let initial = || -> Result<_> {
        if args.init.is_none()
            && let Some(points) = &init
        {
            eprintln!(
                "starting from the photo set's points {} (its ply_file_path)",
                points.display()
            );
        }
        if init.is_none() && args.init_right.is_none() {
            return initial_splats(&train_views, args.initial_points, args.sh_degree, args.seed)
                .context("initialisation");
        }
        let (mut points, mut colours) = (Vec::new(), Vec::new());
        let starts = [(&init, None), (&args.init_right, merged_by)];
        for (path, to_views) in starts {
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
        let named = [&init, &args.init_right]
            .into_iter()
            .flatten()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(" and ");
        if points.len() > args.max_splats {
            bail!(
                "--init {named}: {} points, more than --max-splats {}: thin them (e.g. voxel-downsample) or raise --max-splats",
                points.len(),
                args.max_splats
            );
        }
        splats_from_points(&points, &colours, args.sh_degree)
            .with_context(|| format!("initialising from {named}"))
    };
    let checkpoint_path = {
        let mut name = args.out.as_os_str().to_owned();
        name.push(".checkpoint.safetensors");
        PathBuf::from(name)
    };
    let start_from = if args.resume {
        if !checkpoint_path.is_file() {
            bail!(
                "--resume: no checkpoint at {} (it is written every --checkpoint-every steps)",
                checkpoint_path.display()
            );
        }
        let state = omniscan_splat::checkpoint::load(&checkpoint_path)?;
        resumable_as(&state.splats, appearance, args.antialiased)
            .with_context(|| format!("--resume: {}", checkpoint_path.display()))?;
        eprintln!(
            "resuming after step {} from {}",
            state.step,
            checkpoint_path.display()
        );
        Start::Resume(Box::new(state))
    } else {
        let mut splats = initial()?;
        splats.antialiased = args.antialiased;
        splats.appearance = appearance;
        Start::Fresh(splats)
    };
    let mut save = |state: &omniscan_splat::train::TrainState| {
        omniscan_splat::checkpoint::save(state, &checkpoint_path)
    };
    let model = train_resumable(
        &train_views,
        start_from,
        &config,
        &renderer,
        Some(Checkpoints {
            every: args.checkpoint_every,
            save: &mut save,
        }),
        &mut |step, loss, psnr| {
            recent.push(psnr);
            if recent.len() > 20 {
                recent.remove(0);
            }
            if step % 10 == 0 {
                bar.set_message(format!(
                    "loss {loss:.4}, PSNR {:.2} dB",
                    recent.iter().sum::<f64>() / recent.len() as f64
                ));
            }
            bar.set_position(step as u64);
        },
    )?;
    bar.finish_and_clear();
    write_splats(&args.out, &model)?;
    if checkpoint_path.is_file() {
        std::fs::remove_file(&checkpoint_path)
            .with_context(|| format!("removing {}", checkpoint_path.display()))?;
    }
    let lpips = load_lpips(&args.lpips, args.onnx_runtime.as_deref())?;
    let eval = omniscan_splat::train::evaluate(&model, &test_views, lpips.as_ref())?;
    // The same figures on the views it trained on tell underfitting from
    // poor generalisation: on DTU scan37 after 3000 steps the held-out views'
    // 24 dB looked like overfitting until the training views' own 27 dB
    // showed the model had not yet fitted them either. (LPIPS is left to the
    // held-out views: it is the slow one.)
    let fit = omniscan_splat::train::evaluate(&model, &train_views, None)?;
    let report = json!({
        "model": args.out,
        "splats": model.len(),
        "steps": args.steps,
        "seconds": start.elapsed().as_secs_f64(),
        "train_views": train_views.len(),
        "test_views": test_views.len(),
        "settings": {
            "densification": match config.densification {
                Densification::Adaptive => "adaptive",
                Densification::Mcmc => "mcmc",
            },
            "absolute_gradients": config.absolute_gradients,
            "grad_threshold": config.grad_threshold,
            "antialiased": model.antialiased,
            "appearance": model.appearance.name(),
            "sh_degree": config.max_sh_degree,
            "position_lr": config.position_lr,
            "sh_rest_lr": config.sh_rest_lr,
            "max_splats": config.max_splats,
            "seed": config.seed,
            "init": match (&init, &args.init_right) {
                (None, None) => json!("visual hull"),
                (left, right) => json!([left, right].into_iter().flatten().collect::<Vec<_>>()),
            },
            "right_to_left": merged_by.map(|pose| json!({
                "transform": omniscan_core::geometry::pose_to_rows(&pose),
                "from": match &args.merge.right_to_left {
                    Some(path) => path.display().to_string(),
                    None => "handover estimate T_lh⁻¹·T_rh".to_string(),
                },
            })),
        },
        "test": eval,
        "train": fit,
    });
    Ok(report)
}

#[derive(clap::Args)]
pub struct EvalArgs {
    /// The splat model (3DGS PLY), or a training checkpoint (MODEL.ply.checkpoint.safetensors) to evaluate a run in progress.
    pub model: PathBuf,
    /// The capture whose views to compare against (or a photo set: a transforms.json, its directory, or a cameras.json).
    pub capture: PathBuf,
    /// Where to render: cpu (the reference, whose figures `train`'s report repeats to the digit), gpu (any Vulkan/Metal/DX12 device, software ones included) or auto (a real GPU when there is one); a GPU's figures agree with the CPU's to about 1e-4 relative.
    #[arg(long, default_value = "cpu")]
    pub backend: Backend,
    #[arg(long, value_enum, default_value = "left")]
    pub arm: ArmSet,
    #[command(flatten)]
    pub merge: RightToLeftArg,
    /// Shrink images by this integer factor before comparing.
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// Compare only the views that training with this --hold-out-every held out (the n-th, the 2n-th, ...); 0: every view.
    #[arg(long, default_value_t = 0)]
    pub held_out_every: usize,
    /// The first held-out view's index, as training's --hold-out-first (default: n-1).
    #[arg(long)]
    pub held_out_first: Option<usize>,
    /// An LPIPS network exported to ONNX (two [1,3,H,W] inputs in [-1,1], one distance out) for the `lpips` metrics; needs ONNX Runtime (--onnx-runtime or ORT_DYLIB_PATH).
    #[arg(long)]
    pub lpips: Option<PathBuf>,
    /// ONNX Runtime's shared library for --lpips (default: $ORT_DYLIB_PATH, else python3's onnxruntime package).
    #[arg(long)]
    pub onnx_runtime: Option<PathBuf>,
    /// Also write, per view, the photo (object pixels) beside the render as PNG into this directory.
    #[arg(long)]
    pub renders: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
}

fn load_lpips(
    path: &Option<PathBuf>,
    runtime: Option<&std::path::Path>,
) -> Result<Option<omniscan_splat::lpips::Lpips>> {
    Ok(match path {
        Some(p) => Some(omniscan_splat::lpips::Lpips::load(p, runtime)?),
        None => None,
    })
}

/// The photo set `path` names: a JSON file other than a capture's, or a
/// directory holding a `transforms.json` and no capture.
pub(crate) fn photo_set_file(path: &std::path::Path) -> Option<PathBuf> {
    let capture_file = omniscan_core::capture::CAPTURE_FILE;
    let nerfstudio = path.join("transforms.json");
    if path.extension().is_some_and(|e| e == "json") && !path.ends_with(capture_file) {
        Some(path.to_path_buf())
    } else if path.is_dir() && !path.join(capture_file).exists() && nerfstudio.is_file() {
        Some(nerfstudio)
    } else {
        None
    }
}

/// The views of a capture (one arm, or both merged at the handover or by
/// `right_to_left`) and the set they are, or of a calibrated photo set
/// (a `transforms.json`, a directory holding one and no capture, or a
/// `cameras.json`; no set: it has no arms), not yet read.
pub(crate) fn view_source(
    path: &std::path::Path,
    arm: ArmSet,
    right_to_left: Option<Pose>,
    downscale: u32,
) -> Result<(ViewSource, Option<ViewSet>)> {
    if let Some(photo_set) = photo_set_file(path) {
        let photo_set = photo_set.as_path();
        if right_to_left.is_some() {
            bail!(
                "--right-to-left: {} is a photo set, whose views have no arms to merge",
                photo_set.display()
            );
        }
        return Ok((ViewSource::from_photo_set(photo_set, downscale)?, None));
    }
    let capture = Capture::load(path)?;
    let set = arm.view_set(&capture, right_to_left);
    Ok((
        ViewSource::from_capture(&capture, set, downscale)?,
        Some(set),
    ))
}

/// `omniscan eval`: PSNR/SSIM of a model against a capture's images, whole
/// and masked (object ∩ accumulation, gripper excluded).
pub fn eval(args: EvalArgs) -> Result<()> {
    let is_checkpoint = args.model.extension().is_some_and(|e| e == "safetensors");
    let (model, checkpoint_step) = if is_checkpoint {
        let state = omniscan_splat::checkpoint::load(&args.model)?;
        (state.splats, Some(state.step))
    } else {
        (omniscan_splat::ply::read_splats(&args.model)?, None)
    };
    let right_to_left = args.merge.read(args.arm)?;
    let (source, _) = view_source(&args.capture, args.arm, right_to_left, args.downscale)?;
    // Each compared view keeps its index in the capture, for the per-view
    // figures; only those views are read, each dropped once compared.
    let (training, held_out) = split_held_out_from(
        (0..source.len()).collect(),
        args.held_out_every,
        args.held_out_first,
    );
    let indices = match args.held_out_every {
        0 => training,
        _ => held_out,
    };
    let byte = |x: f32| (x.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    let write_pair =
        |dir: &std::path::Path, i: usize, v: &omniscan_splat::views::View, rgb: &[[f32; 3]]| {
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
        };
    let lpips = load_lpips(&args.lpips, args.onnx_runtime.as_deref())?;
    let bar = crate::progress_bar(indices.len(), "evaluating", "views");
    let renderer = Renderer::new(args.backend)?;
    if renderer.is_gpu() {
        eprintln!("rendering on {}", renderer.describe());
    }
    let mut report = omniscan_splat::train::evaluate_views(
        &model,
        &renderer,
        indices.len(),
        |i| source.load(indices[i]).map(std::borrow::Cow::Owned),
        lpips.as_ref(),
        |i, v, rgb| {
            bar.inc(1);
            match &args.renders {
                Some(dir) => Ok(write_pair(dir, i, v, rgb)?),
                None => Ok(()),
            }
        },
    )?;
    bar.finish_and_clear();
    if let Some(step) = checkpoint_step {
        report["checkpoint_step"] = json!(step);
    }
    if let Some(per_view) = report["per_view"].as_array_mut() {
        for (figures, index) in per_view.iter_mut().zip(indices) {
            figures["view"] = json!(index);
        }
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{} views: PSNR {:.2} dB, SSIM {:.4}; masked PSNR {:.2} dB, masked SSIM {:.4}; {}",
            report["views"],
            report["psnr"].as_f64().unwrap_or(f64::NAN),
            report["ssim"].as_f64().unwrap_or(f64::NAN),
            report["psnr_masked"].as_f64().unwrap_or(f64::NAN),
            report["ssim_masked"].as_f64().unwrap_or(f64::NAN),
            match (report["lpips"].as_f64(), report["lpips_masked"].as_f64()) {
                (Some(l), Some(m)) => format!("LPIPS {l:.4}, masked LPIPS {m:.4}"),
                (Some(l), None) => format!("LPIPS {l:.4}"),
                _ => "LPIPS not computed (no network given: --lpips FILE.onnx)".into(),
            }
        );
    }
    Ok(())
}

/// Whether a checkpoint's model can go on as asked: its appearance and
/// footprint filter are part of the model, so a resumed run keeps them.
fn resumable_as(
    kept: &omniscan_splat::Splats,
    appearance: Appearance,
    antialiased: bool,
) -> Result<()> {
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

/// The demo's training step: the merged model on both arms' views (right
/// frames brought into the left frame by `right_to_left`), every 8th view
/// held out. Returns the evaluation report.
pub fn train_merged(
    capture: &Capture,
    right_to_left: omniscan_core::Pose,
    out: &std::path::Path,
    steps: usize,
    downscale: u32,
) -> Result<serde_json::Value> {
    let all = views_from_capture(capture, ViewSet::Merged { right_to_left }, downscale)?;
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
    let bar = indicatif::ProgressBar::new(steps as u64);
    // The demo stays on the CPU reference: its figures are the same on every machine.
    let model = train(
        &train_views,
        init,
        &config,
        &Renderer::Cpu,
        &mut |step, _, _| bar.set_position(step as u64),
    )?;
    bar.finish_and_clear();
    write_splats(out, &model)?;
    Ok(
        json!({ "model": out, "splats": model.len(), "steps": steps, "test": omniscan_splat::train::evaluate(&model, &test_views, None)? }),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let set = json!({
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
        let kept = omniscan_splat::Splats {
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
