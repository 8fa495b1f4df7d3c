//! The robot's gripper: the ABB YuMi servo gripper with the fin-ray fingers
//! Omni-Scan uses, its wrist link (link 7) and a forearm.
//!
//! Geometry follows `yumi.urdf`: the gripper base sits 7 mm past link 7's
//! flange; each finger is mounted 83.7 mm out from the base at y = ±6.5 mm
//! and slides along x, up to 25 mm each (50 mm opening). With the meshes of
//! `shared/data/grippers/yumi` given (`--gripper-dir`), those are rendered;
//! otherwise a built-in approximation with the same dimensions (including the
//! fin-ray's open rib structure) is used.
//!
//! Frames: the gripper (TCP) frame has its origin midway between the finger
//! pads at [`TCP_FROM_BASE_M`] out from the base, z along the approach, x the
//! closing direction. The opening is the distance between the pads.

use std::path::Path;

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

use omniscan_core::capture::RobotSpec;

use crate::SceneError;
use crate::collision::{CollisionPart, Solid};
use crate::mesh::{Material, Mesh, MeshBuilder};
use crate::robot::RobotGripper;

/// Distance from the gripper base to the finger mounts (URDF), metres.
pub const FINGER_MOUNT_M: f64 = 0.0837;
/// Length of a fin-ray finger from its mount to its tip, metres.
pub const FINGER_LENGTH_M: f64 = 0.0595;
/// Width of a finger across the closing direction, metres.
pub const FINGER_WIDTH_M: f64 = 0.025;
/// TCP: where an object is held, out from the base along z, metres.
pub const TCP_FROM_BASE_M: f64 = 0.118;
/// Largest opening between the pads (2 x 25 mm of finger travel), metres.
pub const MAX_OPENING_M: f64 = 0.050;
/// Distance of the finger's contact face from its mount origin along x (finray_finger.stl).
const PAD_OFFSET_M: f64 = 0.0007;

/// The robot's gripper: the YuMi's parts, or another robot's gripper from
/// its description ([`crate::robot`]).
#[derive(Debug, Clone)]
pub struct GripperModel {
    pub source: String,
    kind: GripperKind,
}

#[derive(Debug, Clone)]
enum GripperKind {
    Yumi(Box<YumiParts>),
    Robot(Box<RobotGripper>),
}

/// The YuMi's meshes in their own (URDF) frames.
#[derive(Debug, Clone)]
struct YumiParts {
    base: Mesh,
    finger: Mesh,
    wrist: Mesh,
    forearm: Mesh,
}

/// A gripper part placed relative to the TCP frame.
pub struct PlacedPart<'a> {
    pub mesh: &'a Mesh,
    pub tcp_to_part: Isometry3<f64>,
    pub is_arm: bool,
}

impl GripperModel {
    /// The YuMi meshes from `dir` (a copy of `shared/data/grippers/yumi`).
    pub fn from_yumi_dir(dir: &Path) -> Result<GripperModel, SceneError> {
        let load = |name: &str, color: [f32; 3], specular: f32| -> Result<Mesh, SceneError> {
            let path = dir.join("meshes").join(name);
            if !path.exists() {
                return Err(SceneError::mesh(
                    &path,
                    "missing: --gripper-dir must hold meshes/finray_finger.stl, gripper_base.stl and link_7.stl",
                ));
            }
            let mut mesh = crate::loaders::load_mesh(&path)?;
            mesh.materials = vec![Material::color(color).with_specular(specular, 20.0)];
            Ok(mesh)
        };
        Ok(GripperModel {
            source: dir.display().to_string(),
            kind: GripperKind::Yumi(Box::new(YumiParts {
                base: load("gripper_base.stl", [0.82, 0.82, 0.80], 0.2)?,
                finger: load("finray_finger.stl", [0.16, 0.16, 0.17], 0.1)?,
                wrist: load("link_7.stl", [0.62, 0.62, 0.62], 0.25)?,
                forearm: forearm_mesh(),
            })),
        })
    }

    /// The gripper of the robot `spec` describes (its URDF relative to `base`).
    pub fn from_robot(spec: &RobotSpec, base: &Path) -> Result<GripperModel, SceneError> {
        let robot = RobotGripper::load(spec, base)?;
        Ok(GripperModel {
            source: format!("{} ({})", spec.description, spec.gripper_root),
            kind: GripperKind::Robot(Box::new(robot)),
        })
    }

