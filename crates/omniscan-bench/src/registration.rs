//! `omniscan bench registration`: local ICP on halves of a real RGB-D
//! fragment against Open3D run in the same process tree, and global
//! registration on random rotations.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use nalgebra::{Translation3, Unit, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};

use omniscan_core::Pose;
use omniscan_core::geometry::{pose_difference, pose_from_rows, pose_to_rows};
use omniscan_register::PointCloud;
use omniscan_register::cloud::read_cloud;
use omniscan_register::fpfh::compute_fpfh;
use omniscan_register::global::{GlobalSettings, global_registration, median_spacing};
use omniscan_register::icp::{Criteria, Estimator, Kernel, Target, icp, multiscale_colored_icp};
use omniscan_register::preprocess::{estimate_normals, voxel_downsample};

#[derive(clap::Args)]
pub struct BenchArgs {
    /// The colored RGB-D fragment (shared/data/registration/frag_115.ply).
    #[arg(long)]
    pub frag: PathBuf,
    /// A directory of splat models (shared/data/real-splats) for the global test.
    #[arg(long)]
    pub splats: Option<PathBuf>,
    /// A Python interpreter with open3d 0.20 installed, for the baseline.
    #[arg(long)]
    pub open3d_python: Option<PathBuf>,
    /// Random rotations per dataset for the global test.
    #[arg(long, default_value_t = 20)]
    pub trials: usize,
    #[arg(long)]
    pub json: bool,
}

/// A random disjoint split of a cloud into two halves.
fn split(cloud: &PointCloud, seed: u64) -> (PointCloud, PointCloud) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (a, b): (Vec<usize>, Vec<usize>) = (0..cloud.len()).partition(|_| rng.random_bool(0.5));
    (cloud.select(&a), cloud.select(&b))
}

fn add_noise(cloud: &mut PointCloud, sigma: f64, seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut normal = || {
        let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    };
    for p in &mut cloud.points {
        *p += Vector3::new(normal(), normal(), normal()) * sigma;
    }
}

/// Timed calls per method, on both sides.
const TIMED_RUNS: usize = 11;

/// The median of `values` (not empty).
fn median(values: &[f64]) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    sorted[sorted.len() / 2]
}

/// The median time of `runs` calls of `f` after one untimed call (the first
/// call of a method pays for fresh memory pages: 15-25% more on `frag_115`),
/// and the last call's result.
fn median_of<T>(runs: usize, mut f: impl FnMut() -> Result<T>) -> Result<(f64, T)> {
    f()?;
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..runs {
        let t = Instant::now();
        last = Some(f()?);
        times.push(t.elapsed().as_secs_f64());
    }
    Ok((median(&times), last.context("no timed run")?))
}

/// Open3D's side of the benchmark: one Python process that reads the inputs
/// once and then times one call per request line (a method's name), so that
/// its calls can alternate with ours. On the shared 2-core VM the speed of
/// the same binary drifts by a third within a minute; timing all of one side
/// and then all of the other put that drift into the ratio (colored ICP's
/// swung 2.4-2.8x between two runs minutes apart).
const OPEN3D_SERVER: &str = r#"
import json, sys, time
import numpy as np
import open3d as o3d
reg = o3d.pipelines.registration
d = json.loads(sys.argv[1])
src = o3d.io.read_point_cloud(d["source"]); tgt = o3d.io.read_point_cloud(d["target"])
fp = o3d.io.read_point_cloud(d["fpfh_cloud"])
crit = reg.ICPConvergenceCriteria(1e-6, 1e-6, d["iterations"])
param = o3d.geometry.KDTreeSearchParamHybrid(radius=d["fpfh_radius"], max_nn=100)
eye = np.eye(4)
calls = {
    "colored": lambda: reg.registration_colored_icp(src, tgt, d["max_distance"], eye, reg.TransformationEstimationForColoredICP(), crit),
    "plane": lambda: reg.registration_icp(src, tgt, d["max_distance"], eye, reg.TransformationEstimationPointToPlane(), crit),
    "icp": lambda: reg.registration_icp(src, tgt, d["max_distance"], eye, reg.TransformationEstimationPointToPoint(), crit),
    "gicp": lambda: reg.registration_generalized_icp(src, tgt, d["max_distance"], eye, reg.TransformationEstimationForGeneralizedICP(), crit),
    "fpfh": lambda: reg.compute_fpfh_feature(fp, param),
}
print("ready", flush=True)
for line in sys.stdin:
    name = line.strip()
    t = time.perf_counter(); out = calls[name](); seconds = time.perf_counter() - t
    if name == "fpfh":
        res = {"seconds": seconds, "points": len(fp.points), "row_sum_mean": float(np.asarray(out.data).sum(axis=0).mean())}
    else:
        res = {"seconds": seconds, "transform": np.asarray(out.transformation).tolist(), "fitness": out.fitness, "inlier_rmse": out.inlier_rmse}
    print(json.dumps(res), flush=True)
