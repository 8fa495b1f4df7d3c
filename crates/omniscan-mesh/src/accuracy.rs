//! How far one surface is from another, in millimetres: Chamfer distance
//! and F-score over points sampled evenly on both (as the DTU and Tanks and
//! Temples benchmarks score meshes), the volume error, and the signed
//! deviation of each point of one surface from the other (positive
//! outside), for inspection. Nearest points come from parry3d's
//! bounding-volume hierarchy; inside/outside from its pseudo-normals.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use parry3d::math::Vector;
use parry3d::query::PointQuery;
use parry3d::shape::{TriMesh as ParryMesh, TriMeshFlags};

use crate::topology::{area, topology, triangle_area, volume};
use crate::{MeshError, TriMesh};

/// A surface ready for nearest-point queries.
pub struct Surface {
    shape: ParryMesh,
}

impl Surface {
    pub fn new(mesh: &TriMesh) -> Result<Surface, MeshError> {
        let vertices = mesh
            .positions
            .iter()
            .map(|p| Vector::new(p[0], p[1], p[2]))
            .collect();
        let shape = ParryMesh::with_flags(vertices, mesh.triangles.clone(), TriMeshFlags::ORIENTED)
            .map_err(|e| MeshError::Input(format!("the mesh cannot be queried: {e}")))?;
        Ok(Surface { shape })
    }

    /// Distance from `p` to the surface, metres.
    pub fn distance(&self, p: [f32; 3]) -> f32 {
        self.signed_distance(p).0.abs()
    }

    /// Signed distance (negative inside) and the nearest surface point.
    pub fn signed_distance(&self, p: [f32; 3]) -> (f32, [f32; 3]) {
        let v = Vector::new(p[0], p[1], p[2]);
        let proj = self.shape.project_local_point(v, false);
        let d = (proj.point - v).length();
        let q = [proj.point.x, proj.point.y, proj.point.z];
        (if proj.is_inside { -d } else { d }, q)
    }
}

/// `count` points spread over the surface by area (seeded, so repeatable).
pub fn sample_surface(mesh: &TriMesh, count: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut cumulative = Vec::with_capacity(mesh.triangles.len());
    let mut total = 0.0f64;
    for t in &mesh.triangles {
        total += triangle_area(mesh, t);
        cumulative.push(total);
    }
    if total <= 0.0 {
        return Vec::new();
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..count)
        .map(|_| {
            let x = rng.random::<f64>() * total;
            let i = cumulative
                .partition_point(|&c| c < x)
                .min(cumulative.len() - 1);
            let (mut r1, mut r2) = (rng.random::<f32>(), rng.random::<f32>());
            if r1 + r2 > 1.0 {
                (r1, r2) = (1.0 - r1, 1.0 - r2);
            }
            let [a, b, c] = mesh.triangles[i].map(|v| mesh.positions[v as usize]);
            [0, 1, 2].map(|k| a[k] + r1 * (b[k] - a[k]) + r2 * (c[k] - a[k]))
        })
        .collect()
}

/// How well a reconstructed surface matches the true one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Accuracy {
    /// Mean of both directions' mean nearest distances, mm.
    pub chamfer_mm: f64,
    /// Mean distance from the reconstruction to the truth, mm.
    pub accuracy_mm: f64,
    /// Mean distance from the truth to the reconstruction, mm.
    pub completeness_mm: f64,
    pub f_score_1mm: f64,
    pub f_score_2mm: f64,
    /// (reconstructed − true) / true volume, percent; `None` when the true
    /// mesh is not closed (its volume is undefined).
    pub volume_error_percent: Option<f64>,
    /// (reconstructed − true) / true area, percent.
    pub area_error_percent: f64,
}

/// Compares `reconstruction` with `truth` over `samples` points on each.
pub fn compare(
    reconstruction: &TriMesh,
    truth: &TriMesh,
    samples: usize,
) -> Result<Accuracy, MeshError> {
    let (rec_surface, true_surface) = (Surface::new(reconstruction)?, Surface::new(truth)?);
    let distances = |points: Vec<[f32; 3]>, to: &Surface| -> Vec<f64> {
        points.par_iter().map(|&p| to.distance(p) as f64).collect()
    };
    let to_truth = distances(sample_surface(reconstruction, samples, 1), &true_surface);
    let to_rec = distances(sample_surface(truth, samples, 2), &rec_surface);
    if to_truth.is_empty() || to_rec.is_empty() {
        return Err(MeshError::Input("a mesh to compare has no area".into()));
    }
    let mean = |d: &[f64]| d.iter().sum::<f64>() / d.len() as f64;
    let within =
        |d: &[f64], tau: f64| d.iter().filter(|&&x| x <= tau).count() as f64 / d.len() as f64;
    let f_score = |tau: f64| {
        let (p, r) = (within(&to_truth, tau), within(&to_rec, tau));
        if p + r > 0.0 {
            2.0 * p * r / (p + r)
        } else {
            0.0
        }
    };
    let (acc, comp) = (mean(&to_truth) * 1e3, mean(&to_rec) * 1e3);
    Ok(Accuracy {
        chamfer_mm: 0.5 * (acc + comp),
        accuracy_mm: acc,
        completeness_mm: comp,
        f_score_1mm: f_score(1e-3),
        f_score_2mm: f_score(2e-3),
        volume_error_percent: topology(truth)
            .is_watertight()
            .then(|| 100.0 * (volume(reconstruction) / volume(truth) - 1.0)),
        area_error_percent: 100.0 * (area(reconstruction) / area(truth) - 1.0),
    })
}
