//! The `omniscan` command line: simulate in-hand scans, check and export
//! captures, print the scan plan, and benchmark.

mod inspect;
mod mask;
mod registration;
mod render;
mod scan_bench;
mod splat_bench;
mod train;
mod twin;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

use omniscan_core::capture::{Arm, Capture};
use omniscan_core::nerfstudio::{ExportOptions, export_nerfstudio};
use omniscan_core::plan::ScanPlanConfig;
use omniscan_core::poses::ViewSet;
use omniscan_sim::{SimConfig, Simulation};

/// mimalloc instead of the system allocator: a training step frees and
/// takes back hundreds of megabytes of image-sized buffers (SSIM's blurs,
/// per-pixel gradients), which glibc hands to the kernel and maps again each
/// time; on the 2-core development VM the page clearing and TLB shootdowns
/// of that made SSIM and its gradient 0.14 s instead of 0.06 s at 640x480,
/// and a step on a 130k-splat model 0.41-0.52 s instead of 0.38 s.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
#[command(
    name = "omniscan",
    version,
    about = "360° Gaussian-splat digital twins from bimanual in-hand scans (Omni-Scan)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
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
    /// Gripper and object masks for every frame of a capture (kinematic gripper masks, the paper's object pipeline).
    Mask(mask::MaskArgs),
    /// Write a nerfstudio transforms.json (OpenGL camera axes, object masks; gripper masks under omniscan's own gripper_mask_path, which nerfstudio ignores).
    ExportNerfstudio {
        capture: PathBuf,
        #[arg(long, value_enum)]
        arm: train::ArmSet,
        #[command(flatten)]
        merge: train::RightToLeftArg,
        #[arg(long)]
        out: PathBuf,
        /// Leave out mask_path (train on whole images).
        #[arg(long)]
        no_masks: bool,
    },
    /// Train a splat model on a capture with the paper's masked losses (CPU, or a GPU with --backend).
    Train(train::TrainArgs),
    /// A capture to its 360° twin: a model per arm, the right aligned onto the left from the handover, the merged model from both (resumable).
    Twin(twin::TwinArgs),
    /// PSNR and SSIM of a splat model against a capture's views (whole and masked).
    Eval(train::EvalArgs),
    /// Render a splat model from orbiting cameras or a capture's cameras.
    Render(render::RenderArgs),
    /// Register SOURCE onto TARGET (point clouds or splat models) and write the transform.
    Align(registration::AlignArgs),
    /// Find the defective copy among splat models of three or more copies of a part, and show where.
    Inspect(inspect::InspectArgs),
    /// Make a good or defective copy of a splat model (for tests and benchmarks).
    MakeCopy(inspect::CopyArgs),
    /// Print the gripper poses of the scan trajectory a robot would execute.
    Plan {
        #[command(flatten)]
        plan: PlanArgs,
        #[arg(long)]
        json: bool,
    },
    /// Benchmarks (numbers go here, not in tests).
    Bench {
        #[command(subcommand)]
        which: BenchCommand,
    },
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Registration speed and accuracy: local ICP on frag_115 halves (against Open3D when given), global registration on random rotations.
    Registration(registration::BenchArgs),
    /// Mask accuracy (IoU against ground truth) and time per image on simulated captures.
    Mask(mask::BenchArgs),
    /// Inspection accuracy and time on triplets of generated good and defective copies.
    Inspect(inspect::BenchArgs),
    /// Inspection of independently scanned copies: simulated scans (a defect planted in one copy's mesh), a twin trained per scan, the three twins inspected.
    Scans(scan_bench::BenchArgs),
    /// Rasterizer time per view: CPU forward and forward+backward, GPU forward, on random scenes or models.
    Splat(splat_bench::BenchArgs),
    /// Time a full simulated capture: both arms' trajectories plus the empty pass.
    Sim {
        #[arg(long, default_value = "builtin:flashlight")]
        object: String,
        #[arg(long, default_value_t = 640)]
        width: u32,
        #[arg(long, default_value_t = 480)]
        height: u32,
        /// Directory for the capture (a temporary one if not given).
        #[arg(long)]
        out: Option<PathBuf>,
        #[arg(long)]
        json: bool,
    },
}

