//! `omniscan inspect`, `omniscan make-copy` and `omniscan bench inspect`:
//! defect inspection of splat models of several copies of a part, the
//! defect generator, and its benchmark on generated triplets.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::Point3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::json;

use omniscan_core::Pose;
use omniscan_inspect::closeup::CloseUpSettings;
use omniscan_inspect::generate::{CopySettings, DefectKind, good_copy, plant_defect};
use omniscan_inspect::report::write_report;
use omniscan_inspect::verdict::Verdict;
use omniscan_inspect::{InspectSettings, Inspection, inspect};
use omniscan_splat::Splats;
use omniscan_splat::ply::{read_splats, write_splats};

/// How the inspection matches the models' colours, for `inspect` and the
/// inspection benchmarks.
#[derive(clap::Args, Clone, Copy)]
pub struct ColourMatchArgs {
    /// Radius over which each model's surface colours are matched to the first model's before
    /// they are compared (lighting baked in per scan), millimetres; 0 compares raw colours.
    #[arg(long, default_value_t = 15.0)]
    pub photometric_radius_mm: f64,
}

impl ColourMatchArgs {
    /// The radius to match colours over, millimetres; `None`: raw colours.
    pub fn radius_mm(&self) -> Option<f64> {
        // NaN passes on, for the inspection to refuse.
        (self.photometric_radius_mm != 0.0).then_some(self.photometric_radius_mm)
    }
}

#[derive(clap::Args)]
pub struct InspectArgs {
    /// Splat models (3DGS PLY) of three or more copies of one part; all are aligned to the first.
    #[arg(required = true, num_args = 3..)]
    pub models: Vec<PathBuf>,
    /// Output directory (verdict.json, difference renders, defects.ply, report.html).
    #[arg(long)]
    pub out: PathBuf,
    /// Models known to be good, comma-separated (paths as given, or file names).
    #[arg(long, value_delimiter = ',')]
    pub reference: Option<Vec<String>>,
    /// Model units per metre (1 for omniscan's models; about 18 for the original Omni-Scan models).
    #[arg(long, default_value_t = 1.0)]
    pub units_per_metre: f64,
    /// Point differencing threshold, millimetres.
    #[arg(long, default_value_t = 4.5)]
    pub threshold_mm: f64,
    /// RGB distance (0-1 channels) above which a pixel differs.
    #[arg(long, default_value_t = 0.3)]
    pub colour_threshold: f64,
    /// Views rendered of every model.
    #[arg(long, default_value_t = 100)]
    pub views: usize,
    /// Render the cameras of this capture (the first model's scan, as the paper does) instead of
    /// views spread over a sphere: --views of them, taken evenly, each zoomed onto the part. The
    /// first model must be in the capture's frame (omniscan's twins are), at --units-per-metre.
    #[arg(long)]
    pub capture: Option<PathBuf>,
    /// Which of the capture's cameras, with --capture: one arm's (in its gripper's frame) or both
    /// (in the left gripper's frame, as `omniscan train --arm both`).
    #[arg(long, value_enum, default_value = "both", requires = "capture")]
    pub arm: crate::train::ArmSet,
    #[command(flatten)]
    pub merge: crate::train::RightToLeftArg,
    #[command(flatten)]
    pub colour: ColourMatchArgs,
    /// Render width, pixels.
    #[arg(long, default_value_t = 160)]
    pub width: u32,
    /// Render height, pixels.
    #[arg(long, default_value_t = 120)]
    pub height: u32,
    /// Seed of the registration's random choices.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Where the views are rendered: auto (a real GPU when there is one, else the CPU), cpu, or gpu.
    #[arg(long, default_value = "auto")]
    pub backend: omniscan_splat::backend::Backend,
    /// Look again, zoomed in (0.4 mm pixels), wherever the views show a
    /// little geometric difference on one copy: finds smaller geometric
    /// defects, and more differences between good copies too.
    #[arg(long)]
    pub close_up: bool,
    /// Print verdict.json instead of a summary.
    #[arg(long)]
    pub json: bool,
}