"#;

/// A running [`OPEN3D_SERVER`].
struct Open3d {
    child: std::process::Child,
    requests: std::process::ChildStdin,
    answers: std::io::BufReader<std::process::ChildStdout>,
    python: PathBuf,
}

impl Open3d {
    fn start(python: &Path, input: &Value) -> Result<Open3d> {
        use std::process::{Command, Stdio};
        let mut child = Command::new(python)
            .arg("-c")
            .arg(OPEN3D_SERVER)
            .arg(input.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .with_context(|| format!("cannot run {}", python.display()))?;
        let requests = child.stdin.take().context("the Open3D baseline's input")?;
        let answers = std::io::BufReader::new(
            child
                .stdout
                .take()
                .context("the Open3D baseline's output")?,
        );
        let mut server = Open3d {
            child,
            requests,
            answers,
            python: python.to_path_buf(),
        };
        let ready = server.read_line()?;
        if ready.trim() != "ready" {
            bail!(
                "the Open3D baseline ({}) did not start: {ready}",
                python.display()
            );
        }
        Ok(server)
    }

    fn read_line(&mut self) -> Result<String> {
        use std::io::BufRead;
        let mut line = String::new();
        if self.answers.read_line(&mut line)? == 0 {
            let status = self.child.wait()?;
            bail!(
                "the Open3D baseline ({}) stopped ({status}); is open3d 0.20 installed for it? Its errors are above",
                self.python.display()
            );
        }
        Ok(line)
    }

    /// One timed call of `method` on Open3D's side: its seconds and results.
    fn time(&mut self, method: &str) -> Result<Value> {
        use std::io::Write;
        writeln!(self.requests, "{method}")
            .and_then(|()| self.requests.flush())
            .with_context(|| format!("the Open3D baseline ({}) stopped", self.python.display()))?;
        let line = self.read_line()?;
        serde_json::from_str(&line).with_context(|| format!("the Open3D baseline's answer {line}"))
    }
}

impl Drop for Open3d {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The processor's name, for the report: a speed ratio belongs to the machine it was measured on.
fn processor_name() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|info| {
            info.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|name| name.trim().to_string())
        })
        .unwrap_or_else(|| std::env::consts::ARCH.to_string())
}