#[derive(Args, Clone)]
pub(crate) struct PlanArgs {
    /// Wrist angles per latitude.
    #[arg(long, default_value_t = 20)]
    wrist_angles: u32,
    /// Number of latitudes.
    #[arg(long, default_value_t = 5)]
    latitudes: u32,
    /// Lowest latitude, degrees.
    #[arg(long, default_value_t = -10.0, allow_hyphen_values = true)]
    latitude_min_deg: f64,
    /// Highest latitude, degrees.
    #[arg(long, default_value_t = 70.0, allow_hyphen_values = true)]
    latitude_max_deg: f64,
}

impl PlanArgs {
    pub(crate) fn config(&self) -> ScanPlanConfig {
        ScanPlanConfig {
            wrist_angles: self.wrist_angles,
            latitudes: self.latitudes,
            latitude_min_rad: self.latitude_min_deg.to_radians(),
            latitude_max_rad: self.latitude_max_deg.to_radians(),
            ..ScanPlanConfig::default()
        }
    }
}

#[derive(Args)]
struct SimArgs {
    /// `builtin:NAME` (flashlight, t_connector, wire_connector, l_bracket, remote) or a mesh file (.obj/.stl/.ply).
    #[arg(long, default_value = "builtin:flashlight")]
    object: String,
    /// Output capture directory.
    #[arg(long)]
    out: PathBuf,
    /// Metres per mesh unit (0.01 for a mesh in centimetres).
    #[arg(long)]
    object_scale: Option<f64>,
    /// Image width, pixels.
    #[arg(long, default_value_t = 640)]
    width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = 480)]
    height: u32,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// A planted defect: geometric:dent|bump|cut,size_mm=S or visual:scratch|tape,size_mm=S.
    #[arg(long)]
    defect: Option<String>,
    /// Rotation of the object at handover, degrees (the recorded handover stays as planned).
    #[arg(long, default_value_t = 0.0)]
    slip_deg: f64,
    /// Translation of the object at handover, millimetres.
    #[arg(long, default_value_t = 0.0)]
    slip_mm: f64,
    /// Supersampling per axis (2 = 4 samples per pixel).
    #[arg(long, default_value_t = 2)]
    supersample: u32,
    /// Sensor depth noise at 1 m, millimetres (grows with distance squared); 0 for clean depth.
    #[arg(long, default_value_t = 2.0)]
    depth_noise_mm_at_1m: f64,
    /// Directory with the YuMi gripper meshes (e.g. ../shared/data/grippers/yumi).
    #[arg(long)]
    gripper_dir: Option<PathBuf>,
    /// Camera distance from the object, metres (default: from the object's size).
    #[arg(long)]
    camera_distance_m: Option<f64>,
    /// Skip the empty-gripper calibration pass.
    #[arg(long)]
    no_empty_pass: bool,
    #[command(flatten)]
    plan: PlanArgs,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

impl SimArgs {
    fn config(&self) -> SimConfig {
        SimConfig {
            object: self.object.clone(),
            object_scale: self.object_scale,
            width: self.width,
            height: self.height,
            seed: self.seed,
            defect: self.defect.clone(),
            slip_deg: self.slip_deg,
            slip_mm: self.slip_mm,
            supersample: self.supersample,
            depth_noise_m_at_1m: self.depth_noise_mm_at_1m * 1e-3,
            plan: self.plan.config(),
            gripper_dir: self.gripper_dir.clone(),
            camera_distance_m: self.camera_distance_m,
            empty_pass: !self.no_empty_pass,
        }
    }
}

