//! The gripper's volume, for the grasp planner's collision tests: is this
//! point of the object inside the gripper at this opening?
//!
//! The YuMi's volume is the boxes of [`crate::gripper::gripper_boxes`].
//! Another robot's gripper comes as link meshes of any shape (an L-shaped
//! finger with its mounting block, a four-bar linkage), so each link is
//! voxelised once, when the planner first asks, in its own frame
//! ([`Voxels`]). A bounding box per
//! link was tried first: an L-shaped finger's box covers the space between
//! the pads, and no grasp fitted the YuMi's own URDF or the Robotiq 2F-85.
//!
//! Written here rather than taken from parry's point-in-mesh queries: those
//! want a watertight, consistently wound mesh, which CAD exports of grippers
//! often are not, and cost a tree walk per query; the voxels take any mesh
//! whose holes are smaller than a voxel and answer in constant time.

use nalgebra::{Isometry3, Point3};

use crate::mesh::Mesh;

/// Edge of a voxel, metres: under the planner's 1.5 mm of slack past the
/// contacts, so the voxels' rounding never blocks a grasp on the pads.
pub const VOXEL_M: f64 = 0.001;
/// The most voxels along one axis (a larger link gets larger voxels).
const MAX_VOXELS_PER_AXIS: usize = 256;
/// Spacing of the surface points a part offers as an obstacle, metres.
const SURFACE_SPACING_M: f64 = 0.003;

/// A mesh's solid as voxels in the mesh's frame: those its surface passes
/// through and those enclosed by it (not reached by a flood fill of the
/// outside from the grid's border).
#[derive(Debug, Clone)]
pub struct Voxels {
    origin: Point3<f64>,
    size_m: f64,
    dims: [usize; 3],
    filled: Vec<bool>,
    lo: Point3<f64>,
    hi: Point3<f64>,
    surface: Vec<Point3<f64>>,
}