fn settings_from(args: &InspectArgs) -> Result<InspectSettings> {
    let references = match &args.reference {
        None => None,
        Some(names) => {
            let mut indices = Vec::new();
            for name in names {
                let found = args.models.iter().position(|m| {
                    m.as_os_str() == name.as_str()
                        || m.file_name().is_some_and(|f| f == name.as_str())
                });
                match found {
                    Some(i) => indices.push(i),
                    None => bail!("--reference {name}: not one of the models given"),
                }
            }
            Some(indices)
        }
    };
    let cameras = match &args.capture {
        None if args.merge.right_to_left.is_some() => {
            bail!("--right-to-left places a capture's cameras: give the capture (--capture)")
        }
        None => None,
        Some(path) => Some(capture_cameras(
            path,
            args.arm,
            args.merge.read(args.arm)?,
            args.units_per_metre,
        )?),
    };
    let mut settings = InspectSettings {
        units_per_metre: args.units_per_metre,
        threshold_mm: args.threshold_mm,
        colour_threshold: args.colour_threshold,
        views: args.views,
        cameras,
        photometric_radius_mm: args.colour.radius_mm(),
        width: args.width,
        height: args.height,
        backend: args.backend,
        references,
        close_up: args.close_up.then(CloseUpSettings::default),
        ..InspectSettings::default()
    };
    settings.align.seed = args.seed;
    Ok(settings)
}

/// The cameras of `path`'s capture (`arm`'s frames, in that set's frame,
/// both arms merged by `right_to_left` or the handover estimate),
/// camera-to-model with positions in model units.
fn capture_cameras(
    path: &Path,
    arm: crate::train::ArmSet,
    right_to_left: Option<Pose>,
    units_per_metre: f64,
) -> Result<omniscan_inspect::views::CameraSet> {
    let capture = omniscan_core::Capture::load(path)
        .with_context(|| format!("reading the capture {}", path.display()))?;
    let camera_to_model: Vec<Pose> =
        omniscan_core::poses::camera_views(&capture, arm.view_set(&capture, right_to_left))
            .into_iter()
            .map(|v| {
                let mut pose = v.camera_to_object;
                pose.translation.vector *= units_per_metre;
                pose
            })
            .collect();
    if camera_to_model.is_empty() {
        bail!(
            "the capture {} has no frames of the {arm:?} arm(s)",
            path.display()
        );
    }
    Ok(omniscan_inspect::views::CameraSet {
        camera_to_model,
        intrinsics: *capture.intrinsics(),
        source: format!(
            "{} ({} arms)",
            path.display(),
            format!("{arm:?}").to_lowercase()
        ),
    })
}

fn spinner(message: &str) -> ProgressBar {
    let bar = ProgressBar::new_spinner();
    bar.set_style(
        ProgressStyle::with_template("{spinner} {msg} [{elapsed}]").expect("valid template"),
    );
    bar.set_message(message.to_string());
    bar.enable_steady_tick(Duration::from_millis(120));
    bar
}

