//! The `omniscan` command line: a thin layer over `omniscan-pipeline`.
//! Each command's flags are the stage's settings struct (flattened), so a
//! default is written once, in the library; the command prints one summary
//! line, or the stage's whole report with `--json`. [`run_from`] is the
//! whole command line, for the binary and for the Python package.

mod gripper;

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use serde_json::json;

use omniscan_core::capture::{Arm, Capture};
use omniscan_core::nerfstudio::{ExportOptions, export_nerfstudio};
use omniscan_pipeline::align::AlignSettings;
use omniscan_pipeline::evaluate::EvalSettings;
use omniscan_pipeline::inspect::{InspectionSettings, MakeCopySettings};
use omniscan_pipeline::mask::MaskingSettings;
use omniscan_pipeline::render::RenderSettings;
use omniscan_pipeline::simulate::{PlanSettings, SimulateSettings};
use omniscan_pipeline::train::TrainSettings;
use omniscan_pipeline::twin::TwinSettings;
use omniscan_pipeline::views::{ArmSet, Merge};

use omniscan_pipeline::progress::Bars;

#[derive(Parser)]
#[command(
    name = "omniscan",
    version,
    about = "360° Gaussian-splat digital twins from bimanual in-hand scans (Omni-Scan)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Read files that a capture.json, transforms.json or cameras.json names outside its own folder (absolute paths, `..`, symbolic links leading out), which are refused otherwise (docs/security.md).
    #[arg(long, global = true)]
    allow_outside_paths: bool,
    /// The GPU to use where a command renders or trains on one: an index among the hardware adapters (0, 1, ...) or a PCI bus id (0000:3b:00.0, as nvidia-smi prints it). Default: wgpu's high-performance adapter.
    #[arg(long, global = true, value_name = "INDEX|PCI_BUS_ID")]
    gpu: Option<omniscan_splat::gpu::select::GpuSelector>,
}