    /// Another robot's gripper; `None` for the YuMi.
    pub fn robot(&self) -> Option<&RobotGripper> {
        match &self.kind {
            GripperKind::Robot(robot) => Some(robot),
            GripperKind::Yumi(_) => None,
        }
    }

    /// The widest opening between the pads, metres.
    pub fn max_opening_m(&self) -> f64 {
        self.robot().map_or(MAX_OPENING_M, |r| r.max_opening_m())
    }

    /// A built-in approximation of the YuMi gripper with the URDF's dimensions.
    pub fn builtin() -> GripperModel {
        let grey = Material::color([0.82, 0.82, 0.80]).with_specular(0.2, 20.0);
        let mut base = MeshBuilder::new(grey);
        let dark = base.add_material(Material::color([0.25, 0.25, 0.27]));
        base.cuboid(
            Point3::new(-0.0416, -0.0345, 0.0),
            Point3::new(0.0416, 0.0345, 0.0931),
            0,
        );
        // Finger rails and a cable boss give the body some structure.
        base.cuboid(
            Point3::new(-0.030, -0.0125, 0.0931),
            Point3::new(0.030, 0.0125, 0.0960),
            dark,
        );
        base.cuboid(
            Point3::new(-0.012, 0.0345, 0.02),
            Point3::new(0.012, 0.040, 0.05),
            dark,
        );
        let mut base = base.finish();
        base.compute_normals();

        let mut finger =
            MeshBuilder::new(Material::color([0.16, 0.16, 0.17]).with_specular(0.1, 20.0));
        let (y0, y1) = (-0.006f32, 0.019f32);
        // Mounting block.
        finger.cuboid(
            Point3::new(-0.005, y0, 0.0),
            Point3::new(0.0245, y1, 0.008),
            0,
        );
        // Fin-ray: inner contact beam, slanted outer beam, ribs between them.
        beam(
            &mut finger,
            [0.0007 - 0.0025, 0.008],
            [0.0007 - 0.0025, 0.0595],
            0.0025,
            y0,
            y1,
        );
        beam(
            &mut finger,
            [-0.022, 0.008],
            [-0.003, 0.0595],
            0.002,
            y0,
            y1,
        );
        for z in [0.018f32, 0.028, 0.038, 0.048] {
            let outer_x = -0.022 + (0.019) * (z - 0.008) / 0.0515;
            beam(
                &mut finger,
                [outer_x, z - 0.003],
                [-0.0018, z],
                0.0015,
                y0,
                y1,
            );
        }
        let mut finger = finger.finish();
        finger.compute_normals();

        let mut wrist =
            MeshBuilder::new(Material::color([0.62, 0.62, 0.62]).with_specular(0.25, 24.0));
        cylinder(&mut wrist, 0.0315, -0.031, 0.0125, 48, 0);
        let mut wrist = wrist.finish();
        wrist.compute_normals();
        GripperModel {
            source: "builtin".into(),
            kind: GripperKind::Yumi(Box::new(YumiParts {
                base,
                finger,
                wrist,
                forearm: forearm_mesh(),
            })),
        }
    }

    /// Where each part sits, relative to the TCP, for a given pad opening (metres).
    pub fn parts(&self, opening: f64) -> Vec<PlacedPart<'_>> {
        let yumi = match &self.kind {
            GripperKind::Yumi(parts) => parts,
            GripperKind::Robot(robot) => {
                return robot
                    .placed(opening)
                    .into_iter()
                    .map(|(mesh, tcp_to_part)| PlacedPart {
                        mesh,
                        tcp_to_part,
                        is_arm: false,
                    })
                    .collect();
            }
        };
        let q = (0.5 * opening).clamp(0.0, 0.5 * MAX_OPENING_M + 0.01);
        let tcp_to_base = Isometry3::translation(0.0, 0.0, -TCP_FROM_BASE_M);
        let half_turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI);
        // finger_r: no rotation, pad facing +x, slides towards -x as it opens.
        let finger_r = Isometry3::from_parts(
            Translation3::new(-q - PAD_OFFSET_M, -0.0065, FINGER_MOUNT_M),
            UnitQuaternion::identity(),
        );
        // finger_l: turned half about z, pad facing -x.
        let finger_l = Isometry3::from_parts(
            Translation3::new(q + PAD_OFFSET_M, 0.0065, FINGER_MOUNT_M),
            half_turn,
        );
        let wrist = Isometry3::from_parts(Translation3::new(0.0, 0.0, -0.007), half_turn);
        vec![
            PlacedPart {
                mesh: &yumi.base,
                tcp_to_part: tcp_to_base,
                is_arm: false,
            },
            PlacedPart {
                mesh: &yumi.finger,
                tcp_to_part: tcp_to_base * finger_r,
                is_arm: false,
            },
            PlacedPart {
                mesh: &yumi.finger,
                tcp_to_part: tcp_to_base * finger_l,
                is_arm: false,
            },
            PlacedPart {
                mesh: &yumi.wrist,
                tcp_to_part: tcp_to_base * wrist,
                is_arm: false,
            },
            PlacedPart {
                mesh: &yumi.forearm,
                tcp_to_part: tcp_to_base * Isometry3::translation(0.0, 0.0, -0.038),
                is_arm: true,
            },
        ]
    }
}