pub fn run(args: InspectArgs) -> Result<()> {
    let settings = settings_from(&args)?;
    let models: Vec<Splats> = args
        .models
        .iter()
        .map(|p| read_splats(p).with_context(|| format!("reading model {}", p.display())))
        .collect::<Result<_>>()?;
    let bar = spinner("aligning, rendering and comparing the models");
    let result = inspect(&models, &settings);
    bar.finish_and_clear();
    let inspection = result.map_err(|e| match e {
        omniscan_inspect::InspectError::Alignment {
            model,
            fitness,
            min_fitness,
        } => anyhow::anyhow!(
            "{} cannot be aligned to {}: best fitness {fitness:.3} is below {min_fitness} \
             (is it a model of the same part, at the same scale?)",
            args.models[model].display(),
            args.models[0].display()
        ),
        other => other.into(),
    })?;
    let verdict_path = write_report(&args.out, &inspection, &args.models, &settings)?;
    if args.json {
        let text = std::fs::read_to_string(&verdict_path)?;
        println!("{text}");
        return Ok(());
    }
    let v = &inspection.verdict;
    for (i, a) in inspection.alignments.iter().enumerate().skip(1) {
        println!(
            "aligned {} to {}: fitness {:.3}, RMSE {:.5} ({})",
            args.models[i].display(),
            args.models[0].display(),
            a.fitness,
            a.inlier_rmse,
            a.method
        );
    }
    match v.defective {
        Some(d) => println!(
            "defective: {} ({} defect, {:.1} mm² in {} significant region(s), the clearest {:.1} \
             times what the other copies differ by)",
            args.models[d].display(),
            v.defect_type,
            v.geometric_area_mm2[d] + v.visual_area_mm2[d],
            v.regions
                .iter()
                .filter(|r| r.significant && r.model == d)
                .count(),
            v.score
        ),
        None => println!("no defective model: the copies agree"),
    }
    println!(
        "report: {} ({:.1} s)",
        args.out.join("report.html").display(),
        inspection.timings.total
    );
    Ok(())
}

#[derive(clap::Args)]
pub struct CopyArgs {
    /// The splat model to copy (3DGS PLY).
    pub model: PathBuf,
    /// Where to write the copy.
    #[arg(long)]
    pub out: PathBuf,
    /// Plant a defect: dent, bump, remove, add, recolour, scratch or tape.
    #[arg(long)]
    pub defect: Option<String>,
    /// Defect size, millimetres.
    #[arg(long, default_value_t = 6.0)]
    pub size_mm: f64,
    /// Model units per metre.
    #[arg(long, default_value_t = 1.0)]
    pub units_per_metre: f64,
    /// Splat position noise, millimetres.
    #[arg(long, default_value_t = 0.3)]
    pub noise_mm: f64,
    /// Keep the model's pose (by default the copy is moved to a random pose).
    #[arg(long)]
    pub keep_pose: bool,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

pub fn make_copy(args: CopyArgs) -> Result<()> {
    let model = read_splats(&args.model)?;
    let (base, defect) = match &args.defect {
        Some(kind) => {
            let kind = DefectKind::parse(kind)?;
            let (m, d) = plant_defect(&model, kind, args.size_mm, args.units_per_metre, args.seed)?;
            (m, Some(d))
        }
        None => (model, None),
    };
    let (copy, pose) = good_copy(
        &base,
        args.units_per_metre,
        &CopySettings {
            seed: args.seed.wrapping_add(1),
            position_noise_mm: args.noise_mm,
            random_pose: !args.keep_pose,
            ..CopySettings::default()
        },
    )?;
    write_splats(&args.out, &copy)?;
    let defect_json = defect.map(|d| {
        let c = pose * Point3::from(d.centre);
        json!({"kind": d.kind, "size_mm": d.size_mm, "centre_in_copy": [c.x, c.y, c.z], "affected_splats": d.affected_splats})
    });
    println!(
        "{}",
        serde_json::to_string_pretty(&json!({
            "copy": args.out,
            "splats": copy.len(),
            "original_to_copy": omniscan_core::geometry::pose_to_rows(&pose),
            "defect": defect_json,
        }))?
    );
    Ok(())
}

#[derive(clap::Args)]
pub struct BenchArgs {
    /// Folder of splat models to make triplets from (e.g. ../shared/data/real-splats).
    #[arg(long)]
    pub splats: PathBuf,
    /// Their units per metre.
    #[arg(long, default_value_t = 18.0)]
    pub units_per_metre: f64,
    /// Further models in metres (e.g. twins trained on simulated captures).
    #[arg(long, num_args = 1..)]
    pub models: Vec<PathBuf>,
    /// Triplets with a defect (half geometric 4.5-10 mm, half visual 2-10 mm).
    #[arg(long, default_value_t = 40)]
    pub triplets: usize,
    /// Triplets of three good copies (false-positive check).
    #[arg(long, default_value_t = 6)]
    pub good_triplets: usize,
    #[arg(long, default_value_t = 100)]
    pub views: usize,
    #[command(flatten)]
    pub colour: ColourMatchArgs,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Keep each triplet's report here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Run only these triplets (0-based numbers, comma-separated); the
    /// others are generated but not inspected, so each one is the same
    /// triplet as in a full run.
    #[arg(long, value_delimiter = ',')]
    pub only: Option<Vec<usize>>,
    /// Inspect with the close look at small geometric differences.
    #[arg(long)]
    pub close_up: bool,
    #[arg(long)]
    pub json: bool,
}

pub(crate) const LABELS: [&str; 4] = ["A", "B", "C", "none"];

fn list_models(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "ply"))
        .collect();
    files.sort();
    if files.is_empty() {
        bail!("{}: no .ply models", dir.display());
    }
    Ok(files)
}

