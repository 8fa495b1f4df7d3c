//! Antipodal grasps for the simulated robot (paper, "Tabletop Grasping" and
//! "Bi-Manual Handover"; the real system uses Contact-GraspNet).
//!
//! Candidates come from surface points sampled by area: the closing axis is
//! the inward normal, the two contacts are where that line enters and leaves
//! the object, and both contact normals must lie in a friction cone about the
//! axis. Each candidate gets the approach direction about its axis that keeps
//! the object clear of the palm and the fingers. The left arm takes the most
//! stable grasp (axis through the centroid, good antipodality); the right arm
//! then takes the best grasp whose pads are away from the left pads and whose
//! gripper does not collide with the left one, so the handover exposes what
//! the left fingers covered. The gripper is the one the scan uses
//! ([`GripperModel::collision_parts`]): the YuMi's palm and finger boxes,
//! or another robot's voxelised links at the grasp's opening.

use nalgebra::{Matrix3, Point3, Rotation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::Serialize;

use crate::SimError;
use crate::gripper::GripperModel;
use crate::mesh::Mesh;
use omniscan_core::Pose;
use omniscan_scene::collision::CollisionPart;

/// A two-finger grasp in the object's frame.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Grasp {
    /// Midpoint of the two contacts (the TCP), object frame, metres.
    pub center: [f64; 3],
    /// Closing direction of the fingers (gripper x), object frame.
    pub axis: [f64; 3],
    /// Approach direction (gripper z, wrist to fingertips), object frame.
    pub approach: [f64; 3],
    /// Distance between the contacts = the finger opening, metres.
    pub width_m: f64,
    /// How far towards the fingertips the contacts sit from the TCP, metres
    /// (0 = mid-pad; larger = held nearer the tips, for crowded handovers).
    pub depth_m: f64,
    pub contacts: [[f64; 3]; 2],
    /// Higher is better: antipodality minus a torque penalty.
    pub quality: f64,
}

impl Grasp {
    /// Pose of the object in the gripper: object frame to TCP frame.
    pub fn object_to_gripper(&self) -> Pose {
        let x = Vector3::from(self.axis);
        let z = Vector3::from(self.approach);
        let y = z.cross(&x);
        let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
            Matrix3::from_columns(&[x, y, z]),
        ));
        let tcp = Vector3::from(self.center) - z * self.depth_m;
        let gripper_to_object = Pose::from_parts(nalgebra::Translation3::from(tcp), rotation);
        gripper_to_object.inverse()
    }
}

/// Settings of the grasp search.
#[derive(Debug, Clone, Copy)]
pub struct GraspSettings {
    pub candidates: usize,
    /// Half-angle of the friction cone, radians.
    pub friction_cone_rad: f64,
    pub min_width_m: f64,
    pub max_width_m: f64,
    pub seed: u64,
}

impl GraspSettings {
    /// The simulator's search for `gripper`: 600 candidates, a 20° friction
    /// cone, widths from 2 mm to 4 mm short of the widest opening.
    pub fn for_gripper(gripper: &GripperModel, seed: u64) -> GraspSettings {
        GraspSettings {
            candidates: 600,
            friction_cone_rad: 20f64.to_radians(),
            min_width_m: 0.002,
            max_width_m: gripper.max_opening_m() - 0.004,
            seed,
        }
    }
}

struct Candidate {
    center: Point3<f64>,
    axis: Vector3<f64>,
    width: f64,
    contacts: [Point3<f64>; 2],
    quality: f64,
}

/// The object's vertices in its frame: a subsample of at most 3000 to rank
/// a candidate's approaches, and all of them to confirm the chosen one (a
/// thin finger can slip between the subsample's points).
struct Vertices {
    sample: Vec<Point3<f64>>,
    all: Vec<Point3<f64>>,
}

impl Vertices {
    fn of(mesh: &Mesh) -> Vertices {
        let all: Vec<Point3<f64>> = mesh.positions.iter().map(|p| p.cast::<f64>()).collect();
        let step = (all.len() / 3000).max(1);
        let sample = all.iter().step_by(step).copied().collect();
        Vertices { sample, all }
    }
}

