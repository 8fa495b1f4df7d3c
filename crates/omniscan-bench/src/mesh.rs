//! `omniscan bench mesh`: how accurate a twin's mesh is, in millimetres.
//!
//! Per object: a simulated scan (both arms), a merged twin trained on it
//! (the simulator's masks, the robot's handover estimate, as `bench
//! scans`), `omniscan asset`'s mesh of the twin, and, as the baseline a
//! user would otherwise run, a TSDF of the capture's own sensor depth maps
//! (object pixels only, same fusion and extraction). Both are scored
//! against the simulator's true mesh placed by `gt.object_to_left_gripper`
//! (the twin's frame): Chamfer distance, F-score at 1 and 2 mm, volume
//! error. Captures and twins are kept under `--out` and reused.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde_json::json;

use omniscan_core::capture::Capture;
use omniscan_core::image_io::{read_depth, read_mask};
use omniscan_core::poses::{ViewSet, camera_views};
use omniscan_mesh::TriMesh;
use omniscan_mesh::accuracy::{Accuracy, compare};
use omniscan_mesh::fusion::{DepthView, Grid, Sample, fuse};
use omniscan_mesh::topology::largest_component;
use omniscan_pipeline::geometry::{AssetSettings, asset};
use omniscan_sim::SimConfig;
use omniscan_splat::raster::Camera;

#[derive(clap::Args)]
pub struct BenchArgs {
    /// Where captures, twins and meshes are kept (reused on a second run).
    #[arg(long)]
    pub out: PathBuf,
    /// Objects: built-in names, or mesh files (e.g. ../shared/data/objects/*/*.obj).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "flashlight,t_connector,wire_connector,l_bracket,remote"
    )]
    pub objects: Vec<String>,
    /// Training steps of each twin.
    #[arg(long, default_value_t = 3000)]
    pub steps: usize,
    /// Training image downscale.
    #[arg(long, default_value_t = 2)]
    pub downscale: u32,
    /// Points sampled on each surface for the scores.
    #[arg(long, default_value_t = 200_000)]
    pub samples: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub asset: AssetSettings,
    #[arg(long)]
    pub json: bool,
}

fn object_spec(object: &str) -> String {
    if Path::new(object).exists() {
        object.to_string()
    } else {
        format!("builtin:{object}")
    }
}

fn object_label(object: &str) -> String {
    let path = Path::new(object);
    if !path.exists() {
        return object.to_string();
    }
    let stem = path
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("object");
    match (
        stem,
        path.parent()
            .and_then(|p| p.file_name())
            .and_then(|s| s.to_str()),
    ) {
        ("model" | "textured" | "mesh", Some(parent)) => parent.to_string(),
        _ => stem.to_string(),
    }
}

/// The simulated capture and the twin trained on it, made once.
fn capture_and_twin(dir: &Path, object: &str, args: &BenchArgs) -> Result<(Capture, PathBuf)> {
    let capture_dir = dir.join("capture");
    if !capture_dir.join("capture.json").exists() {
        let config = SimConfig {
            object: object_spec(object),
            seed: args.seed,
            empty_pass: false,
            ..SimConfig::default()
        };
        omniscan_pipeline::simulate::simulate_config(
            config,
            &capture_dir,
            &omniscan_pipeline::Bars::new(),
        )?;
    }
    let capture = Capture::load(&capture_dir)?;
    let model = dir.join(format!("twin-{}-{}.ply", args.steps, args.downscale));
    if !model.exists() {
        let ViewSet::Merged { right_to_left } = ViewSet::merged_from_handover(&capture) else {
            unreachable!("merged_from_handover gives a merged set")
        };
        omniscan_pipeline::demo::train_merged(
            &capture,
            right_to_left,
            &model,
            (args.steps, args.downscale, true),
            &omniscan_pipeline::Bars::new(),
        )
        .with_context(|| format!("training {}", model.display()))?;
    }
    Ok((capture, model))
}

/// The simulator's mesh of the object in the twin's (left gripper's) frame.
pub fn true_mesh(capture: &Capture) -> Result<TriMesh> {
    let gt = capture
        .file
        .gt
        .as_ref()
        .context("the capture has no ground truth")?;
    let object = gt.extra.get("object").context("gt.object missing")?;
    let source = object["source"]
        .as_str()
        .context("gt.object.source missing")?;
    let scale = object["scale_m_per_unit"].as_f64();
    let sim = omniscan_sim::simulate::load_object(source, scale)?;
    let mesh = TriMesh {
        positions: sim.mesh.positions.iter().map(|p| [p.x, p.y, p.z]).collect(),
        colors: vec![[0.5; 3]; sim.mesh.positions.len()],
        unseen: vec![false; sim.mesh.triangles.len()],
        triangles: sim.mesh.triangles.clone(),
    };
    Ok(mesh.transformed(&gt.object_to_left_gripper.0))
}

