//! `omniscan bench inspect`: inspection accuracy and time on triplets of
//! generated good and defective copies of splat models.

use std::path::{Path, PathBuf};
use std::time::Instant;

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
use omniscan_pipeline::inspect::ColourMatch;
use omniscan_splat::Splats;
use omniscan_splat::ply::read_splats;

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
    pub colour: ColourMatch,
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
                        &copies,
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