pub fn bench(args: BenchArgs) -> Result<()> {
    let mut report = serde_json::Map::new();
    let frag = read_cloud(&args.frag)?;
    let centre = frag.centroid();
    let frag = frag.transformed(&Pose::translation(-centre.x, -centre.y, -centre.z));
    let spacing = median_spacing(&frag);
    let (mut target, mut source) = split(&frag, 1);
    add_noise(&mut source, 0.5 * spacing, 2);
    let perturb = Pose::from_parts(
        Translation3::new(0.01, 0.0, 0.0),
        UnitQuaternion::from_axis_angle(
            &Unit::new_normalize(Vector3::new(0.3, -0.5, 0.81)),
            10f64.to_radians(),
        ),
    );
    let mut source = source.transformed(&perturb);
    estimate_normals(&mut target, 4.0 * spacing, 30);
    estimate_normals(&mut source, 4.0 * spacing, 30);
    let tmp = tempfile::tempdir()?;
    let (src_path, tgt_path, fp_path) = (
        tmp.path().join("source.ply"),
        tmp.path().join("target.ply"),
        tmp.path().join("fpfh.ply"),
    );
    omniscan_register::cloud::write_ply(&src_path, &source)?;
    omniscan_register::cloud::write_ply(&tgt_path, &target)?;
    // Both sides read the same files, so they register identical inputs.
    let source = read_cloud(&src_path)?;
    let target = read_cloud(&tgt_path)?;
    let fpfh_voxel = 3.0 * spacing;
    let mut fp_cloud = voxel_downsample(&target, fpfh_voxel);
    estimate_normals(&mut fp_cloud, 2.0 * fpfh_voxel, 30);
    omniscan_register::cloud::write_ply(&fp_path, &fp_cloud)?;
    let fp_cloud = read_cloud(&fp_path)?;
    let max_distance = 0.016;
    let iterations = 30;
    let truth = perturb.inverse();
    let mut ours = serde_json::Map::new();
    // Both sides time each method in turn, one call each per round, in
    // alternating order, after one untimed call each (the first call in a
    // process pays for fresh memory pages: 15-25% more on `frag_115`, for
    // Open3D and omniscan alike).
    let mut open3d = match &args.open3d_python {
        Some(py) => Some(Open3d::start(
            py,
            &json!({"source": src_path, "target": tgt_path, "fpfh_cloud": fp_path, "max_distance": max_distance, "iterations": iterations, "fpfh_radius": 5.0 * fpfh_voxel}),
        )?),
        None => None,
    };
    let crit = Criteria {
        max_iteration: iterations,
        ..Criteria::default()
    };
    let estimators = [
        ("colored", Estimator::COLORED),
        ("plane", Estimator::PointToPlane),
        ("icp", Estimator::PointToPoint),
        ("gicp", Estimator::GENERALIZED),
    ];
    // The target's search structures are built inside the timing, as Open3D builds its k-d tree inside each call.
    let register = |est: Estimator| {
        icp(
            &source,
            &Target::new(&target),
            max_distance,
            &Pose::identity(),
            est,
            Kernel::L2,
            &crit,
        )
    };
    let fpfh = || compute_fpfh(&fp_cloud, 5.0 * fpfh_voxel, 100);
    let methods: Vec<&str> = estimators
        .iter()
        .map(|e| e.0)
        .chain(std::iter::once("fpfh"))
        .collect();
    // One of our calls of `method`: its seconds, and its result as JSON.
    let ours_once = |method: &str| -> Result<(f64, Value)> {
        let t = Instant::now();
        Ok(match estimators.iter().find(|e| e.0 == method) {
            Some(&(_, est)) => {
                let r = register(est)?;
                let seconds = t.elapsed().as_secs_f64();
                let (rot, trans) = pose_difference(&r.transformation, &truth);
                (
                    seconds,
                    json!({"fitness": r.fitness, "inlier_rmse": r.inlier_rmse, "rotation_error_deg": rot.to_degrees(), "translation_error_m": trans, "iterations": r.iterations, "transform": pose_to_rows(&r.transformation)}),
                )
            }
            None => {
                let f = fpfh();
                let seconds = t.elapsed().as_secs_f64();
                (
                    seconds,
                    json!({"points": fp_cloud.len(), "row_sum_mean": f.iter().map(|r| r.iter().sum::<f32>() as f64).sum::<f64>() / f.len() as f64}),
                )
            }
        })
    };
    let mut our_times: Vec<Vec<f64>> = vec![Vec::new(); methods.len()];
    let mut their_times: Vec<Vec<f64>> = vec![Vec::new(); methods.len()];
    let mut our_results = vec![Value::Null; methods.len()];
    let mut their_results = vec![Value::Null; methods.len()];
    for (m, method) in methods.iter().enumerate() {
        our_results[m] = ours_once(method)?.1;
        if let Some(o) = open3d.as_mut() {
            their_results[m] = o.time(method)?;
        }
    }
    for round in 0..TIMED_RUNS {
        for (m, method) in methods.iter().enumerate() {
            let mut ours_now = || -> Result<()> {
                let (t, r) = ours_once(method)?;
                our_times[m].push(t);
                our_results[m] = r;
                Ok(())
            };
            if round % 2 == 0 {
                ours_now()?;
            }
            if let Some(o) = open3d.as_mut() {
                let r = o.time(method)?;
                their_times[m].push(r["seconds"].as_f64().context("Open3D's seconds")?);
                their_results[m] = r;
            }
            if round % 2 == 1 {
                ours_now()?;
            }
        }
    }
    drop(open3d);
    for (m, method) in methods.iter().enumerate() {
        let mut result = our_results[m].clone();
        result["seconds"] = json!(median(&our_times[m]));
        ours.insert(method.to_string(), result);
    }
    // The error depends on which points land in which half: repeat over splits.
    let mut split_errors = Vec::new();
    for seed in 10..18u64 {
        let (mut t, s) = split(&frag, seed);
        let mut s = s;
        add_noise(&mut s, 0.5 * spacing, seed + 100);
        let s = s.transformed(&perturb);
        estimate_normals(&mut t, 4.0 * spacing, 30);
        let r = icp(
            &s,
            &Target::new(&t),
            max_distance,
            &Pose::identity(),
            Estimator::COLORED,
            Kernel::L2,
            &crit,
        )?;
        let (rot, trans) = pose_difference(&r.transformation, &truth);
        split_errors.push((rot.to_degrees(), trans * 1e3));
    }
    let rots: Vec<f64> = split_errors.iter().map(|e| e.0).collect();
    let trans: Vec<f64> = split_errors.iter().map(|e| e.1).collect();
    let largest = |v: &[f64]| v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    ours.insert("colored_over_splits".into(), json!({"splits": split_errors.len(), "median_rotation_error_deg": median(&rots), "max_rotation_error_deg": largest(&rots), "median_translation_error_mm": median(&trans), "max_translation_error_mm": largest(&trans)}));
    // Open3D's tutorial schedule for colored ICP, scaled to this cloud's spacing.
    let voxels = [8.0 * spacing, 4.0 * spacing, 2.0 * spacing];
    let (t, r) = median_of(TIMED_RUNS, || {
        Ok(multiscale_colored_icp(
            &source,
            &target,
            &Pose::identity(),
            &voxels,
            &[50, 30, 14],
        )?)
    })?;
    let (rot, trans) = pose_difference(&r.transformation, &truth);
    ours.insert("colored_multiscale".into(), json!({"seconds": t, "fitness": r.fitness, "inlier_rmse": r.inlier_rmse, "rotation_error_deg": rot.to_degrees(), "translation_error_m": trans, "voxels_m": voxels}));
    report.insert("processor".into(), json!(processor_name()));
    report.insert("frag_115_local".into(), json!({"points": [source.len(), target.len()], "spacing_m": spacing, "max_distance_m": max_distance, "iterations": iterations, "omniscan": ours}));

    let versus = match args.open3d_python {
        Some(_) => versus_open3d(
            &methods,
            &ours,
            &our_times,
            &their_times,
            &their_results,
            &truth,
        )?,
        None => json!("not measured: pass --open3d-python PATH (a Python with open3d 0.20)"),
    };
    report.insert("versus_open3d".into(), versus);
    report.insert("global".into(), global_trials(&args, &frag)?);
    let report = Value::Object(report);
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_bench(&report);
    }
    Ok(())
}