/// Perpendicular unit vectors to `axis`.
fn basis(axis: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let helper = if axis.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = axis.cross(&helper).normalize();
    let e2 = axis.cross(&e1);
    (e1, e2)
}

/// Finds antipodal grasp candidates, best first (without approach directions).
fn candidates(mesh: &Mesh, settings: &GraspSettings) -> Vec<Candidate> {
    let areas: Vec<f64> = (0..mesh.triangles.len())
        .map(|t| {
            let [a, b, c] = mesh.triangle(t).map(|p| p.cast::<f64>());
            (b - a).cross(&(c - a)).norm()
        })
        .collect();
    let total: f64 = areas.iter().sum();
    let mut cdf = Vec::with_capacity(areas.len());
    let mut acc = 0.0;
    for a in &areas {
        acc += a / total;
        cdf.push(acc);
    }
    let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
    let seeds: Vec<(usize, f64, f64)> = (0..settings.candidates)
        .map(|_| {
            let r: f64 = rng.random();
            let t = cdf.partition_point(|&c| c < r).min(areas.len() - 1);
            (t, rng.random(), rng.random())
        })
        .collect();
    let centroid = mesh.surface_centroid();
    let (lo, hi) = mesh.bounds();
    let radius = 0.5 * (hi - lo).cast::<f64>().norm();
    let cos_cone = settings.friction_cone_rad.cos();
    let mut found: Vec<Candidate> = seeds
        .par_iter()
        .filter_map(|&(t, mut u, mut v)| {
            if u + v > 1.0 {
                u = 1.0 - u;
                v = 1.0 - v;
            }
            let [a, b, c] = mesh.triangle(t).map(|p| p.cast::<f64>());
            let p = a + (b - a) * u + (c - a) * v;
            let axis = -mesh.face_normal(t).cast::<f64>();
            let hits = mesh.line_hits(&p, &axis);
            let (first, last) = (hits.first()?, hits.last()?);
            let width = last.0 - first.0;
            if width < settings.min_width_m || width > settings.max_width_m {
                return None;
            }
            let n1 = mesh.face_normal(first.1).cast::<f64>();
            let n2 = mesh.face_normal(last.1).cast::<f64>();
            let (d1, d2) = (n1.dot(&axis).abs(), n2.dot(&axis).abs());
            if d1 < cos_cone || d2 < cos_cone {
                return None;
            }
            let contacts = [p + axis * first.0, p + axis * last.0];
            let center = Point3::from((contacts[0].coords + contacts[1].coords) * 0.5);
            let to_centroid = centroid - center;
            let torque_arm = (to_centroid - axis * to_centroid.dot(&axis)).norm();
            let quality = 0.5 * (d1 + d2) - 1.5 * torque_arm / radius;
            Some(Candidate {
                center,
                axis,
                width,
                contacts,
                quality,
            })
        })
        .collect();
    found.sort_by(|a, b| b.quality.total_cmp(&a.quality));
    found
}

/// Tries approach directions about the candidate's axis, and grasp depths
/// from mid-pad towards the fingertips; returns the grasp at the smallest
/// depth that keeps the object and `obstacles` (object-frame points that must
/// stay outside the gripper) clear, preferring clearance from the palm.
fn with_approach(
    gripper: &GripperModel,
    c: &Candidate,
    vertices: &Vertices,
    obstacles: &[Point3<f64>],
) -> Option<Grasp> {
    GRASP_DEPTHS_M
        .into_iter()
        .find_map(|depth| with_approach_at_depth(gripper, c, depth, vertices, obstacles))
}

const GRASP_DEPTHS_M: [f64; 3] = [0.0, 0.01, 0.018];
/// How deep a vertex must be inside the gripper for the confirmation with
/// every vertex to refuse a grasp, metres.
const DEEP_M: f64 = 0.0005;

