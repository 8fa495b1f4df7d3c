//! Defect inspection of splat models of three or more copies of a part
//! (the paper's "Defect inspection": alignment, pixel and point
//! differencing, a located verdict and an HTML report), and the copy maker
//! that plants defects for tests and benchmarks.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use nalgebra::Point3;
use serde::{Deserialize, Serialize};

use omniscan_core::Pose;
use omniscan_inspect::InspectSettings;
use omniscan_inspect::closeup::CloseUpSettings;
use omniscan_inspect::generate::{CopySettings, DefectKind, good_copy, plant_defect};
use omniscan_inspect::report::write_report;
use omniscan_splat::Splats;
use omniscan_splat::ply::{read_splats, write_splats};

use crate::Progress;
use crate::settings::default_from_flags;
use crate::views::{ArmSet, Merge};

/// How the inspection matches the models' colours.
#[derive(clap::Args, Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ColourMatch {
    /// Radius over which each model's surface colours are matched to the first model's before
    /// they are compared (lighting baked in per scan), millimetres; 0 compares raw colours.
    #[arg(long, default_value_t = InspectSettings::default().photometric_radius_mm.unwrap_or(0.0))]
    pub photometric_radius_mm: f64,
}

impl ColourMatch {
    /// The radius to match colours over, millimetres; `None`: raw colours.
    pub fn radius_mm(&self) -> Option<f64> {
        // NaN passes on, for the inspection to refuse.
        (self.photometric_radius_mm != 0.0).then_some(self.photometric_radius_mm)
    }
}

/// Everything `inspect` can be told besides the models and output folder.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct InspectionSettings {
    /// Models known to be good, comma-separated (paths as given, or file names).
    #[arg(long, value_delimiter = ',')]
    pub reference: Option<Vec<String>>,
    /// Model units per metre (1 for omniscan's models; about 18 for the original Omni-Scan models).
    #[arg(long, default_value_t = InspectSettings::default().units_per_metre)]
    pub units_per_metre: f64,
    /// Point differencing threshold, millimetres (the paper's 4.5).
    #[arg(long, default_value_t = InspectSettings::default().threshold_mm)]
    pub threshold_mm: f64,
    /// RGB distance (0-1 channels) above which a pixel differs.
    #[arg(long, default_value_t = InspectSettings::default().colour_threshold)]
    pub colour_threshold: f64,
    /// Views rendered of every model (the paper's 100).
    #[arg(long, default_value_t = InspectSettings::default().views)]
    pub views: usize,
    /// Render the cameras of this capture (the first model's scan, as the paper does) instead of
    /// views spread over a sphere: --views of them, taken evenly, each zoomed onto the part. The
    /// first model must be in the capture's frame (omniscan's twins are), at --units-per-metre.
    #[arg(long)]
    pub capture: Option<PathBuf>,
    /// Which of the capture's cameras, with --capture: one arm's (in its gripper's frame) or both
    /// (in the left gripper's frame, as `omniscan train --arm both`).
    #[arg(long, value_enum, default_value = "both", requires = "capture")]
    pub arm: ArmSet,
    #[command(flatten)]
    #[serde(flatten)]
    pub merge: Merge,
    #[command(flatten)]
    #[serde(flatten)]
    pub colour: ColourMatch,
    /// Render width, pixels.
    #[arg(long, default_value_t = InspectSettings::default().width)]
    pub width: u32,
    /// Render height, pixels.
    #[arg(long, default_value_t = InspectSettings::default().height)]
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
    /// Skip meshing the copies for their surface deviation in millimetres
    /// (deviation_K.ply; regions where it passes 1 mm are typed geometric).
    #[arg(long)]
    pub no_surface_deviation: bool,
}

default_from_flags!(InspectionSettings);

impl InspectionSettings {
    /// The inspection crate's settings for these `models`.
    pub fn resolve(&self, models: &[PathBuf]) -> Result<InspectSettings> {
        let references = match &self.reference {
            None => None,
            Some(names) => Some(reference_indices(names, models)?),
        };
        let cameras = match &self.capture {
            None if self.merge.right_to_left.is_some() => {
                bail!("--right-to-left places a capture's cameras: give the capture (--capture)")
            }
            None => None,
            Some(path) => Some(capture_cameras(
                path,
                self.arm,
                self.merge.read(self.arm)?,
                self.units_per_metre,
            )?),
        };
        let mut settings = InspectSettings {
            units_per_metre: self.units_per_metre,
            threshold_mm: self.threshold_mm,
            colour_threshold: self.colour_threshold,
            views: self.views,
            cameras,
            photometric_radius_mm: self.colour.radius_mm(),
            width: self.width,
            height: self.height,
            backend: self.backend,
            references,
            close_up: self.close_up.then(CloseUpSettings::default),
            ..InspectSettings::default()
        };
        settings.align.seed = self.seed;
        Ok(settings)
    }
}