/// omniscan against Open3D, method by method: the median times, their
/// ratio and its spread over the rounds, and how far each side's transform
/// is from the truth and from the other's.
fn versus_open3d(
    methods: &[&str],
    ours: &serde_json::Map<String, Value>,
    our_times: &[Vec<f64>],
    their_times: &[Vec<f64>],
    their_results: &[Value],
    truth: &Pose,
) -> Result<Value> {
    let largest = |v: &[f64]| v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let mut table = Vec::new();
    for (m, &name) in methods.iter().enumerate() {
        let ours_t = ours[name]["seconds"].as_f64().unwrap_or(f64::NAN);
        let theirs_t = median(&their_times[m]);
        // Each round's ratio of two neighbouring calls: how far the machine's drift moved it.
        let ratios: Vec<f64> = their_times[m]
            .iter()
            .zip(&our_times[m])
            .map(|(theirs, ours)| theirs / ours)
            .collect();
        let mut row = json!({"method": name, "omniscan_s": ours_t, "open3d_s": theirs_t, "speedup": theirs_t / ours_t, "speedup_per_round": {"min": ratios.iter().copied().fold(f64::INFINITY, f64::min), "median": median(&ratios), "max": largest(&ratios)}});
        let o3d = &their_results[m];
        if name != "fpfh" {
            let rows: [[f64; 4]; 4] = serde_json::from_value(o3d["transform"].clone())?;
            let theirs = pose_from_rows(&rows)?;
            let (rot, trans) = pose_difference(&theirs, truth);
            let ours_rows: [[f64; 4]; 4] = serde_json::from_value(ours[name]["transform"].clone())?;
            let (drot, dtrans) = pose_difference(&pose_from_rows(&ours_rows)?, &theirs);
            row["open3d_rotation_error_deg"] = json!(rot.to_degrees());
            row["open3d_translation_error_m"] = json!(trans);
            row["open3d_fitness"] = o3d["fitness"].clone();
            row["omniscan_fitness"] = ours[name]["fitness"].clone();
            row["omniscan_rotation_error_deg"] = ours[name]["rotation_error_deg"].clone();
            row["difference_to_open3d_deg"] = json!(drot.to_degrees());
            row["difference_to_open3d_m"] = json!(dtrans);
        } else {
            row["open3d_row_sum"] = o3d["row_sum_mean"].clone();
            row["omniscan_row_sum"] = ours[name]["row_sum_mean"].clone();
        }
        table.push(row);
    }
    Ok(json!(table))
}