/// The forearm (links 5-6), a tapered cylinder running back from the wrist.
fn forearm_mesh() -> Mesh {
    let mut b = MeshBuilder::new(Material::color([0.80, 0.80, 0.78]).with_specular(0.2, 16.0));
    let dark = b.add_material(Material::color([0.3, 0.3, 0.32]));
    cylinder(&mut b, 0.036, -0.26, 0.0, 48, 0);
    cylinder(&mut b, 0.0375, -0.07, -0.05, 48, dark);
    let mut m = b.finish();
    m.compute_normals();
    m
}

/// A closed cylinder about z from `z0` to `z1`.
pub fn cylinder(
    b: &mut MeshBuilder,
    radius: f32,
    z0: f32,
    z1: f32,
    segments: usize,
    material: u16,
) {
    let base = b.mesh.positions.len() as u32;
    for &z in &[z0, z1] {
        for s in 0..segments {
            let a = std::f32::consts::TAU * s as f32 / segments as f32;
            b.vertex(
                Point3::new(radius * a.cos(), radius * a.sin(), z),
                Vector3::z(),
                [s as f32 / segments as f32, 0.0],
            );
        }
    }
    let centre0 = b.vertex(Point3::new(0.0, 0.0, z0), -Vector3::z(), [0.5, 0.5]);
    let centre1 = b.vertex(Point3::new(0.0, 0.0, z1), Vector3::z(), [0.5, 0.5]);
    let n = segments as u32;
    for s in 0..n {
        let (a, c) = (base + s, base + (s + 1) % n);
        b.quad(a, c, c + n, a + n, material);
        b.triangle(centre0, c, a, material);
        b.triangle(centre1, a + n, c + n, material);
    }
}

/// A straight beam of rectangular section between two (x, z) points, `thickness`
/// across the beam in the x-z plane, spanning y0..y1.
fn beam(b: &mut MeshBuilder, from: [f32; 2], to: [f32; 2], thickness: f32, y0: f32, y1: f32) {
    let d = Vector3::new(to[0] - from[0], 0.0, to[1] - from[1]);
    let side = Vector3::new(d.z, 0.0, -d.x).normalize() * thickness;
    let p = |v: [f32; 2], s: f32, y: f32| Point3::new(v[0] + side.x * s, y, v[1] + side.z * s);
    let corners = [
        p(from, 0.0, y0),
        p(to, 0.0, y0),
        p(to, 1.0, y0),
        p(from, 1.0, y0),
        p(from, 0.0, y1),
        p(to, 0.0, y1),
        p(to, 1.0, y1),
        p(from, 1.0, y1),
    ];
    let ids: Vec<u32> = corners
        .iter()
        .map(|c| b.vertex(*c, Vector3::z(), [0.0, 0.0]))
        .collect();
    let faces = [
        [0, 1, 2, 3],
        [7, 6, 5, 4],
        [0, 4, 5, 1],
        [1, 5, 6, 2],
        [2, 6, 7, 3],
        [3, 7, 4, 0],
    ];
    for f in faces {
        b.quad(ids[f[0]], ids[f[1]], ids[f[2]], ids[f[3]], 0);
    }
}