fn main() {
    quiet_headless_gpu_probe();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    if let Err(e) = run(Cli::parse()) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// Mesa's Vulkan device-select layer looks for the GPU driving a Wayland
/// display when the instance lists its devices; on a machine without a
/// session (no `XDG_RUNTIME_DIR`: servers, CI, containers) libwayland then
/// prints "error: XDG_RUNTIME_DIR is invalid or not set" twice, although
/// nothing is wrong and the GPU, if any, is used. There the layer has no
/// display to find, so it is turned off (`NODEVICE_SELECT`), unless the user
/// picked a device through it (`MESA_VK_DEVICE_SELECT`). Set before any
/// thread starts, as the environment must be.
fn quiet_headless_gpu_probe() {
    let unset = |key: &str| std::env::var_os(key).is_none();
    if unset("XDG_RUNTIME_DIR") && unset("MESA_VK_DEVICE_SELECT") && unset("NODEVICE_SELECT") {
        // SAFETY: called first thing in `main`, while this is the only thread.
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
}

/// A bar over `total` `items` (frames, views), labelled `what`.
fn progress_bar(total: usize, what: &str, items: &str) -> ProgressBar {
    let bar = ProgressBar::new(total as u64);
    bar.set_style(
        ProgressStyle::with_template(&format!(
            "{{msg}} [{{bar:40}}] {{pos}}/{{len}} {items}, {{elapsed_precise}} (eta {{eta}})"
        ))
        .unwrap()
        .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}

fn simulate(config: SimConfig, out: &Path) -> Result<omniscan_sim::SimSummary> {
    let sim = Simulation::new(config).context("cannot set up the simulation")?;
    let bar = progress_bar(sim.frames.len(), "simulating", "frames");
    let summary = sim
        .run(out, &|done, _| bar.set_position(done as u64))
        .with_context(|| format!("simulation into {} failed", out.display()))?;
    bar.finish_and_clear();
    Ok(summary)
}

fn merge_transform(merge: &serde_json::Value) -> Result<omniscan_core::Pose> {
    let rows: [[f64; 4]; 4] = serde_json::from_value(merge["right_to_left"].clone())?;
    Ok(omniscan_core::geometry::pose_from_rows(&rows)?)
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Demo { out, object } => {
            let capture_dir = out.join("capture");
            // A little slip at handover, as on the real robot, gives the merge step work to do.
            let config = SimConfig {
                object,
                slip_deg: 3.0,
                slip_mm: 2.0,
                ..SimConfig::default()
            };
            eprintln!(
                "1/6 simulating a bimanual scan of {} into {}",
                config.object,
                capture_dir.display()
            );
            let summary = simulate(config, &capture_dir)?;
            eprintln!(
                "    {} frames + {} empty-gripper frames in {:.1} s",
                summary.frames, summary.empty_frames, summary.seconds
            );
            eprintln!("2/6 validating the capture");
            let mut capture = Capture::load(&capture_dir)?;
            let s = capture.summary();
            eprintln!(
                "    {}x{}, {} left, {} right, {} empty frames, ground truth: {}",
                s.width, s.height, s.left_frames, s.right_frames, s.empty_frames, s.ground_truth
            );
            eprintln!(
                "3/6 masking every frame: kinematic gripper masks, object masks by the paper's scores"
            );
            let masker = omniscan_mask::pipeline::Masker::new(
                &capture,
                None,
                omniscan_mask::MaskSettings::default(),
            )?;
            let bar = progress_bar(capture.file.frames.len(), "masking", "frames");
            let masking = omniscan_mask::mask_capture(&mut capture, &masker, &|done, _| {
                bar.set_position(done as u64)
            })?;
            bar.finish_and_clear();
            let mask_eval = omniscan_mask::evaluate_capture(&capture)?;
            eprintln!(
                "    {:.1} s; against ground truth: object mIoU {:.4} / {:.4}, gripper mIoU {:.4} / {:.4} (left / right)",
                masking.seconds,
                mask_eval.object_miou.left.unwrap_or(f64::NAN),
                mask_eval.object_miou.right.unwrap_or(f64::NAN),
                mask_eval.gripper_miou.left.unwrap_or(f64::NAN),
                mask_eval.gripper_miou.right.unwrap_or(f64::NAN)
            );
            eprintln!(
                "4/6 merging the scans: right depth cloud onto the left from T_lh⁻¹·T_rh, refined by ICP and colored ICP"
            );
            let merge = registration::merge_scans(&capture)?;
            eprintln!(
                "    handover estimate off by {:.2}° / {:.2} mm; after {} {:.3}° / {:.2} mm (fitness {:.3})",
                merge["handover_error_deg"].as_f64().unwrap_or(0.0),
                merge["handover_error_mm"].as_f64().unwrap_or(0.0),
                merge["method"].as_str().unwrap_or(""),
                merge["refined_error_deg"].as_f64().unwrap_or(0.0),
                merge["refined_error_mm"].as_f64().unwrap_or(0.0),
                merge["fitness"].as_f64().unwrap_or(0.0)
            );
            eprintln!("5/6 exporting both arms, merged with the refined transform, for nerfstudio");
            let right_to_left = merge_transform(&merge)?;
            let export = export_nerfstudio(
                &capture,
                &out.join("nerfstudio"),
                ExportOptions {
                    views: ViewSet::Merged { right_to_left },
                    masks: true,
                },
            )?;
            eprintln!(
                "6/6 training the merged splat model on both arms (600 steps at 160x120 on the CPU; use `omniscan train` for full quality)"
            );
            let twin = train::train_merged(&capture, right_to_left, &out.join("twin.ply"), 600, 4)?;
            eprintln!(
                "    {} splats; held-out views: PSNR {:.2} dB, masked PSNR {:.2} dB",
                twin["splats"],
                twin["test"]["psnr"].as_f64().unwrap_or(f64::NAN),
                twin["test"]["psnr_masked"].as_f64().unwrap_or(f64::NAN)
            );
            println!(
                "{}",
                serde_json::to_string_pretty(&json!({
                    "capture": capture_dir,
                    "twin": twin,
                    "summary": s,
                    "masks": {
                        "object_miou": mask_eval.object_miou,
                        "gripper_miou": mask_eval.gripper_miou,
                        "object_min_iou": mask_eval.object_min_iou,
                        "gripper_min_iou": mask_eval.gripper_min_iou,
                        "seconds": masking.seconds,
                    },
                    "merge": {
                        "method": merge["method"],
                        "fitness": merge["fitness"],
                        "handover_error_deg": merge["handover_error_deg"],
                        "handover_error_mm": merge["handover_error_mm"],
                        "refined_error_deg": merge["refined_error_deg"],
                        "refined_error_mm": merge["refined_error_mm"],
                        "right_to_left": merge["right_to_left"],
                        "candidates": merge["candidates"].as_array().map(|all| all.iter().zip(merge["candidate_errors_deg"].as_array().cloned().unwrap_or_default()).map(|(c, e)| json!({"method": c["method"], "fitness": c["registration"]["fitness"], "inlier_rmse": c["registration"]["inlier_rmse"], "error_deg": e})).collect::<Vec<_>>()),
                    },
                    "nerfstudio": export.transforms,
                    "seconds": summary.seconds,
                }))?
            );
        }
        Command::Sim(args) => {
            let summary = simulate(args.config(), &args.out)?;
            if args.json {
                println!("{}", serde_json::to_string_pretty(&summary)?);
            } else {
                println!(
                    "wrote {} ({} frames, {} empty frames) in {:.1} s",
                    summary.capture.display(),
                    summary.frames,
                    summary.empty_frames,
                    summary.seconds
                );
            }
        }
        Command::Validate { capture, json } => {
            if let Some(photos) = train::photo_set_file(&capture) {
                let source = omniscan_splat::views::ViewSource::from_photo_set(&photos, 1)?;
                let summary = source
                    .check_photos()?
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
            let loaded = Capture::load(&capture)?;
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
        }
        Command::ExportNerfstudio {
            capture,
            arm,
            merge,
            out,
            no_masks,
        } => {
            let right_to_left = merge.read(arm)?;
            let loaded = Capture::load(&capture)?;
            let views = arm.view_set(&loaded, right_to_left);
            let summary = export_nerfstudio(
                &loaded,
                &out,
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
        }
        Command::Align(args) => registration::align(args)?,
        Command::Twin(args) => twin::run(args)?,
        Command::Inspect(args) => inspect::run(args)?,
        Command::Mask(args) => mask::run(args)?,
        Command::Bench {
            which: BenchCommand::Mask(args),
        } => mask::bench(args)?,
        Command::MakeCopy(args) => inspect::make_copy(args)?,
        Command::Bench {
            which: BenchCommand::Inspect(args),
        } => inspect::bench(args)?,
        Command::Bench {
            which: BenchCommand::Scans(args),
        } => scan_bench::bench(args)?,
        Command::Render(args) => render::run(args)?,
        Command::Bench {
            which: BenchCommand::Splat(args),
        } => splat_bench::bench(args)?,
        Command::Train(args) => train::run(args)?,
        Command::Eval(args) => train::eval(args)?,
        Command::Bench {
            which: BenchCommand::Registration(args),
        } => registration::bench(args)?,
        Command::Plan { plan, json } => {
            let config = plan.config();
            if let Err(e) = config.validate() {
                bail!("invalid scan plan: {e}");
            }
            let left = config.trajectory(Arm::Left);
            let right = config.trajectory(Arm::Right);
            if json {
                println!(
                    "{}",
                    serde_json::to_string_pretty(&json!({
                        "config": config,
                        "units": "metres and radians; poses are gripper (TCP) to world, 4x4 row-major",
                        "camera_to_world": omniscan_core::RigidTransform(config.camera_to_world()),
                        "left": left,
                        "right": right,
                        "left_handover": omniscan_core::RigidTransform(config.left_handover_pose()),
                        "right_handover": "computed from the regrasp chosen on the object at handover: T_rh = T_lh · T_lo · T_ro⁻¹",
                    }))?
                );
            } else {
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
            }
        }
        Command::Bench {
            which:
                BenchCommand::Sim {
                    object,
                    width,
                    height,
                    out,
                    json,
                },
        } => {
            let tmp;
            let dir = match out {
                Some(d) => d,
                None => {
                    tmp = tempfile::tempdir()?;
                    tmp.path().join("capture")
                }
            };
            let config = SimConfig {
                object,
                width,
                height,
                ..SimConfig::default()
            };
            let setup = Instant::now();
            let sim = Simulation::new(config)?;
            let setup_s = setup.elapsed().as_secs_f64();
            let bar = progress_bar(sim.frames.len(), "bench sim", "frames");
            let summary = sim.run(&dir, &|done, _| bar.set_position(done as u64))?;
            bar.finish_and_clear();
            let total = setup_s + summary.seconds;
            let threads = rayon::current_num_threads();
            if json {
                println!(
                    "{}",
                    serde_json::to_string_pretty(&json!({
                        "object": sim.config.object, "width": width, "height": height,
                        "frames": summary.frames, "empty_frames": summary.empty_frames,
                        "setup_s": setup_s, "render_and_write_s": summary.seconds, "total_s": total,
                        "seconds_per_frame": summary.seconds / (summary.frames + summary.empty_frames) as f64,
                        "threads": threads,
                    }))?
                );
            } else {
                println!(
                    "{}x{} {}: {} frames + {} empty frames in {:.1} s total ({:.1} s setup, {:.3} s per frame, {} threads)",
                    width,
                    height,
                    sim.config.object,
                    summary.frames,
                    summary.empty_frames,
                    total,
                    setup_s,
                    summary.seconds / (summary.frames + summary.empty_frames) as f64,
                    threads
                );
            }
        }
    }
    Ok(())
}