/// How many views may be compared at once in the memory available (each
/// holds a render of every model), or an error naming a size that fits.
fn inspect_memory_check(settings: &InspectSettings, models: usize) -> Result<usize> {
    use crate::memory::{RENDER_BYTES_PER_PIXEL, side_that_fits};
    let (w, h) = (settings.width, settings.height);
    let per_pixel = RENDER_BYTES_PER_PIXEL * models as u64;
    crate::memory::views_at_once(
        &format!("comparing {models} models' {w}x{h} renders of a view"),
        u64::from(w) * u64::from(h) * per_pixel,
        rayon::current_num_threads(),
        crate::memory::available(),
        |available| {
            let (fw, fh) = side_that_fits(w, h, per_pixel, available);
            format!("--width {fw} --height {fh} fits")
        },
    )
}

fn reference_indices(names: &[String], models: &[PathBuf]) -> Result<Vec<usize>> {
    names
        .iter()
        .map(|name| {
            models
                .iter()
                .position(|m| {
                    m.as_os_str() == name.as_str()
                        || m.file_name().is_some_and(|f| f == name.as_str())
                })
                .with_context(|| format!("--reference {name}: not one of the models given"))
        })
        .collect()
}

/// The cameras of `path`'s capture (`arm`'s frames, in that set's frame,
/// both arms merged by `right_to_left` or the handover estimate),
/// camera-to-model with positions in model units.
fn capture_cameras(
    path: &Path,
    arm: ArmSet,
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

/// How one model was aligned to the first.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelAlignment {
    pub model: PathBuf,
    pub fitness: f64,
    pub inlier_rmse: f64,
    pub method: String,
}

/// What [`inspect`] found; `verdict.json` has every figure.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InspectReport {
    pub verdict: PathBuf,
    pub report: PathBuf,
    /// The defective model; `None`: the copies agree.
    pub defective: Option<PathBuf>,
    pub defect_type: String,
    /// The defective model's differing area, square millimetres.
    pub area_mm2: f64,
    pub significant_regions: usize,
    /// The clearest region's difference over what the other copies differ by.
    pub score: f64,
    /// Every model but the first, aligned to it.
    pub alignments: Vec<ModelAlignment>,
    /// Every model but the first: its surface's deviation from the first's
    /// (empty with `no_surface_deviation`; also in surface_deviation.json).
    pub surface_deviation: Vec<crate::deviation::CopyDeviation>,
    pub seconds: f64,
}