impl Voxels {
    /// Voxelises `mesh` with voxels of [`VOXEL_M`] (larger for a link over
    /// 254 mm, whose grid would pass 256 a side). An empty mesh gives no
    /// voxels.
    pub fn of_mesh(mesh: &Mesh) -> Voxels {
        let (mut lo, mut hi) = (
            Point3::from([f64::INFINITY; 3]),
            Point3::from([f64::NEG_INFINITY; 3]),
        );
        for p in &mesh.positions {
            let p = p.cast::<f64>();
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        if mesh.positions.is_empty() {
            return Voxels {
                origin: Point3::origin(),
                size_m: VOXEL_M,
                dims: [0; 3],
                filled: Vec::new(),
                lo: Point3::origin(),
                hi: Point3::origin(),
                surface: Vec::new(),
            };
        }
        let extent = (hi - lo).max();
        let size_m = VOXEL_M.max(extent / (MAX_VOXELS_PER_AXIS - 2) as f64);
        // One empty voxel all round, where the flood fill of the outside starts.
        let origin = lo - nalgebra::Vector3::repeat(size_m);
        let dims = [0, 1, 2].map(|a| ((hi[a] - lo[a]) / size_m).ceil() as usize + 3);
        let mut voxels = Voxels {
            origin,
            size_m,
            dims,
            filled: vec![false; dims[0] * dims[1] * dims[2]],
            lo,
            hi,
            surface: Vec::new(),
        };
        voxels.mark_surface(mesh);
        voxels.fill_enclosed();
        voxels
    }

    fn index(&self, p: &Point3<f64>) -> Option<usize> {
        let mut at = [0usize; 3];
        for a in 0..3 {
            let v = ((p[a] - self.origin[a]) / self.size_m).floor();
            if !(v >= 0.0 && v < self.dims[a] as f64) {
                return None;
            }
            at[a] = v as usize;
        }
        Some(at[0] + self.dims[0] * (at[1] + self.dims[1] * at[2]))
    }

    /// Marks the voxels each triangle passes through, from points spaced a
    /// third of a voxel over it, and keeps one point per
    /// [`SURFACE_SPACING_M`] cell as the part's surface.
    fn mark_surface(&mut self, mesh: &Mesh) {
        let step = self.size_m / 3.0;
        let mut seen = std::collections::HashSet::new();
        for t in 0..mesh.triangles.len() {
            let [a, b, c] = mesh.triangle(t).map(|p| p.cast::<f64>());
            let longest = (b - a).norm().max((c - a).norm()).max((c - b).norm());
            let n = (longest / step).ceil().max(1.0) as usize;
            for i in 0..=n {
                for j in 0..=(n - i) {
                    let p = a + (b - a) * (i as f64 / n as f64) + (c - a) * (j as f64 / n as f64);
                    if let Some(k) = self.index(&p) {
                        self.filled[k] = true;
                    }
                    let cell = (p.coords / SURFACE_SPACING_M).map(|v| v.floor() as i64);
                    if seen.insert((cell.x, cell.y, cell.z)) {
                        self.surface.push(p);
                    }
                }
            }
        }
    }

    /// Fills every voxel the outside cannot reach through empty voxels
    /// (six-connected) from the border.
    fn fill_enclosed(&mut self) {
        let [nx, ny, nz] = self.dims;
        let mut outside = vec![false; self.filled.len()];
        let mut stack = vec![0usize];
        outside[0] = true;
        while let Some(k) = stack.pop() {
            let (x, y, z) = (k % nx, (k / nx) % ny, k / (nx * ny));
            let mut visit = |k: usize| {
                if !outside[k] && !self.filled[k] {
                    outside[k] = true;
                    stack.push(k);
                }
            };
            if x > 0 {
                visit(k - 1);
            }
            if x + 1 < nx {
                visit(k + 1);
            }
            if y > 0 {
                visit(k - nx);
            }
            if y + 1 < ny {
                visit(k + nx);
            }
            if z > 0 {
                visit(k - nx * ny);
            }
            if z + 1 < nz {
                visit(k + nx * ny);
            }
        }
        for (filled, outside) in self.filled.iter_mut().zip(outside) {
            *filled = !outside;
        }
    }

    /// Whether `p` (the mesh's frame) lies in a filled voxel.
    pub fn contains(&self, p: &Point3<f64>) -> bool {
        self.index(p).is_some_and(|k| self.filled[k])
    }
}

/// What a part of the gripper fills, in the part's frame.
#[derive(Debug, Clone, Copy)]
pub enum Solid<'a> {
    /// The box `lo..hi` (the YuMi's parts).
    Cuboid { lo: Point3<f64>, hi: Point3<f64> },
    /// A link mesh's voxels.
    Voxels(&'a Voxels),
}

/// A part of the gripper placed in the TCP frame at some opening.
#[derive(Debug, Clone, Copy)]
pub struct CollisionPart<'a> {
    /// The part's frame in the TCP frame.
    pub tcp_to_part: Isometry3<f64>,
    pub solid: Solid<'a>,
    /// Moves with the fingers; else part of the palm.
    pub finger: bool,
}

impl CollisionPart<'_> {
    /// Whether the TCP-frame point `p` lies inside the part (strictly, for
    /// a box).
    pub fn contains(&self, p: &Point3<f64>) -> bool {
        let q = self.tcp_to_part.inverse_transform_point(p);
        match &self.solid {
            Solid::Cuboid { lo, hi } => {
                q.x > lo.x && q.y > lo.y && q.z > lo.z && q.x < hi.x && q.y < hi.y && q.z < hi.z
            }
            Solid::Voxels(voxels) => voxels.contains(&q),
        }
    }

    /// The part's extent along the TCP frame's axes (min, max).
    pub fn tcp_extent(&self) -> (Point3<f64>, Point3<f64>) {
        let (lo, hi) = match &self.solid {
            Solid::Cuboid { lo, hi } => (*lo, *hi),
            Solid::Voxels(v) => (v.lo, v.hi),
        };
        let mut out = (
            Point3::from([f64::INFINITY; 3]),
            Point3::from([f64::NEG_INFINITY; 3]),
        );
        for i in 0..8 {
            let corner = Point3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            );
            let p = self.tcp_to_part * corner;
            out = (out.0.inf(&p), out.1.sup(&p));
        }
        out
    }

    /// Points on the part's surface in the TCP frame: a box's faces on a
    /// grid of 6 steps an edge, a mesh's surface about every 3 mm.
    pub fn surface_points(&self) -> Vec<Point3<f64>> {
        match &self.solid {
            Solid::Cuboid { lo, hi } => cuboid_surface(lo, hi, 6)
                .into_iter()
                .map(|p| self.tcp_to_part * p)
                .collect(),
            Solid::Voxels(v) => v.surface.iter().map(|p| self.tcp_to_part * p).collect(),
        }
    }
}