fn with_approach_at_depth(
    gripper: &GripperModel,
    c: &Candidate,
    depth_m: f64,
    vertices: &Vertices,
    obstacles: &[Point3<f64>],
) -> Option<Grasp> {
    let (e1, e2) = basis(&c.axis);
    // Fingers need 1.5 mm of slack beyond the contacts before a vertex counts as a collision.
    let volume = Volume::at(gripper, c.width + 0.003);
    let collides = |to_gripper: &Pose, points: &[Point3<f64>]| {
        points.iter().any(|p| volume.inside(&(to_gripper * p)))
    };
    let mut clear: Vec<(f64, Grasp)> = Vec::new();
    for k in 0..24 {
        let psi = std::f64::consts::TAU * k as f64 / 24.0;
        let approach = e1 * psi.cos() + e2 * psi.sin();
        let grasp = Grasp {
            center: c.center.coords.into(),
            axis: c.axis.into(),
            approach: approach.into(),
            width_m: c.width,
            depth_m,
            contacts: [c.contacts[0].coords.into(), c.contacts[1].coords.into()],
            quality: c.quality,
        };
        let to_gripper = grasp.object_to_gripper();
        if collides(&to_gripper, &vertices.sample) || collides(&to_gripper, obstacles) {
            continue;
        }
        let clearance = volume.palm_clearance(vertices.sample.iter().map(|v| to_gripper * v));
        clear.push((clearance, grasp));
    }
    // Most clearance first, the first approach among equals; confirmed on
    // every vertex.
    clear.sort_by(|a, b| b.0.total_cmp(&a.0));
    clear.into_iter().map(|(_, g)| g).find(|g| {
        let to_gripper = g.object_to_gripper();
        !vertices
            .all
            .iter()
            .any(|v| volume.deeply_inside(to_gripper * v))
    })
}

/// The gripper at one opening, as the planner tests points (TCP frame)
/// against it.
struct Volume<'a> {
    parts: Vec<CollisionPart<'a>>,
    /// The extent of all parts along the TCP frame's axes.
    lo: Point3<f64>,
    hi: Point3<f64>,
    /// The palm parts' extents.
    palms: Vec<(Point3<f64>, Point3<f64>)>,
}