#[derive(Subcommand)]
enum ImportSource {
    /// A ROS 2 bag (rosbag2: MCAP or sqlite3, a file or its folder) to a capture: images, depth and camera_info from the camera's topics, poses from TF at each image's stamp, the scan's phases from /omniscan/phase. The capture appears whole or not at all. docs/ros2.md
    Ros2 {
        /// The bag: a .mcap or .db3 file, or the rosbag2 folder holding them.
        bag: PathBuf,
        /// The capture folder to create (must not exist).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        settings: omniscan_pipeline::import::ImportSettings,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand)]
enum Command {
    /// Run the whole pipeline on a built-in object: simulate a scan, mask it, merge the two arms, export it for nerfstudio, train a first twin.
    Demo {
        /// Where to write the demo's outputs.
        #[arg(long, default_value = "omniscan-demo")]
        out: PathBuf,
        /// Built-in object to scan.
        #[arg(long, default_value = "builtin:flashlight")]
        object: String,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Simulate a bimanual in-hand scan and write a capture with ground truth.
    Sim(SimArgs),
    /// Check a capture (or a photo set: every image's, mask's and depth map's header and size) and print its summary.
    Validate {
        /// Capture directory (or its capture.json), or a photo set (a transforms.json, its directory, or a cameras.json).
        capture: PathBuf,
        /// Print the summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Write one HTML file that shows splat models in 3D in any browser, offline (orbit, pan, zoom; several models side by side or one at a time). docs/view.md
    View {
        /// The models to show (any format `convert` reads).
        #[arg(required = true)]
        models: Vec<PathBuf>,
        /// The page to write.
        #[arg(long, default_value = "view.html")]
        out: PathBuf,
        #[command(flatten)]
        settings: omniscan_pipeline::share::ViewSettings,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Convert a splat model between formats, chosen by extension: .ply (3DGS PLY, lossless), .spz (Niantic SPZ, about a tenth of the size), .glb (glTF KHR_gaussian_splatting), .splat (web viewers: base colour only); .compressed.ply (PlayCanvas) is read. docs/formats.md
    Convert {
        /// The model to read.
        input: PathBuf,
        /// The model to write.
        output: PathBuf,
        #[command(flatten)]
        settings: omniscan_pipeline::share::ConvertSettings,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
    /// A watertight, coloured triangle mesh of a twin, in metres: OBJ + MTL + PNG texture, PLY, GLB, and mesh.json (area, volume, unseen area in mm², watertightness). docs/mesh.md
    Mesh {
        /// The twin (any format `convert` reads).
        model: PathBuf,
        /// The folder to write.
        #[arg(long, default_value = "mesh")]
        out: PathBuf,
        #[command(flatten)]
        settings: omniscan_pipeline::geometry::MeshSettings,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
    /// A simulation asset of a twin: the mesh, convex collision pieces, mass and inertia, as URDF and MuJoCo MJCF. docs/mesh.md
    Asset {
        /// The twin (any format `convert` reads).
        model: PathBuf,
        /// The folder to write.
        #[arg(long, default_value = "asset")]
        out: PathBuf,
        #[command(flatten)]
        settings: omniscan_pipeline::geometry::AssetSettings,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Make a capture from a real robot's recording. docs/ros2.md
    #[command(subcommand)]
    Import(ImportSource),
    /// Gripper and object masks for every frame of a capture (kinematic gripper masks, the paper's object pipeline).
    Mask(MaskArgs),
    /// Write a nerfstudio transforms.json (OpenGL camera axes, object masks; gripper masks under omniscan's own gripper_mask_path, which nerfstudio ignores).
    ExportNerfstudio {
        capture: PathBuf,
        #[arg(long, value_enum)]
        arm: ArmSet,
        #[command(flatten)]
        merge: Merge,
        #[arg(long)]
        out: PathBuf,
        /// Leave out mask_path (train on whole images).
        #[arg(long)]
        no_masks: bool,
    },
    /// Train a splat model on a capture with the paper's masked losses (CPU, or a GPU with --backend).
    Train(TrainArgs),
    /// A capture to its 360° twin: a model per arm, the right aligned onto the left from the handover, the merged model from both (resumable).
    Twin(TwinArgs),
    /// PSNR and SSIM of a splat model against a capture's views (whole and masked).
    Eval(EvalArgs),
    /// Render a splat model from orbiting cameras or a capture's cameras.
    Render(RenderArgs),
    /// Register SOURCE onto TARGET (point clouds or splat models) and write the transform.
    Align(AlignArgs),
    /// Find the defective copy among splat models of three or more copies of a part, and show where.
    Inspect(InspectArgs),
    /// Make a good or defective copy of a splat model (for tests and benchmarks).
    MakeCopy(CopyArgs),
    /// Print the gripper poses of the scan trajectory a robot would execute.
    Plan {
        #[command(flatten)]
        plan: PlanSettings,
        #[arg(long)]
        json: bool,
    },
    /// Benchmarks (numbers go here, not in tests).
    Bench {
        #[command(subcommand)]
        which: omniscan_bench::BenchCommand,
    },
}

#[derive(Args)]
struct SimArgs {
    /// Output capture directory.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    settings: SimulateSettings,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
struct MaskArgs {
    #[command(subcommand)]
    command: Option<gripper::MaskCommand>,
    /// Capture directory (or its capture.json).
    #[arg(required = true)]
    capture: Option<PathBuf>,
    #[command(flatten)]
    settings: MaskingSettings,
    /// Compare the masks with the simulator's ground truth (mean IoU per arm).
    #[arg(long)]
    eval: bool,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct TrainArgs {
    /// The capture directory, or a calibrated photo set: a nerfstudio transforms.json (or its directory; perspective or OPENCV_FISHEYE cameras, their lens distortion undone as the photos are read, the object near the origin or where the cameras look, mask_path as the object mask, else the image's alpha, else the whole image), or a cameras.json (file_path, mask_path, fl_x, fl_y, cx, cy in OpenCV's pixel convention, camera_to_world_opencv per frame). A frame's w, h, when given, must be its image's size, since the intrinsics are in its pixels.
    capture: PathBuf,
    /// Output model (3DGS PLY).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    settings: TrainSettings,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct TwinArgs {
    /// The capture directory (both arms' scans, with masks).
    capture: PathBuf,
    /// Folder for the stages' models, transform and records (reused when run again).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    settings: TwinSettings,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct EvalArgs {
    /// The splat model (3DGS PLY), or a training checkpoint (MODEL.ply.checkpoint.safetensors) to evaluate a run in progress.
    model: PathBuf,
    /// The capture whose views to compare against (or a photo set: a transforms.json, its directory, or a cameras.json).
    capture: PathBuf,
    #[command(flatten)]
    settings: EvalSettings,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct RenderArgs {
    /// The splat model (3DGS PLY).
    model: PathBuf,
    /// Output directory for the PNG images.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    settings: RenderSettings,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct AlignArgs {
    /// Point cloud or splat model to move (.ply, .pcd, .xyz).
    source: PathBuf,
    /// Point cloud or splat model to align to.
    target: PathBuf,
    /// Output JSON: transform (4x4 row-major, maps SOURCE into TARGET), fitness, inlier_rmse, method.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    settings: AlignSettings,
    /// Also print the result as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct InspectArgs {
    /// Splat models (3DGS PLY) of three or more copies of one part; all are aligned to the first.
    #[arg(required = true, num_args = 3..)]
    models: Vec<PathBuf>,
    /// Output directory (verdict.json, difference renders, defects.ply, report.html).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    settings: InspectionSettings,
    /// Print verdict.json instead of a summary.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct CopyArgs {
    /// The splat model to copy (3DGS PLY).
    model: PathBuf,
    /// Where to write the copy.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    settings: MakeCopySettings,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

/// Runs the command line on `args` (the first the program's name) and
/// returns the exit status: 0, or after an error (printed as `error: …` with
/// its causes) 1 for bad input, 74 for a file that could not be read or
/// written, 75 for an output in use
/// ([`Failure::exit_code`](omniscan_pipeline::failure::Failure::exit_code)),
/// or clap's 2 for a usage error. The binary
/// and the Python package's `omniscan` command both call it.
pub fn run_from<I, T>(args: I) -> i32
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    // A second call in one process (Python) keeps the first subscriber.
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .try_init();
    let cli = match Cli::try_parse_from(args) {
        Ok(cli) => cli,
        Err(e) => {
            let _ = e.print();
            return e.exit_code();
        }
    };
    match run(cli) {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("error: {e:#}");
            omniscan_pipeline::failure::Failure::of(&e).exit_code()
        }
    }
}

/// Prints `report` as pretty JSON.
fn print_json(report: &impl serde::Serialize) -> Result<()> {
    println!("{}", serde_json::to_string_pretty(report)?);
    Ok(())
}

fn run(cli: Cli) -> Result<()> {
    let bars = Bars::new();
    omniscan_core::paths::set_allow_outside(cli.allow_outside_paths);
    if let Some(gpu) = cli.gpu.clone() {
        omniscan_splat::gpu::select::select_gpu(gpu);
    }
    match cli.command {
        Command::Demo { out, object, json } => demo(&out, &object, json, &bars),
        Command::Sim(args) => sim(args, &bars),
        Command::Validate { capture, json } => validate(&capture, json),
        Command::View {
            models,
            out,
            settings,
            json,
        } => view(&models, &out, &settings, json),
        Command::Convert {
            input,
            output,
            settings,
            json,
        } => convert(&input, &output, &settings, json),
        Command::Mesh {
            model,
            out,
            settings,
            json,
        } => mesh(&model, &out, &settings, json, &bars),
        Command::Asset {
            model,
            out,
            settings,
            json,
        } => asset(&model, &out, &settings, json, &bars),
        Command::Import(ImportSource::Ros2 {
            bag,
            out,
            settings,
            json,
        }) => import_ros2(&bag, &out, &settings, json, &bars),
        Command::Mask(args) => mask(args, &bars),
        Command::ExportNerfstudio {
            capture,
            arm,
            merge,
            out,
            no_masks,
        } => export_nerfstudio_set(&capture, arm, &merge, &out, no_masks),
        Command::Train(args) => train(args, &bars),
        Command::Twin(args) => twin(args, &bars),
        Command::Eval(args) => eval(args, &bars),
        Command::Render(args) => render(args, &bars),
        Command::Align(args) => align(args),
        Command::Inspect(args) => inspect(args, &bars),
        Command::MakeCopy(args) => make_copy(args),
        Command::Plan { plan, json } => print_plan(&plan, json),
        Command::Bench { which } => omniscan_bench::run(which),
    }
}

fn demo(out: &std::path::Path, object: &str, json: bool, bars: &Bars) -> Result<()> {
    let report = omniscan_pipeline::demo::demo(object, out, bars)?;
    if json {
        return print_json(&report);
    }
    println!(
        "wrote the demo to {}: twin {} ({} splats, held-out masked PSNR {:.2} dB)",
        out.display(),
        report.twin.model.display(),
        report.twin.splats,
        report.twin.test.psnr_masked.unwrap_or(f64::NAN)
    );
    println!("open in a browser:");
    println!(
        "  {}   the twin in 3D (drag to orbit)",
        report.view_page.display()
    );
    println!(
        "  {}   what each step did, with pictures",
        report.report_page.display()
    );
    println!("next:");
    println!(
        "  omniscan twin {} --out {}   the full twin (about 5 minutes), with its own report.html",
        report.capture.display(),
        out.join("full-twin").display()
    );
    println!(
        "  omniscan convert {} {}   a compact copy for other viewers (SPZ, .glb)",
        report.twin.model.display(),
        out.join("twin.spz").display()
    );
    Ok(())
}

fn sim(args: SimArgs, bars: &Bars) -> Result<()> {
    let summary = omniscan_pipeline::simulate::simulate(&args.settings, &args.out, bars)?;
    if args.json {
        return print_json(&summary);
    }
    println!(
        "wrote {} ({} frames, {} empty frames) in {:.1} s",
        summary.capture.display(),
        summary.frames,
        summary.empty_frames,
        summary.seconds
    );
    Ok(())
}

fn export_nerfstudio_set(
    capture: &std::path::Path,
    arm: ArmSet,
    merge: &Merge,
    out: &std::path::Path,
    no_masks: bool,
) -> Result<()> {
    let right_to_left = merge.read(arm)?;
    let loaded = Capture::load(capture)?;
    let views = arm.view_set(&loaded, right_to_left);
    let summary = export_nerfstudio(
        &loaded,
        out,
        ExportOptions {
            views,
            masks: !no_masks,
        },
    )?;
    println!(
        "wrote {} ({} frames)",
        summary.transforms.display(),
        summary.frames
    );
    Ok(())
}

fn train(args: TrainArgs, bars: &Bars) -> Result<()> {
    let report = omniscan_pipeline::train::train(&args.capture, &args.out, &args.settings, bars)?;
    if args.json {
        return print_json(&report);
    }
    println!(
        "wrote {} ({} splats) in {:.0} s; {}",
        args.out.display(),
        report.splats,
        report.seconds,
        scores(&report)
    );
    Ok(())
}

fn twin(args: TwinArgs, bars: &Bars) -> Result<()> {
    let report = omniscan_pipeline::twin::twin(&args.capture, &args.out, &args.settings, bars)?;
    if args.json {
        return print_json(&report);
    }
    let twin = &report.stages.twin.report;
    let align = &report.stages.align.report;
    println!(
        "wrote {} ({} splats); {}; right onto left by {} (fitness {:.4})",
        report.twin.display(),
        twin.splats,
        held_out(&twin.test),
        align.method,
        align.fitness,
    );
    Ok(())
}

fn eval(args: EvalArgs, bars: &Bars) -> Result<()> {
    let report =
        omniscan_pipeline::evaluate::evaluate(&args.model, &args.capture, &args.settings, bars)?;
    if args.json {
        return print_json(&report);
    }
    print_evaluation(&report.evaluation);
    Ok(())
}

fn render(args: RenderArgs, bars: &Bars) -> Result<()> {
    let report = omniscan_pipeline::render::render(&args.model, &args.out, &args.settings, bars)?;
    if args.json {
        return print_json(&report);
    }
    println!(
        "wrote {} images to {}",
        report.images.len(),
        args.out.display()
    );
    Ok(())
}

fn align(args: AlignArgs) -> Result<()> {
    let report =
        omniscan_pipeline::align::align(&args.source, &args.target, &args.out, &args.settings)?;
    if args.json {
        return print_json(&report);
    }
    println!(
        "{}: fitness {:.4}, inlier RMSE {:.6}, {} iterations, {:.2} s; wrote {}",
        report.method,
        report.fitness,
        report.inlier_rmse,
        report.iterations,
        report.seconds,
        args.out.display()
    );
    Ok(())
}

fn make_copy(args: CopyArgs) -> Result<()> {
    let report = omniscan_pipeline::inspect::make_copy(&args.model, &args.out, &args.settings)?;
    if args.json {
        return print_json(&report);
    }
    let defect = match &report.defect {
        Some(d) => format!(
            "with a {} mm {} ({} splats changed)",
            d.size_mm, d.kind, d.affected_splats
        ),
        None => "without a defect".into(),
    };
    println!(
        "wrote {} ({} splats), a copy {defect}; --json for its pose and the defect's place",
        report.copy.display(),
        report.splats
    );
    Ok(())
}

/// The summary's words for views whose object pixels the model never covers.
const NO_MASKED_PSNR: &str = "masked PSNR none (the model covers none of their object pixels)";

/// The held-out views' figures in words; without held-out views
/// (--hold-out-every 0) there is nothing to score, which it says rather
/// than print NaN.
fn held_out(test: &omniscan_splat::evaluation::Evaluation) -> String {
    match (test.psnr, test.psnr_masked) {
        (Some(psnr), Some(masked)) => {
            format!("held-out views: PSNR {psnr:.2} dB, masked PSNR {masked:.2} dB")
        }
        // Views to score, but no object pixel the model covers: say so
        // plainly, it is a failed run, not a missing figure.
        (Some(psnr), None) => format!("held-out views: PSNR {psnr:.2} dB, {NO_MASKED_PSNR}"),
        _ => "no held-out views to score".to_string(),
    }
}

/// A training's held-out and training-view figures in words.
fn scores(report: &omniscan_pipeline::train::TrainReport) -> String {
    let held_out = held_out(&report.test);
    match report.train.psnr_masked {
        Some(masked) => format!("{held_out}; training views: masked PSNR {masked:.2} dB"),
        None if report.train.views > 0 => format!("{held_out}; training views: {NO_MASKED_PSNR}"),
        None => held_out,
    }
}

fn print_evaluation(e: &omniscan_splat::evaluation::Evaluation) {
    let f = |v: Option<f64>| v.unwrap_or(f64::NAN);
    println!(
        "{} views: PSNR {:.2} dB, SSIM {:.4}; masked PSNR {:.2} dB, masked SSIM {:.4}; {}",
        e.views,
        f(e.psnr),
        f(e.ssim),
        f(e.psnr_masked),
        f(e.ssim_masked),
        match (e.lpips, e.lpips_masked) {
            (Some(l), Some(m)) => format!("LPIPS {l:.4}, masked LPIPS {m:.4}"),
            (Some(l), None) => format!("LPIPS {l:.4}"),
            _ => "LPIPS not computed (no network given: --lpips FILE.onnx)".into(),
        }
    );
}

fn view(
    models: &[PathBuf],
    out: &std::path::Path,
    settings: &omniscan_pipeline::share::ViewSettings,
    json: bool,
) -> Result<()> {
    let report = omniscan_pipeline::share::view(models, out, settings)?;
    if json {
        return print_json(&report);
    }
    println!(
        "wrote {} ({} models, {} splats, {:.1} MB): open it in a browser",
        report.out.display(),
        report.models,
        report.splats,
        report.bytes as f64 / 1e6
    );
    Ok(())
}

fn convert(
    input: &std::path::Path,
    output: &std::path::Path,
    settings: &omniscan_pipeline::share::ConvertSettings,
    json: bool,
) -> Result<()> {
    let report = omniscan_pipeline::share::convert(input, output, settings)?;
    if json {
        return print_json(&report);
    }
    println!(
        "wrote {} splats to {} ({}, {:.2} MB)",
        report.splats,
        report.output.display(),
        report.format,
        report.bytes as f64 / 1e6
    );
    Ok(())
}

fn print_mesh(report: &omniscan_pipeline::geometry::MeshReport) {
    let s = &report.stats;
    println!(
        "mesh: {} triangles, {:.1} x {:.1} x {:.1} mm, area {:.0} mm², volume {:.0} mm³, {}",
        s.topology.faces,
        s.extent_mm[0],
        s.extent_mm[1],
        s.extent_mm[2],
        s.area_mm2,
        s.volume_mm3,
        if s.topology.is_watertight() {
            "watertight"
        } else {
            "NOT watertight"
        }
    );
    println!(
        "  {:.2} mm voxels, {} views; closed over {:.1} mm² no view saw (marked `unseen` in the PLY); {:.1} s",
        s.voxel_mm, s.views, s.unseen_area_mm2, s.seconds
    );
    let f = &report.files;
    for path in [&f.obj, &f.ply, &f.glb] {
        println!("  wrote {}", path.display());
    }
}

fn mesh(
    model: &std::path::Path,
    out: &std::path::Path,
    settings: &omniscan_pipeline::geometry::MeshSettings,
    json: bool,
    bars: &omniscan_pipeline::Bars,
) -> Result<()> {
    let report = omniscan_pipeline::geometry::mesh(model, out, settings, bars)?;
    if json {
        return print_json(&report);
    }
    print_mesh(&report);
    Ok(())
}

fn import_ros2(
    bag: &std::path::Path,
    out: &std::path::Path,
    settings: &omniscan_pipeline::import::ImportSettings,
    json: bool,
    bars: &omniscan_pipeline::Bars,
) -> Result<()> {
    let report = omniscan_pipeline::import::import_ros2(bag, out, settings, bars)?;
    if json {
        return print_json(&report);
    }
    println!(
        "imported {}: {} left and {} right frames, {} empty; {} with depth, {} with the finger opening; {} images outside the scan phases skipped; {}; {:.1} s",
        report.capture.display(),
        report.left_frames,
        report.right_frames,
        report.empty_frames,
        report.frames_with_depth,
        report.frames_with_opening,
        report.skipped_images,
        match report.distortion {
            Some(_) => "lens distortion recorded",
            None => "pinhole camera",
        },
        report.seconds
    );
    Ok(())
}

fn asset(
    model: &std::path::Path,
    out: &std::path::Path,
    settings: &omniscan_pipeline::geometry::AssetSettings,
    json: bool,
    bars: &omniscan_pipeline::Bars,
) -> Result<()> {
    let report = omniscan_pipeline::geometry::asset(model, out, settings, bars)?;
    if json {
        return print_json(&report);
    }
    print_mesh(&report.mesh);
    let m = &report.mass;
    println!(
        "asset: {:.1} g at {:.0} kg/m³, {} convex pieces ({:.0}% of the volume), {:.1} s",
        m.mass_kg * 1e3,
        m.density_kg_m3,
        report.collision_meshes.len(),
        report.hull_volume_percent,
        report.seconds
    );
    println!("  wrote {}", report.urdf.display());
    println!("  wrote {}", report.mjcf.display());
    Ok(())
}

fn validate(capture: &std::path::Path, json: bool) -> Result<()> {
    if let Some(photos) = omniscan_pipeline::views::photo_set_file(capture) {
        let source = omniscan_splat::views::ViewSource::from_photo_set(&photos, 1)?;
        let summary = source
            .check_photos(true)?
            .with_context(|| format!("{} is not a photo set", photos.display()))?;
        if json {
            println!("{}", serde_json::to_string(&summary)?);
        } else {
            let size = match (summary.width, summary.height) {
                (Some(w), Some(h)) => format!("{w}x{h}"),
                _ => "sizes vary".into(),
            };
            println!(
                "{}: valid photo set ({}), {} frames, {size}, object masks: {} files / {} alpha / {} whole images, depth maps: {}, gripper masks: {}, lens distortion undone: {} frames, initial points: {}",
                photos.display(),
                summary.format.name(),
                summary.frames,
                summary.mask_files,
                summary.alpha_masks,
                summary.whole_image_masks,
                summary.depth_maps,
                summary.gripper_masks,
                summary.undistorted,
                summary
                    .initial_points
                    .as_ref()
                    .map_or("none".into(), |p| p.display().to_string()),
            );
        }
        return Ok(());
    }
    let loaded = Capture::load_unchecked(capture)?;
    loaded.validate_pixels()?;
    let summary = loaded.summary();
    if json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        println!(
            "{}: valid capture v{}, {}x{}, {} left / {} right / {} empty frames, depth: {}, ground truth: {}",
            capture.display(),
            summary.version,
            summary.width,
            summary.height,
            summary.left_frames,
            summary.right_frames,
            summary.empty_frames,
            summary.depth,
            summary.ground_truth
        );
    }
    Ok(())
}

fn mask(args: MaskArgs, bars: &Bars) -> Result<()> {
    if let Some(command) = args.command {
        return gripper::run(command);
    }
    let capture = args.capture.context("a capture directory is required")?;
    let report = omniscan_pipeline::mask::mask(&capture, &args.settings, args.eval, bars)?;
    if args.json {
        return print_json(&report);
    }
    let summary = &report.masking;
    println!(
        "{} frames masked ({} computed, {} kept from an earlier run) in {:.1} s; masks in {}",
        summary.frames,
        summary.computed,
        summary.resumed,
        summary.seconds,
        report.mask_dir.display()
    );
    if let Some(e) = report.evaluation {
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
    Ok(())
}

fn inspect(args: InspectArgs, bars: &Bars) -> Result<()> {
    let report =
        omniscan_pipeline::inspect::inspect(&args.models, &args.out, &args.settings, bars)?;
    if args.json {
        let text = std::fs::read_to_string(&report.verdict)
            .with_context(|| format!("reading {}", report.verdict.display()))?;
        println!("{text}");
        return Ok(());
    }
    for a in &report.alignments {
        println!(
            "aligned {} to {}: fitness {:.3}, RMSE {:.5} ({})",
            a.model.display(),
            args.models[0].display(),
            a.fitness,
            a.inlier_rmse,
            a.method
        );
    }
    match &report.defective {
        Some(model) => println!(
            "defective: {} ({} defect, {:.1} mm² in {} significant region(s), the clearest {:.1} \
             times what the other copies differ by)",
            model.display(),
            report.defect_type,
            report.area_mm2,
            report.significant_regions,
            report.score
        ),
        None => println!("no defective model: the copies agree"),
    }
    println!(
        "report: {} ({:.1} s)",
        report.report.display(),
        report.seconds
    );
    Ok(())
}

fn print_plan(plan: &PlanSettings, json: bool) -> Result<()> {
    let config = plan.config();
    if let Err(e) = config.validate() {
        bail!("invalid scan plan: {e}");
    }
    let left = config.trajectory(Arm::Left);
    let right = config.trajectory(Arm::Right);
    if json {
        return print_json(&json!({
            "config": config,
            "units": "metres and radians; poses are gripper (TCP) to world, 4x4 row-major",
            "camera_to_world": omniscan_core::RigidTransform(config.camera_to_world()),
            "left": left,
            "right": right,
            "left_handover": omniscan_core::RigidTransform(config.left_handover_pose()),
            "right_handover": "computed from the regrasp chosen on the object at handover: T_rh = T_lh · T_lo · T_ro⁻¹",
        }));
    }
    println!(
        "scan plan: {} wrist angles x {} latitudes = {} poses per arm",
        config.wrist_angles,
        config.latitudes,
        left.len()
    );
    for j in 0..config.latitudes {
        println!("  latitude {:>6.1}°", config.latitude(j).to_degrees());
    }
    let t = config.scan_point_m;
    println!(
        "object held at ({:.3}, {:.3}, {:.3}) m; camera {:.2} m away",
        t[0], t[1], t[2], config.camera_distance_m
    );
    println!("use --json for the poses");
    Ok(())
}