/// Global registration of disjoint halves under random rotations and
/// shifts, on `frag` and the splat models in `--splats`: the share of
/// trials within 0.5° and their times.
fn global_trials(args: &BenchArgs, frag: &PointCloud) -> Result<Value> {
    let mut global = Vec::new();
    let mut datasets: Vec<(String, PointCloud)> = vec![("frag_115".into(), frag.clone())];
    if let Some(dir) = &args.splats {
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "ply"))
            .collect();
        files.sort();
        for f in files {
            datasets.push((
                f.file_stem().unwrap().to_string_lossy().into(),
                read_cloud(&f)?,
            ));
        }
    }
    let mut all_ok = 0;
    let mut all = 0;
    for (name, cloud) in datasets.iter().filter(|_| args.trials > 0) {
        let (target, half) = split(cloud, 3);
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut errors = Vec::new();
        let mut times = Vec::new();
        let extent = cloud.extent();
        for trial in 0..args.trials {
            let axis = Vector3::new(
                rng.random::<f64>() - 0.5,
                rng.random::<f64>() - 0.5,
                rng.random::<f64>() - 0.5,
            );
            let angle = rng.random::<f64>() * std::f64::consts::PI;
            let shift = Vector3::new(
                rng.random::<f64>() - 0.5,
                rng.random::<f64>() - 0.5,
                rng.random::<f64>() - 0.5,
            ) * extent;
            let truth = Pose::from_parts(
                Translation3::from(shift),
                UnitQuaternion::from_axis_angle(&Unit::new_normalize(axis), angle),
            );
            let source = half.transformed(&truth.inverse());
            let t = Instant::now();
            let result = global_registration(
                &source,
                &target,
                &GlobalSettings {
                    seed: trial as u64,
                    ..GlobalSettings::default()
                },
            );
            times.push(t.elapsed().as_secs_f64());
            match result {
                Ok(r) => errors.push(
                    pose_difference(&r.best.registration.transformation, &truth)
                        .0
                        .to_degrees(),
                ),
                Err(e) => {
                    eprintln!("global {name} trial {trial}: {e}");
                    errors.push(180.0);
                }
            }
        }
        let ok = errors.iter().filter(|&&e| e <= 0.5).count();
        all_ok += ok;
        all += errors.len();
        let max_t = times.iter().copied().fold(0.0, f64::max);
        let mut sorted = errors.clone();
        sorted.sort_by(f64::total_cmp);
        global.push(json!({"data": name, "points": cloud.len(), "trials": errors.len(), "within_0_5_deg": ok, "median_error_deg": sorted[sorted.len() / 2], "max_error_deg": sorted.last(), "max_seconds": max_t, "mean_seconds": times.iter().sum::<f64>() / times.len() as f64}));
        eprintln!(
            "global {name}: {ok}/{} within 0.5°, max {:.2} s",
            errors.len(),
            max_t
        );
    }
    Ok(json!({"per_dataset": global, "success_rate": all_ok as f64 / all.max(1) as f64}))
}