/// Inspects `models` (three or more copies), writes `verdict.json`, the
/// renders and `report.html` into `out`.
pub fn inspect(
    models: &[PathBuf],
    out: &Path,
    settings: &InspectionSettings,
    progress: &dyn Progress,
) -> Result<InspectReport> {
    let resolved = settings.resolve(models)?;
    let splats: Vec<Splats> = models
        .iter()
        .map(|p| read_splats(p).with_context(|| format!("reading model {}", p.display())))
        .collect::<Result<_>>()?;
    let at_once = inspect_memory_check(&resolved, splats.len())?;
    progress.start("aligning, rendering and comparing the models", 0, "");
    let result =
        crate::memory::with_threads(at_once, || omniscan_inspect::inspect(&splats, &resolved))?;
    progress.finish();
    let mut inspection = result.map_err(|e| match e {
        omniscan_inspect::InspectError::Alignment {
            model,
            fitness,
            min_fitness,
        } => anyhow::anyhow!(
            "{} cannot be aligned to {}: best fitness {fitness:.3} is below {min_fitness} \
             (is it a model of the same part, at the same scale?)",
            models[model].display(),
            models[0].display()
        ),
        other => other.into(),
    })?;
    let _lock = omniscan_core::lock::OutputLock::folder(out, "inspect")?;
    let deviations = if settings.no_surface_deviation {
        Vec::new()
    } else {
        progress.start("meshing the copies for their surface deviation", 0, "");
        let d = crate::deviation::surface_deviation(
            &splats,
            &mut inspection,
            resolved.units_per_metre,
            out,
        );
        progress.finish();
        // The verdict stands without it: say why it is missing.
        d.unwrap_or_else(|e| {
            tracing::warn!("no surface deviation: {e:#}");
            progress.note(&format!("no surface deviation: {e:#}"));
            Vec::new()
        })
    };
    let verdict = write_report(out, &inspection, &splats, models, &resolved)?;
    if !deviations.is_empty() {
        omniscan_core::io::write_json_atomic(&out.join("surface_deviation.json"), &deviations)?;
    }
    let v = &inspection.verdict;
    Ok(InspectReport {
        verdict,
        report: out.join("report.html"),
        defective: v.defective.map(|d| models[d].clone()),
        defect_type: v.defect_type.to_string(),
        area_mm2: v
            .defective
            .map_or(0.0, |d| v.geometric_area_mm2[d] + v.visual_area_mm2[d]),
        significant_regions: v.defective.map_or(0, |d| {
            v.regions
                .iter()
                .filter(|r| r.significant && r.model == d)
                .count()
        }),
        score: v.score,
        alignments: inspection
            .alignments
            .iter()
            .zip(models)
            .skip(1)
            .map(|(a, model)| ModelAlignment {
                model: model.clone(),
                fitness: a.fitness,
                inlier_rmse: a.inlier_rmse,
                method: a.method.clone(),
            })
            .collect(),
        surface_deviation: deviations,
        seconds: inspection.timings.total,
    })
}

/// Everything `make-copy` can be told besides the model and output.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MakeCopySettings {
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
    #[arg(long, default_value_t = CopySettings::default().position_noise_mm)]
    pub noise_mm: f64,
    /// Keep the model's pose (by default the copy is moved to a random pose).
    #[arg(long)]
    pub keep_pose: bool,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

default_from_flags!(MakeCopySettings);

/// The defect planted in a copy.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlantedDefect {
    pub kind: String,
    pub size_mm: f64,
    /// Its centre in the copy's frame, model units.
    pub centre_in_copy: [f64; 3],
    pub affected_splats: usize,
}

/// What [`make_copy`] wrote.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CopyReport {
    pub copy: PathBuf,
    pub splats: usize,
    /// The original's frame in the copy's, 4x4 row-major.
    pub original_to_copy: [[f64; 4]; 4],
    pub defect: Option<PlantedDefect>,
}

/// A good or defective copy of `model`, written to `out`.
pub fn make_copy(model: &Path, out: &Path, settings: &MakeCopySettings) -> Result<CopyReport> {
    omniscan_splat::ply::ModelFormat::writable(out)?;
    let original = read_splats(model)?;
    let (base, defect) = match &settings.defect {
        Some(kind) => {
            let kind = DefectKind::parse(kind)?;
            let (m, d) = plant_defect(
                &original,
                kind,
                settings.size_mm,
                settings.units_per_metre,
                settings.seed,
            )?;
            (m, Some(d))
        }
        None => (original, None),
    };
    let (copy, pose) = good_copy(
        &base,
        settings.units_per_metre,
        &CopySettings {
            seed: settings.seed.wrapping_add(1),
            position_noise_mm: settings.noise_mm,
            random_pose: !settings.keep_pose,
            ..CopySettings::default()
        },
    )?;
    write_splats(out, &copy)?;
    Ok(CopyReport {
        copy: out.to_path_buf(),
        splats: copy.len(),
        original_to_copy: omniscan_core::geometry::pose_to_rows(&pose),
        defect: defect.map(|d| {
            let c = pose * Point3::from(d.centre);
            PlantedDefect {
                kind: d.kind.name().into(),
                size_mm: d.size_mm,
                centre_in_copy: [c.x, c.y, c.z],
                affected_splats: d.affected_splats,
            }
        }),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_inspection_crates() {
        let s = InspectionSettings::default();
        let d = InspectSettings::default();
        assert_eq!(
            (s.threshold_mm, s.colour_threshold),
            (d.threshold_mm, d.colour_threshold)
        );
        assert_eq!((s.views, s.width, s.height), (d.views, d.width, d.height));
        assert_eq!(s.colour.radius_mm(), d.photometric_radius_mm);
        assert_eq!(MakeCopySettings::default().size_mm, 6.0);
    }
}