impl<'a> Volume<'a> {
    fn at(gripper: &'a GripperModel, opening: f64) -> Volume<'a> {
        let parts = gripper.collision_parts(opening);
        let extents: Vec<_> = parts.iter().map(CollisionPart::tcp_extent).collect();
        let (mut lo, mut hi) = (
            Point3::from([f64::INFINITY; 3]),
            Point3::from([f64::NEG_INFINITY; 3]),
        );
        for (a, b) in &extents {
            lo = lo.inf(a);
            hi = hi.sup(b);
        }
        let palms = parts
            .iter()
            .zip(&extents)
            .filter(|(part, _)| !part.finger)
            .map(|(_, extent)| *extent)
            .collect();
        Volume {
            parts,
            lo,
            hi,
            palms,
        }
    }

    fn inside(&self, p: &Point3<f64>) -> bool {
        // Points compare componentwise: first the whole gripper's extent.
        *p >= self.lo && *p <= self.hi && self.parts.iter().any(|part| part.contains(p))
    }

    /// Inside by more than [`DEEP_M`]: `p` and its six neighbours that far
    /// along the axes are. The confirmation on every vertex looks for a
    /// finger that slipped between the subsample's points, not for grazes
    /// the fingers' give absorbs.
    fn deeply_inside(&self, p: Point3<f64>) -> bool {
        self.inside(&p)
            && (0..3).all(|axis| {
                [-DEEP_M, DEEP_M].iter().all(|d| {
                    let mut q = p;
                    q[axis] += d;
                    self.inside(&q)
                })
            })
    }

    /// How far the object (points) stays above the palm: the least height
    /// over the top of a palm part (its TCP-frame extent) of the points over
    /// its footprint.
    fn palm_clearance(&self, points: impl Iterator<Item = Point3<f64>>) -> f64 {
        let mut clearance = f64::INFINITY;
        for p in points {
            for (lo, hi) in &self.palms {
                if p.x > lo.x && p.x < hi.x && p.y > lo.y && p.y < hi.y {
                    clearance = clearance.min(p.z - hi.z);
                }
            }
        }
        clearance
    }
}

/// Collision-free left grasps, best first, skipping near-duplicates.
fn left_grasps(gripper: &GripperModel, mesh: &Mesh, settings: &GraspSettings) -> Vec<Grasp> {
    let vertices = Vertices::of(mesh);
    let found = candidates(mesh, settings);
    let mut out: Vec<Grasp> = Vec::new();
    for c in found.iter().take(200) {
        let duplicate = out.iter().any(|g| {
            (Point3::from(g.center) - c.center).norm() < 0.004
                && Vector3::from(g.axis).dot(&c.axis).abs() > 0.95
        });
        if duplicate {
            continue;
        }
        if let Some(g) = with_approach(gripper, c, &vertices, &[]) {
            out.push(g);
            if out.len() >= 12 {
                break;
            }
        }
    }
    out
}

/// The left arm's grasp: the best collision-free candidate.
pub fn plan_left_grasp(
    gripper: &GripperModel,
    mesh: &Mesh,
    settings: &GraspSettings,
) -> Result<Grasp, SimError> {
    left_grasps(gripper, mesh, settings)
        .into_iter()
        .next()
        .ok_or_else(|| no_grasp(settings))
}

/// The grasps of both arms: the best left grasp for which a handover regrasp
/// exists (as a planner moves on to the next grasp when one is infeasible).
pub fn plan_grasp_pair(
    gripper: &GripperModel,
    mesh: &Mesh,
    settings: &GraspSettings,
) -> Result<(Grasp, Grasp), SimError> {
    let lefts = left_grasps(gripper, mesh, settings);
    if lefts.is_empty() {
        return Err(no_grasp(settings));
    }
    let mut last_error = None;
    for left in lefts {
        match plan_right_grasp(gripper, mesh, &left, settings) {
            Ok(right) => return Ok((left, right)),
            Err(e) => last_error = Some(e),
        }
    }
    Err(last_error.unwrap())
}

fn no_grasp(settings: &GraspSettings) -> SimError {
    {
        SimError::Invalid(format!(
            "no antipodal grasp fits the gripper: the object needs two opposite faces between {:.0} and {:.0} mm apart \
             ({} candidates tried); check the object's scale",
            settings.min_width_m * 1e3,
            settings.max_width_m * 1e3,
            settings.candidates
        ))
    }
}

/// The right arm's regrasp at handover: pads away from the left pads, no
/// collision with the left gripper, preferring a different closing axis.
pub fn plan_right_grasp(
    gripper: &GripperModel,
    mesh: &Mesh,
    left: &Grasp,
    settings: &GraspSettings,
) -> Result<Grasp, SimError> {
    let vertices = Vertices::of(mesh);
    let left_to_object = left.object_to_gripper().inverse();
    let left_gripper: Vec<Point3<f64>> = gripper
        .collision_parts(left.width_m)
        .iter()
        .flat_map(CollisionPart::surface_points)
        .map(|p| left_to_object * p)
        .collect();
    let left_pads: Vec<Point3<f64>> = gripper
        .pad_points(left.width_m)
        .iter()
        .map(|p| left_to_object * p)
        .collect();
    let left_axis = Vector3::from(left.axis);
    let settings = GraspSettings {
        seed: settings.seed ^ 0x5eed,
        ..*settings
    };
    let found = candidates(mesh, &settings);
    let separation = |g: &Grasp| -> f64 {
        let to_object = g.object_to_gripper().inverse();
        let pads: Vec<Point3<f64>> = gripper
            .pad_points(g.width_m)
            .iter()
            .map(|p| to_object * p)
            .collect();
        pads.iter()
            .flat_map(|a| left_pads.iter().map(move |b| (a - b).norm()))
            .fold(f64::INFINITY, f64::min)
    };
    let scored: Vec<(f64, Grasp)> = found
        .par_iter()
        .take(400)
        .flat_map_iter(|c| {
            GRASP_DEPTHS_M.into_iter().filter_map(|depth| {
                with_approach_at_depth(gripper, c, depth, &vertices, &left_gripper)
            })
        })
        .filter_map(|g| {
            let sep = separation(&g);
            (sep >= 0.004).then(|| {
                let score = g.quality
                    + (sep.min(0.03) / 0.03)
                    + 0.5 * (1.0 - Vector3::from(g.axis).dot(&left_axis).abs())
                    - 10.0 * g.depth_m;
                (score, g)
            })
        })
        .collect();
    let mut best: Option<(f64, Grasp)> = None;
    for (score, g) in scored {
        if best.as_ref().is_none_or(|(s, _)| score > *s) {
            best = Some((score, g));
        }
    }
    best.map(|(_, g)| g).ok_or_else(|| {
        SimError::Invalid("no regrasp for the handover: every antipodal grasp of the right gripper collides with the left gripper or overlaps its fingers".into())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{Material, MeshBuilder};

    fn bar() -> Mesh {
        // 80 x 20 x 30 mm bar: the only graspable widths are 20 and 30 mm.
        let mut b = MeshBuilder::new(Material::color([0.5; 3]));
        b.cuboid(
            Point3::new(-0.04, -0.01, -0.015),
            Point3::new(0.04, 0.01, 0.015),
            0,
        );
        let mut m = b.finish();
        m.compute_normals();
        m
    }

    fn settings() -> GraspSettings {
        GraspSettings {
            candidates: 400,
            friction_cone_rad: 0.35,
            min_width_m: 0.002,
            max_width_m: 0.046,
            seed: 3,
        }
    }

    #[test]
    fn left_grasp_is_antipodal_across_a_narrow_side_and_clear_of_the_gripper() {
        let mesh = bar();
        let gripper = GripperModel::builtin();
        let g = plan_left_grasp(&gripper, &mesh, &settings()).unwrap();
        assert!(
            (g.width_m - 0.02).abs() < 1e-9 || (g.width_m - 0.03).abs() < 1e-9,
            "{}",
            g.width_m
        );
        let axis = Vector3::from(g.axis);
        assert!(axis.x.abs() < 1e-9, "never across the 80 mm length: {axis}");
        // Contacts lie on the surface, on the axis, and the TCP between them.
        let to_gripper = g.object_to_gripper();
        for c in &g.contacts {
            let p = to_gripper * Point3::from(*c);
            assert!(p.y.abs() < 1e-9 && (p.z - g.depth_m).abs() < 1e-9);
            assert!((p.x.abs() - 0.5 * g.width_m).abs() < 1e-9, "{p}");
        }
        // Stable: the axis passes through the centroid.
        let centre = to_gripper * Point3::origin();
        assert!(centre.y.abs() < 0.003 && centre.z.abs() < 0.003, "{centre}");
        // No vertex inside the palm or fingers.
        for v in &mesh.positions {
            let p = to_gripper * v.cast::<f64>();
            assert!(
                !crate::gripper::gripper_boxes(g.width_m + 0.003)
                    .iter()
                    .any(|(lo, hi)| p.x > lo.x
                        && p.y > lo.y
                        && p.z > lo.z
                        && p.x < hi.x
                        && p.y < hi.y
                        && p.z < hi.z)
            );
        }
    }

    #[test]
    fn right_grasp_keeps_away_from_the_left_pads() {
        let mesh = bar();
        let gripper = GripperModel::builtin();
        let left = plan_left_grasp(&gripper, &mesh, &settings()).unwrap();
        let right = plan_right_grasp(&gripper, &mesh, &left, &settings()).unwrap();
        let l = Point3::from(left.center);
        let r = Point3::from(right.center);
        assert!(
            (l - r).norm() > 0.01,
            "right grasp {r} too close to left {l}"
        );
        // Approaches do not point at each other's gripper: the right palm is not on the left palm's side.
        assert!(Vector3::from(left.approach).dot(&Vector3::from(right.approach)) < 0.9);
    }
}