fn print_bench(report: &Value) {
    let local = &report["frag_115_local"]["omniscan"];
    println!(
        "frag_115 halves, 10°/1 cm perturbation, {} iterations:",
        report["frag_115_local"]["iterations"]
    );
    for name in ["colored", "colored_multiscale", "plane", "icp", "gicp"] {
        let r = &local[name];
        println!(
            "  {name:18} {:.3} s  fitness {:.4}  rotation error {:.4}°  translation error {:.2} mm",
            r["seconds"].as_f64().unwrap_or(0.0),
            r["fitness"].as_f64().unwrap_or(0.0),
            r["rotation_error_deg"].as_f64().unwrap_or(0.0),
            r["translation_error_m"].as_f64().unwrap_or(0.0) * 1e3
        );
    }
    println!(
        "  fpfh               {:.3} s  ({} points)",
        local["fpfh"]["seconds"].as_f64().unwrap_or(0.0),
        local["fpfh"]["points"]
    );
    let o = &local["colored_over_splits"];
    println!(
        "  colored ICP over {} other random splits: rotation error median {:.4}° (max {:.4}°), translation median {:.2} mm (max {:.2} mm)",
        o["splits"],
        o["median_rotation_error_deg"].as_f64().unwrap_or(0.0),
        o["max_rotation_error_deg"].as_f64().unwrap_or(0.0),
        o["median_translation_error_mm"].as_f64().unwrap_or(0.0),
        o["max_translation_error_mm"].as_f64().unwrap_or(0.0)
    );
    match &report["versus_open3d"] {
        Value::Array(rows) => {
            println!(
                "versus Open3D on {} (same inputs, same run; calls alternate, {TIMED_RUNS} rounds after one untimed call each; medians):",
                report["processor"].as_str().unwrap_or("this machine")
            );
            println!(
                "  {:8} {:>10} {:>10} {:>8}  per round (min-max)",
                "method", "omniscan s", "open3d s", "speedup"
            );
            for r in rows {
                let round = &r["speedup_per_round"];
                println!(
                    "  {:8} {:>10.3} {:>10.3} {:>7.2}x  {:.2}-{:.2}x",
                    r["method"].as_str().unwrap_or(""),
                    r["omniscan_s"].as_f64().unwrap_or(0.0),
                    r["open3d_s"].as_f64().unwrap_or(0.0),
                    r["speedup"].as_f64().unwrap_or(0.0),
                    round["min"].as_f64().unwrap_or(0.0),
                    round["max"].as_f64().unwrap_or(0.0)
                );
            }
        }
        other => println!("versus Open3D: {other}"),
    }
    println!("global registration (rotation error after ICP <= 0.5°):");
    if let Value::Array(rows) = &report["global"]["per_dataset"] {
        for r in rows {
            println!(
                "  {:20} {}/{}  median {:.3}°  max {:.2}°  max {:.2} s",
                r["data"].as_str().unwrap_or(""),
                r["within_0_5_deg"],
                r["trials"],
                r["median_error_deg"].as_f64().unwrap_or(0.0),
                r["max_error_deg"].as_f64().unwrap_or(0.0),
                r["max_seconds"].as_f64().unwrap_or(0.0)
            );
        }
    }
    if report["global"]["per_dataset"]
        .as_array()
        .is_some_and(|r| !r.is_empty())
    {
        println!(
            "  success rate {:.1}%",
            report["global"]["success_rate"].as_f64().unwrap_or(0.0) * 100.0
        );
    } else {
        println!("  not run (--trials 0)");
    }
}