/// A TSDF of the capture's sensor depth (object pixels by the simulator's
/// masks; other measured pixels are empty space up to their depth).
fn sensor_depth_mesh(capture: &Capture, voxel_m: f64, truth: &TriMesh) -> Result<TriMesh> {
    let intrinsics = capture.intrinsics();
    let set = ViewSet::merged_from_handover(capture);
    let mut views = Vec::new();
    for view in camera_views(capture, set) {
        let frame = &capture.file.frames[view.frame_index];
        let (Some(depth), Some(mask)) = (
            frame.depth_path.as_ref(),
            frame.gt.as_ref().and_then(|g| g.object_mask_path.as_ref()),
        ) else {
            bail!(
                "{}: a frame lacks sensor depth or a true object mask",
                capture.dir.display()
            );
        };
        let depth = read_depth(&capture.resolve(depth))?;
        let mask = read_mask(&capture.resolve(mask))?;
        let samples = (0..depth.height)
            .flat_map(|y| (0..depth.width).map(move |x| (x, y)))
            .map(|(x, y)| match (depth.metres(x, y), mask.get(x, y)) {
                (Some(z), true) => Sample::Surface(z as f32),
                (Some(z), false) => Sample::EmptyUntil(z as f32),
                (None, _) => Sample::EmptyUntil(0.0),
            })
            .collect();
        views.push(DepthView {
            camera: Camera::from_pose(&view.camera_to_object, intrinsics),
            samples,
            rgb: None,
        });
    }
    let (lo, hi) = truth.bounds();
    let margin = 0.01;
    let grid = Grid::covering(
        lo.map(|c| c as f64 - margin),
        hi.map(|c| c as f64 + margin),
        voxel_m,
    );
    // Plain TSDF fusion, as a user would run on sensor depth.
    let tsdf = fuse(grid, 3.0 * voxel_m, &views, 2.0);
    Ok(largest_component(&omniscan_mesh::extract::extract(&tsdf)).0)
}

/// The signed distance (positive outside) of the twin's opaque splat
/// centres from the true surface: median and 90th percentile of |d|, mm.
fn splat_offsets(model: &Path, truth: &TriMesh) -> Result<(f64, f64)> {
    let splats = omniscan_splat::ply::read_splats(model)?;
    let surface = omniscan_mesh::accuracy::Surface::new(truth)?;
    let mut signed: Vec<f64> = splats
        .means
        .iter()
        .zip(&splats.opacity_logits)
        .filter(|(_, o)| **o > 0.0)
        .map(|(m, _)| surface.signed_distance(*m).0 as f64 * 1e3)
        .collect();
    if signed.is_empty() {
        bail!("{}: no opaque splats", model.display());
    }
    signed.sort_by(f64::total_cmp);
    let median = signed[signed.len() / 2];
    let mut magnitudes: Vec<f64> = signed.iter().map(|d| d.abs()).collect();
    magnitudes.sort_by(f64::total_cmp);
    Ok((median, magnitudes[magnitudes.len() * 9 / 10]))
}

fn row(object: &str, method: &str, a: &Accuracy, seconds: f64) -> serde_json::Value {
    json!({"object": object, "method": method, "accuracy": a, "seconds": seconds})
}

pub fn bench(args: BenchArgs) -> Result<()> {
    let mut rows = Vec::new();
    println!(
        "{:<24} {:<14} {:>8} {:>8} {:>8} {:>7} {:>7} {:>8} {:>7}",
        "object", "method", "chamfer", "acc", "comp", "F@1mm", "F@2mm", "vol err", "s"
    );
    for object in &args.objects {
        let label = object_label(object);
        let dir = args.out.join(&label);
        let (capture, model) = capture_and_twin(&dir, object, &args)?;
        let truth = true_mesh(&capture)?;
        let start = Instant::now();
        let report = asset(
            &model,
            &dir.join("asset"),
            &args.asset,
            &omniscan_pipeline::Bars::new(),
        )?;
        let asset_s = start.elapsed().as_secs_f64();
        let ours = omniscan_mesh::files::read_ply_mesh(&report.mesh.files.ply)?;
        let (splat_median_mm, splat_p90_mm) = splat_offsets(&model, &truth)?;
        println!(
            "{label:<24} opaque splat centres from the true surface: median {splat_median_mm:+.3} mm, 90% within {splat_p90_mm:.3} mm"
        );
        let ours_acc = compare(&ours, &truth, args.samples)?;
        let start = Instant::now();
        let voxel_m = report.mesh.stats.voxel_mm * 1e-3;
        let baseline = sensor_depth_mesh(&capture, voxel_m, &truth)?;
        let baseline_s = start.elapsed().as_secs_f64();
        let base_acc = compare(&baseline, &truth, args.samples)?;
        for (method, a, s) in [
            ("twin mesh", &ours_acc, asset_s),
            ("sensor TSDF", &base_acc, baseline_s),
        ] {
            println!(
                "{:<24} {:<14} {:>8.3} {:>8.3} {:>8.3} {:>7.3} {:>7.3} {:>8} {:>7.1}",
                label,
                method,
                a.chamfer_mm,
                a.accuracy_mm,
                a.completeness_mm,
                a.f_score_1mm,
                a.f_score_2mm,
                a.volume_error_percent
                    .map_or("open GT".into(), |v| format!("{v:.1}%")),
                s
            );
            rows.push(row(&label, method, a, s));
        }
        rows.push(json!({"object": label, "method": "asset report", "report": report.mesh.stats,
            "mass_kg": report.mass.mass_kg, "hulls": report.collision_meshes.len(), "seconds": report.seconds}));
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
    }
    Ok(())
}
