//! Geometric inspection in millimetres: each copy's mesh ([`omniscan_mesh`])
//! aligned onto the first copy's by the inspection's alignment, the signed
//! distance of every vertex from the first copy's surface (positive
//! outwards: material added or pushed out), a PLY coloured by it, and the
//! largest deviation and where it is. A significant region where the
//! surfaces deviate by more than the threshold is typed geometric: the
//! pixel and point differencing alone called a 6 mm dent on a simulated
//! T-connector visual.

use std::path::{Path, PathBuf};

use anyhow::Result;
use serde::{Deserialize, Serialize};

use omniscan_inspect::Inspection;
use omniscan_inspect::verdict::Kind;
use omniscan_mesh::TriMesh;
use omniscan_mesh::accuracy::Surface;
use omniscan_mesh::twin::{MeshConfig, mesh_model};
use omniscan_splat::Splats;

/// Deviation past which a region is geometric, mm.
pub const GEOMETRIC_DEVIATION_MM: f64 = 1.0;

/// One copy's surface against the first copy's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CopyDeviation {
    pub model_index: usize,
    /// The copy's mesh in the first copy's frame, coloured by signed distance.
    pub ply: PathBuf,
    /// The largest |signed distance| and its sign, mm.
    pub max_deviation_mm: f64,
    /// Where it is, in the first copy's frame, mm.
    pub max_deviation_at_mm: [f64; 3],
    /// The 99th percentile of |signed distance|: what the surfaces differ by
    /// away from a defect, mm.
    pub p99_deviation_mm: f64,
}

/// A vertex's deviation and position (reference frame, metres).
type Samples = Vec<(f32, [f32; 3])>;

/// Meshes the models, measures each copy's deviation from the first,
/// writes `deviation_K.ply` into `out`, and types the verdict's regions by
/// it. `units_per_metre`: the models' units.
pub fn surface_deviation(
    models: &[Splats],
    inspection: &mut Inspection,
    units_per_metre: f64,
    out: &Path,
) -> Result<Vec<CopyDeviation>> {
    let config = MeshConfig {
        scale_m_per_unit: 1.0 / units_per_metre,
        views: 48,
        view_px: 256,
        ..MeshConfig::default()
    };
    let meshes: Vec<TriMesh> = models
        .iter()
        .enumerate()
        .map(|(i, m)| {
            mesh_model(m, &config)
                .map(|meshed| meshed.mesh)
                .map_err(|e| anyhow::anyhow!("meshing model {i} for its surface deviation: {e}"))
        })
        .collect::<Result<_>>()?;
    let reference = Surface::new(&meshes[0])?;
    let mut samples: Vec<Samples> = vec![Vec::new()];
    let mut report = Vec::new();
    for (i, mesh) in meshes.iter().enumerate().skip(1) {
        let mut pose = inspection.alignments[i].transform;
        pose.translation.vector /= units_per_metre;
        let mut aligned = mesh.transformed(&pose);
        let deviations: Samples = aligned
            .positions
            .iter()
            .map(|&p| (reference.signed_distance(p).0, p))
            .collect();
        aligned.colors = deviations
            .iter()
            .map(|(d, _)| diverging(*d / COLOUR_SCALE_M))
            .collect();
        let ply = out.join(format!("deviation_{i}.ply"));
        omniscan_core::io::write_atomic(&ply, &omniscan_mesh::files::ply(&aligned))?;
        report.push(summary(i, ply, &deviations));
        samples.push(deviations);
    }
    type_regions(inspection, &samples, units_per_metre);
    Ok(report)
}

/// The colour scale's saturation (twice the geometric threshold), metres.
const COLOUR_SCALE_M: f32 = (GEOMETRIC_DEVIATION_MM * 2e-3) as f32;

/// Blue (inwards) through white to red (outwards), saturating at ±1.
fn diverging(t: f32) -> [f32; 3] {
    let t = t.clamp(-1.0, 1.0);
    if t >= 0.0 {
        [1.0, 1.0 - t, 1.0 - t]
    } else {
        [1.0 + t, 1.0 + t, 1.0]
    }
}

fn summary(model_index: usize, ply: PathBuf, deviations: &Samples) -> CopyDeviation {
    let (max, at) = deviations
        .iter()
        .max_by(|a, b| a.0.abs().total_cmp(&b.0.abs()))
        .copied()
        .unwrap_or((0.0, [0.0; 3]));
    let mut magnitudes: Vec<f32> = deviations.iter().map(|d| d.0.abs()).collect();
    magnitudes.sort_by(f32::total_cmp);
    let p99 = magnitudes
        .get(magnitudes.len().saturating_sub(1) * 99 / 100)
        .copied()
        .unwrap_or(0.0);
    CopyDeviation {
        model_index,
        ply,
        max_deviation_mm: max as f64 * 1e3,
        max_deviation_at_mm: at.map(|c| c as f64 * 1e3),
        p99_deviation_mm: p99 as f64 * 1e3,
    }
}

/// The largest |deviation| within `radius` of `centre` (metres) in a set.
fn deviation_near(samples: &Samples, centre: [f64; 3], radius: f64) -> f64 {
    samples
        .iter()
        .filter(|(_, p)| {
            (0..3)
                .map(|k| (p[k] as f64 - centre[k]).powi(2))
                .sum::<f64>()
                <= radius * radius
        })
        .map(|(d, _)| d.abs() as f64)
        .fold(0.0, f64::max)
}

/// Types each significant region by the surfaces' deviation there: on the
/// copy itself, or, for the first copy (the reference of every
/// deviation), as the smallest of the other copies' deviations there.
fn type_regions(inspection: &mut Inspection, samples: &[Samples], units_per_metre: f64) {
    let verdict = &mut inspection.verdict;
    for region in verdict.regions.iter_mut().filter(|r| r.significant) {
        let centre = region.centroid.map(|c| c / units_per_metre);
        let radius = (region.extent_mm * 0.5 + 2.0) * 1e-3;
        let deviation = if region.model == 0 {
            samples[1..]
                .iter()
                .map(|s| deviation_near(s, centre, radius))
                .fold(f64::INFINITY, f64::min)
        } else {
            deviation_near(&samples[region.model], centre, radius)
        };
        if deviation.is_finite() && deviation * 1e3 >= GEOMETRIC_DEVIATION_MM {
            region.kind = Kind::Geometric;
        }
    }
    if let Some(d) = verdict.defective {
        let kinds = |kind: Kind| {
            verdict
                .regions
                .iter()
                .any(|r| r.significant && r.model == d && r.kind == kind)
        };
        verdict.defect_type = match (kinds(Kind::Geometric), kinds(Kind::Visual)) {
            (true, true) => "both",
            (true, false) => "geometric",
            _ => "visual",
        }
        .into();
    }
}