/// A benchmark's verdicts counted against the truth.
#[derive(Default)]
pub(crate) struct Score {
    /// confusion[truth][predicted], index 3 = none.
    pub confusion: [[usize; 4]; 4],
    pub correct: usize,
    pub located: usize,
    pub defect_trials: usize,
    pub total: usize,
}

impl Score {
    pub fn add(&mut self, truth: usize, predicted: usize, has_defect: bool, located: bool) {
        self.confusion[truth][predicted] += 1;
        self.correct += usize::from(predicted == truth);
        self.total += 1;
        if has_defect {
            self.defect_trials += 1;
            self.located += usize::from(located);
        }
    }
    pub fn accuracy(&self) -> f64 {
        self.correct as f64 / self.total.max(1) as f64
    }
    pub fn located_share(&self) -> f64 {
        self.located as f64 / self.defect_trials.max(1) as f64
    }
    /// The report's counts (`correct`, `accuracy`, `located`,
    /// `located_share`, `confusion`), for the caller to add its own keys to.
    pub fn summary(&self) -> serde_json::Value {
        json!({
            "correct": self.correct,
            "accuracy": self.accuracy(),
            "located": self.located,
            "located_share": self.located_share(),
            "confusion": self.confusion,
        })
    }
}

/// Each model's alignment error against the truth (degrees, millimetres),
/// where `poses[k]` takes a common frame into model k's (`units_per_metre`),
/// so model k's frame maps into the reference's by pose_0 · pose_k⁻¹.
pub(crate) fn alignment_errors(
    inspection: &Inspection,
    poses: &[Pose],
    units_per_metre: f64,
) -> Vec<[f64; 2]> {
    inspection
        .alignments
        .iter()
        .zip(poses)
        .map(|(a, pose)| {
            let truth = poses[0] * pose.inverse();
            let (angle, shift) = omniscan_core::geometry::pose_difference(&a.transform, &truth);
            [angle.to_degrees(), shift * 1000.0 / units_per_metre]
        })
        .collect()
}

/// Whether `verdict` names `defective` and one of its significant regions
/// reaches the true defect at `centre` (reference frame, model units): its
/// centroid within half its extent plus the defect's size.
pub(crate) fn defect_located(
    verdict: &Verdict,
    defective: usize,
    centre: &Point3<f64>,
    size_mm: f64,
    units_per_metre: f64,
) -> bool {
    verdict.defective == Some(defective)
        && verdict
            .regions
            .iter()
            .filter(|r| r.significant && r.model == defective)
            .any(|r| {
                let distance_mm =
                    (Point3::from(r.centroid) - centre).norm() * 1000.0 / units_per_metre;
                distance_mm <= 0.5 * r.extent_mm + size_mm
            })
}