impl GripperModel {
    /// The gripper's parts for collision tests with its pads `opening`
    /// apart (metres): for the YuMi, the boxes of [`gripper_boxes`]; for
    /// another robot, its link meshes' voxels ([`crate::collision`]).
    pub fn collision_parts(&self, opening: f64) -> Vec<CollisionPart<'_>> {
        match &self.kind {
            GripperKind::Robot(robot) => robot.collision_parts(opening),
            GripperKind::Yumi(_) => gripper_boxes(opening)
                .into_iter()
                .enumerate()
                .map(|(i, (lo, hi))| CollisionPart {
                    tcp_to_part: Isometry3::identity(),
                    solid: Solid::Cuboid { lo, hi },
                    finger: i > 0,
                })
                .collect(),
        }
    }

    /// Points on the finger pads (TCP frame) with the pads `opening` apart:
    /// where the fingers touch a held object. For another robot than the
    /// YuMi, the surface points of its moving links within 2 mm of the pad
    /// planes x = ±opening/2 (all their surface points if none are).
    pub fn pad_points(&self, opening: f64) -> Vec<Point3<f64>> {
        if self.robot().is_none() {
            return yumi_pad_points(opening);
        }
        let fingers: Vec<Point3<f64>> = self
            .collision_parts(opening)
            .iter()
            .filter(|part| part.finger)
            .flat_map(|part| part.surface_points())
            .collect();
        let on_pads: Vec<Point3<f64>> = fingers
            .iter()
            .filter(|p| (p.x.abs() - 0.5 * opening).abs() < 0.002)
            .copied()
            .collect();
        if on_pads.is_empty() { fingers } else { on_pads }
    }
}

/// The YuMi's pads in its TCP frame for an opening, as points.
fn yumi_pad_points(opening: f64) -> Vec<Point3<f64>> {
    let z0 = FINGER_MOUNT_M - TCP_FROM_BASE_M;
    let mut pts = Vec::new();
    for side in [-1.0, 1.0] {
        for i in 0..=6 {
            for j in 0..=4 {
                let y = -0.5 * FINGER_WIDTH_M + FINGER_WIDTH_M * j as f64 / 4.0;
                let z = z0 + FINGER_LENGTH_M * i as f64 / 6.0;
                pts.push(Point3::new(side * 0.5 * opening, y, z));
            }
        }
    }
    pts
}

/// Axis-aligned boxes (in the TCP frame) that the YuMi gripper occupies at a
/// given opening: used to test grasps for collisions. Each is (min, max).
pub fn gripper_boxes(opening: f64) -> Vec<(Point3<f64>, Point3<f64>)> {
    let q = 0.5 * opening;
    let z_mount = FINGER_MOUNT_M - TCP_FROM_BASE_M;
    let z_tip = z_mount + FINGER_LENGTH_M;
    let hw = 0.5 * FINGER_WIDTH_M;
    vec![
        // Palm (gripper body) and wrist.
        (
            Point3::new(-0.0416, -0.0345, -TCP_FROM_BASE_M - 0.05),
            Point3::new(0.0416, 0.0345, z_mount),
        ),
        // Fingers, outward of the pads.
        (
            Point3::new(-q - 0.024, -hw, z_mount),
            Point3::new(-q, hw, z_tip),
        ),
        (
            Point3::new(q, -hw, z_mount),
            Point3::new(q + 0.024, hw, z_tip),
        ),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pads_sit_at_the_opening() {
        let model = GripperModel::builtin();
        for opening in [0.0, 0.02, 0.04] {
            let parts = model.parts(opening);
            // Inner faces of the fingers in the TCP frame: the finger mesh's
            // largest x (right finger) and, mirrored, the left finger's smallest.
            let xs = |part: &PlacedPart| -> (f64, f64) {
                let xs: Vec<f64> = part
                    .mesh
                    .positions
                    .iter()
                    .filter(|p| p.z > 0.01)
                    .map(|p| (part.tcp_to_part * p.cast::<f64>()).x)
                    .collect();
                (
                    xs.iter().cloned().fold(f64::INFINITY, f64::min),
                    xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
                )
            };
            let (_, right_inner) = xs(&parts[1]);
            let (left_inner, _) = xs(&parts[2]);
            assert!((right_inner + 0.5 * opening).abs() < 1e-4, "{right_inner}");
            assert!((left_inner - 0.5 * opening).abs() < 1e-4, "{left_inner}");
        }
    }
}