/// A grid of points on the faces of the box `lo..hi`, `per_axis` steps along
/// each edge.
fn cuboid_surface(lo: &Point3<f64>, hi: &Point3<f64>, per_axis: usize) -> Vec<Point3<f64>> {
    let at = |a: f64, b: f64, s: usize| a + (b - a) * s as f64 / per_axis as f64;
    let mut out = Vec::new();
    for i in 0..=per_axis {
        for j in 0..=per_axis {
            for k in 0..=per_axis {
                if [i, j, k].iter().any(|&v| v == 0 || v == per_axis) {
                    out.push(Point3::new(
                        at(lo.x, hi.x, i),
                        at(lo.y, hi.y, j),
                        at(lo.z, hi.z, k),
                    ));
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{Material, MeshBuilder};

    /// An L of two boxes: a foot 30 x 10 x 8 mm and a post 5 x 10 x 60 mm.
    fn l_shape() -> Mesh {
        let mut b = MeshBuilder::new(Material::color([0.5; 3]));
        b.cuboid(
            Point3::new(0.0, 0.0, 0.0),
            Point3::new(0.030, 0.010, 0.008),
            0,
        );
        b.cuboid(
            Point3::new(0.0, 0.0, 0.008),
            Point3::new(0.005, 0.010, 0.068),
            0,
        );
        b.finish()
    }

    #[test]
    fn voxels_fill_an_l_and_leave_its_corner_empty() {
        let voxels = Voxels::of_mesh(&l_shape());
        for inside in [[0.015, 0.005, 0.004], [0.0025, 0.005, 0.040]] {
            assert!(voxels.contains(&Point3::from(inside)), "{inside:?}");
        }
        // Inside the L's bounding box but outside the L, a voxel and more
        // from its faces.
        for outside in [
            [0.020, 0.005, 0.030],
            [0.0075, 0.005, 0.010],
            [0.015, 0.012, 0.004],
        ] {
            assert!(!voxels.contains(&Point3::from(outside)), "{outside:?}");
        }
    }

    /// A 20 mm cube as six separate faces, each shrunk by `gap` from its
    /// edges (cracks along every edge, as in a careless CAD export), without
    /// the faces in `missing`.
    fn cracked_cube(gap: f64, missing: &[usize]) -> Mesh {
        let mut mesh = Mesh::default();
        let s = 0.010;
        for face in 0..6 {
            if missing.contains(&face) {
                continue;
            }
            let (axis, sign) = (face / 2, if face % 2 == 0 { -1.0 } else { 1.0 });
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let corner = |a: f64, b: f64| {
                let mut p = Point3::origin();
                p[axis] = sign * s;
                p[u] = a * (s - gap);
                p[v] = b * (s - gap);
                p.cast::<f32>()
            };
            let base = mesh.positions.len() as u32;
            mesh.positions.extend([
                corner(-1.0, -1.0),
                corner(1.0, -1.0),
                corner(1.0, 1.0),
                corner(-1.0, 1.0),
            ]);
            mesh.triangles
                .extend([[base, base + 1, base + 2], [base, base + 2, base + 3]]);
        }
        mesh
    }

    #[test]
    fn cracks_under_a_voxel_keep_the_inside_a_missing_face_does_not() {
        let centre = Point3::origin();
        assert!(Voxels::of_mesh(&cracked_cube(0.0, &[])).contains(&centre));
        assert!(Voxels::of_mesh(&cracked_cube(0.0003, &[])).contains(&centre));
        let open = Voxels::of_mesh(&cracked_cube(0.0, &[5]));
        assert!(!open.contains(&centre), "an open box is a shell");
    }

    #[test]
    fn surface_points_lie_on_the_surface() {
        let voxels = Voxels::of_mesh(&l_shape());
        assert!(voxels.surface.len() > 50);
        let part = CollisionPart {
            tcp_to_part: Isometry3::translation(0.1, 0.0, 0.0),
            solid: Solid::Voxels(&voxels),
            finger: true,
        };
        for p in part.surface_points() {
            let q = p - nalgebra::Vector3::new(0.1, 0.0, 0.0);
            let on_face = [
                q.x,
                q.y,
                q.z,
                q.x - 0.005,
                q.x - 0.030,
                q.y - 0.010,
                q.z - 0.008,
                q.z - 0.068,
            ]
            .iter()
            .any(|v| v.abs() < 1e-6);
            assert!(on_face, "{q}");
            assert!(
                part.contains(&p),
                "a surface point is in a filled voxel: {q}"
            );
        }
    }
}