pub fn bench(args: BenchArgs) -> Result<()> {
    let mut sources: Vec<(PathBuf, f64)> = list_models(&args.splats)?
        .into_iter()
        .map(|p| (p, args.units_per_metre))
        .collect();
    sources.extend(args.models.iter().map(|p| (p.clone(), 1.0)));
    let loaded: Vec<(PathBuf, f64, Splats)> = sources
        .into_iter()
        .map(|(p, u)| {
            let m = read_splats(&p).with_context(|| format!("reading {}", p.display()))?;
            Ok((p, u, m))
        })
        .collect::<Result<_>>()?;
    let all = args.triplets + args.good_triplets;
    let total = args
        .only
        .as_ref()
        .map_or(all, |only| only.iter().filter(|&&t| t < all).count());
    let bar = ProgressBar::new(total as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} {msg} [{elapsed}<{eta}]")
            .expect("valid template"),
    );
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed);
    let mut score = Score::default();
    let mut rows = Vec::new();
    let mut times = Vec::new();
    for t in 0..all {
        let (path, units, model) = &loaded[t % loaded.len()];
        let has_defect = t < args.triplets;
        let kind = if t % 2 == 0 {
            DefectKind::GEOMETRIC[(t / 2) % DefectKind::GEOMETRIC.len()]
        } else {
            DefectKind::VISUAL[(t / 2) % DefectKind::VISUAL.len()]
        };
        let size_mm = if kind.is_geometric() {
            rng.random_range(4.5..10.0)
        } else {
            rng.random_range(2.0..10.0)
        };
        let slot = rng.random_range(0..3usize);
        let seed = rng.random::<u64>();
        let mut copies = Vec::new();
        let mut poses = Vec::new();
        let mut planted = None;
        for k in 0..3 {
            let base = if has_defect && k == slot {
                // A site can be too sparse for a thin mark: try other sites.
                let mut attempt = 0;
                let (m, d) = loop {
                    match plant_defect(model, kind, size_mm, *units, seed.wrapping_add(attempt)) {
                        Ok(planted) => break planted,
                        Err(e) if attempt >= 5 => return Err(e.into()),
                        Err(_) => attempt += 1,
                    }
                };
                planted = Some(d);
                m
            } else {
                model.clone()
            };
            let (copy, pose) = good_copy(
                &base,
                *units,
                &CopySettings {
                    seed: seed.wrapping_add(k as u64 + 1),
                    ..CopySettings::default()
                },
            )?;
            copies.push(copy);
            poses.push(pose);
        }
        if args.only.as_ref().is_some_and(|only| !only.contains(&t)) {
            continue;
        }
        let settings = InspectSettings {
            units_per_metre: *units,
            views: args.views,
            photometric_radius_mm: args.colour.radius_mm(),
            close_up: args.close_up.then(CloseUpSettings::default),
            ..InspectSettings::default()
        };
        let name = path
            .file_stem()
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_default();
        bar.set_message(format!(
            "{name} {}",
            if has_defect { kind.name() } else { "good" }
        ));
        let started = Instant::now();
        let outcome = inspect(&copies, &settings);
        let seconds = started.elapsed().as_secs_f64();
        times.push(seconds);
        let truth = if has_defect { slot } else { 3 };
        let mut diagnostics = serde_json::Value::Null;
        let (predicted, found_type, is_located, error) = match &outcome {
            Ok(inspection) => {
                let v = &inspection.verdict;
                let alignment_error = alignment_errors(inspection, &poses, *units);
                diagnostics = json!({
                    "alignment_error_deg_mm": alignment_error,
                    "regions": v.regions.iter().take(8).collect::<Vec<_>>(),
                    "timings": inspection.timings,
                    "close_ups": inspection.close_ups.iter().map(|c| json!({
                        "model": c.model, "views": c.views.len(),
                        "side": c.views.first().map(|v| v.intrinsics.width),
                        "regions": c.regions.iter().map(|r| json!([r.model, r.area_mm2, r.significant])).collect::<Vec<_>>(),
                    })).collect::<Vec<_>>(),
                    "geometric_area_mm2": v.geometric_area_mm2,
                    "visual_area_mm2": v.visual_area_mm2,
                    "evidence_near_defect": planted.as_ref().map(|d| {
                        let centre = poses[0] * Point3::from(d.centre);
                        let reach = (d.size_mm + 3.0) * units / 1000.0;
                        inspection.pairs.iter().map(|p| {
                            let near = |e: &omniscan_inspect::differencing::Evidence| {
                                e.points.iter().filter(|q| (*q - centre).norm() <= reach).count()
                            };
                            let nearest_mm = |e: &omniscan_inspect::differencing::Evidence| {
                                e.points.iter().map(|q| (*q - centre).norm() * 1000.0 / units).fold(f64::INFINITY, f64::min)
                            };
                            json!({"pair": [p.a, p.b], "geometric": near(&p.geometric), "visual": near(&p.visual),
                                   "nearest_geometric_mm": nearest_mm(&p.geometric), "nearest_visual_mm": nearest_mm(&p.visual),
                                   "total_geometric": p.geometric.len(), "total_visual": p.visual.len()})
                        }).collect::<Vec<_>>()
                    }),
                });
                let predicted = v.defective.unwrap_or(3);
                let is_located = planted.as_ref().is_some_and(|d| {
                    defect_located(
                        v,
                        slot,
                        &(poses[0] * Point3::from(d.centre)),
                        d.size_mm,
                        *units,
                    )
                });
                if let Some(dir) = &args.out {
                    let names: Vec<PathBuf> = (0..3)
                        .map(|k| PathBuf::from(format!("{name}_{}", ["A", "B", "C"][k])))
                        .collect();
                    write_report(
                        &dir.join(format!("triplet_{t:03}")),
                        inspection,
                        &names,
                        &settings,
                    )?;
                }
                (predicted, v.defect_type.clone(), is_located, None)
            }
            Err(e) => (3, "error".to_string(), false, Some(e.to_string())),
        };
        score.add(truth, predicted, has_defect, is_located);
        rows.push(json!({
            "model": name,
            "defect": if has_defect { Some(kind.name()) } else { None },
            "size_mm": if has_defect { Some(size_mm) } else { None },
            "truth": LABELS[truth],
            "predicted": LABELS[predicted],
            "type": found_type,
            "located": is_located,
            "seconds": seconds,
            "error": error,
            "triplet": t,
            "seed": seed,
            "diagnostics": diagnostics,
        }));
        bar.inc(1);
    }
    bar.finish_and_clear();
    let mean_time = times.iter().sum::<f64>() / times.len().max(1) as f64;
    let max_time = times.iter().copied().fold(0.0, f64::max);
    if args.json {
        let mut report = score.summary();
        report["triplets"] = total.into();
        report["mean_seconds"] = mean_time.into();
        report["max_seconds"] = max_time.into();
        report["trials"] = rows.into();
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    for r in &rows {
        println!(
            "{:<18} {:<9} {:>5} truth {:<4} predicted {:<4} {:<9} located {:<5} {:.1} s{}",
            r["model"].as_str().unwrap_or(""),
            r["defect"].as_str().unwrap_or("-"),
            r["size_mm"]
                .as_f64()
                .map_or("-".into(), |s| format!("{s:.1}")),
            r["truth"].as_str().unwrap_or(""),
            r["predicted"].as_str().unwrap_or(""),
            r["type"].as_str().unwrap_or(""),
            r["located"].as_bool().unwrap_or(false),
            r["seconds"].as_f64().unwrap_or(0.0),
            r["error"]
                .as_str()
                .map_or(String::new(), |e| format!("  ERROR {e}"))
        );
    }
    println!("\nconfusion (rows = truth, columns = predicted):");
    println!("{:>6} {}", "", LABELS.map(|l| format!("{l:>6}")).join(""));
    for (i, row) in score.confusion.iter().enumerate() {
        println!(
            "{:>6} {}",
            LABELS[i],
            row.map(|c| format!("{c:>6}")).join("")
        );
    }
    println!(
        "correct {}/{total} ({:.1}%), defect inside a reported region {}/{} ({:.1}%), \
         {mean_time:.1} s per triplet (max {max_time:.1} s)",
        score.correct,
        100.0 * score.accuracy(),
        score.located,
        score.defect_trials,
        100.0 * score.located_share()
    );
    Ok(())
}
