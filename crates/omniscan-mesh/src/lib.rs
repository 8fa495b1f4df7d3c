//! Geometry from a twin, for simulators, CAD and inspection.
//!
//! - [`twin`]: render the splat model's median depth from views all round
//!   it, fuse them ([`fusion`], a TSDF), extract the surface ([`extract`],
//!   marching tetrahedra), keep the object's piece, decimate ([`simplify`],
//!   quadric edge collapse) and colour it ([`texture`]: vertex colours and a baked
//!   UV texture);
//! - [`files`]: OBJ + MTL + PNG, PLY and GLB;
//! - [`physics`]: convex decomposition (parry3d's V-HACD), mass properties,
//!   URDF and MJCF;
//! - [`accuracy`]: Chamfer distance, F-score, volume error and signed
//!   surface deviation against another mesh.
//!
//! Units are metres throughout; reports give millimetres where they say so.

pub mod accuracy;
pub mod depth;
pub mod extract;
pub mod files;
pub mod fusion;
pub mod physics;
pub mod simplify;
pub mod texture;
pub mod topology;
pub mod twin;

use std::path::PathBuf;

/// A triangle mesh in metres with a colour per vertex (0-1 RGB) and, per
/// triangle, whether it closes a region no view saw.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriMesh {
    pub positions: Vec<[f32; 3]>,
    pub colors: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
    pub unseen: Vec<bool>,
}

impl TriMesh {
    /// The triangles for which `keep(index)` holds, with only the vertices
    /// they use (renumbered in first-use order).
    pub fn filter_triangles(&self, keep: impl Fn(usize) -> bool) -> TriMesh {
        let mut renumber = vec![u32::MAX; self.positions.len()];
        let mut out = TriMesh::default();
        for (i, t) in self.triangles.iter().enumerate() {
            if !keep(i) {
                continue;
            }
            let corners = t.map(|v| {
                let slot = &mut renumber[v as usize];
                if *slot == u32::MAX {
                    *slot = out.positions.len() as u32;
                    out.positions.push(self.positions[v as usize]);
                    out.colors
                        .push(self.colors.get(v as usize).copied().unwrap_or([0.5; 3]));
                }
                *slot
            });
            out.triangles.push(corners);
            out.unseen
                .push(self.unseen.get(i).copied().unwrap_or(false));
        }
        out
    }

    /// Axis-aligned bounds (min, max); zeros for an empty mesh.
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        if self.positions.is_empty() {
            return ([0.0; 3], [0.0; 3]);
        }
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for p in &self.positions {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        (lo, hi)
    }

    /// The mesh moved by the rigid transform `pose` (a point p goes to pose·p).
    pub fn transformed(&self, pose: &nalgebra::Isometry3<f64>) -> TriMesh {
        let mut out = self.clone();
        for p in &mut out.positions {
            let q = pose * nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            *p = [q.x as f32, q.y as f32, q.z as f32];
        }
        out
    }
}

/// What can go wrong making geometry.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    /// The model or the settings cannot give a mesh; says which flag to change.
    #[error("{0}")]
    Input(String),
    /// A file could not be read or written.
    #[error("{path}: {message}")]
    File { path: PathBuf, message: String },
    #[error(transparent)]
    Io(#[from] omniscan_core::CoreError),
}
