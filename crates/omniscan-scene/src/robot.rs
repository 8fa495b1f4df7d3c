//! A gripper from a robot's URDF: the link subtree under a chosen root, its
//! visual geometry (STL, OBJ and PLY meshes, boxes, cylinders, spheres),
//! its finger joints (prismatic, revolute, continuous, with `mimic`) and a
//! tool (TCP) frame whose z axis is the approach and x axis the closing
//! direction, as the YuMi model's.
//!
//! The URDF is parsed with `urdf-rs`; forward kinematics is a walk down the
//! tree (a few links, no library needed). Mesh paths resolve the ROS way:
//! `package://NAME/…` in `ROS_PACKAGE_PATH` or `AMENT_PREFIX_PATH`
//! (`share/NAME`), else in a folder `NAME` above the URDF; `file://` and
//! plain paths relative to the URDF's folder.
//!
//! The gripper's state is its opening in metres, as for the YuMi: every
//! non-mimic finger joint moves by the same share of its travel, and the
//! opening of a share is the gap the fingers leave along the TCP's x axis,
//! measured on the meshes (rays from the TCP; twice the one side's for a
//! model with one finger). [`RobotGripper::joint_share`] inverts that table.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use omniscan_core::capture::RobotSpec;

use crate::SceneError;
use crate::mesh::{Material, Mesh, MeshBuilder};

/// How a finger joint moves.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Motion {
    Fixed,
    Revolute,
    Prismatic,
}

#[derive(Debug, Clone)]
struct Joint {
    name: String,
    parent: String,
    child: String,
    origin: Isometry3<f64>,
    axis: Vector3<f64>,
    motion: Motion,
    /// Travel (radians or metres).
    lower: f64,
    upper: f64,
    /// (joint, multiplier, offset): this joint = multiplier x that + offset.
    mimic: Option<(String, f64, f64)>,
}

/// One link's visual geometry in its own frame.
#[derive(Debug, Clone)]
struct LinkMesh {
    link: String,
    mesh: Mesh,
}

/// A gripper from a URDF, ready to be placed at an opening.
#[derive(Debug, Clone)]
pub struct RobotGripper {
    root: String,
    /// Root frame to TCP frame.
    tcp_in_root: Isometry3<f64>,
    /// Joints of the subtree, parents before children.
    joints: Vec<Joint>,
    meshes: Vec<LinkMesh>,
    /// (joint share, opening metres), the share rising from closed to open.
    openings: Vec<(f64, f64)>,
    /// Whether share 0 is the joints' lower limit (else the upper).
    open_at_upper: bool,
}

/// Poses from the URDF's `xyz`/`rpy` (fixed-axis roll, pitch, yaw).
fn pose_of(origin: &urdf_rs::Pose) -> Isometry3<f64> {
    let [x, y, z] = origin.xyz.0;
    let [r, p, yw] = origin.rpy.0;
    Isometry3::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_euler_angles(r, p, yw),
    )
}

/// Where a mesh `filename` of the URDF at `urdf` is.
fn resolve(filename: &str, urdf: &Path) -> Result<PathBuf, String> {
    let dir = urdf.parent().unwrap_or(Path::new("."));
    if let Some(rest) = filename.strip_prefix("package://") {
        let (package, inner) = rest.split_once('/').unwrap_or((rest, ""));
        let mut roots: Vec<PathBuf> = Vec::new();
        for var in ["ROS_PACKAGE_PATH", "AMENT_PREFIX_PATH"] {
            if let Some(paths) = std::env::var_os(var) {
                for p in std::env::split_paths(&paths) {
                    roots.push(p.join(package));
                    roots.push(p.join("share").join(package));
                }
            }
        }
        roots.extend(dir.ancestors().map(|a| a.join(package)));
        return roots
            .iter()
            .map(|r| r.join(inner))
            .find(|p| p.is_file())
            .ok_or_else(|| {
                format!(
                    "{filename}: package `{package}` has no such file in ROS_PACKAGE_PATH, AMENT_PREFIX_PATH or a folder `{package}` above the URDF"
                )
            });
    }
    let path = dir.join(filename.strip_prefix("file://").unwrap_or(filename));
    if path.is_file() {
        Ok(path)
    } else {
        Err(format!(
            "{filename}: no such mesh file ({})",
            path.display()
        ))
    }
}

/// A visual's geometry in its link's frame, coloured `colour`.
fn visual_mesh(visual: &urdf_rs::Visual, urdf: &Path, colour: [f32; 3]) -> Result<Mesh, String> {
    let origin = pose_of(&visual.origin);
    let material = Material::color(colour).with_specular(0.2, 20.0);
    let (mut mesh, scale) = match &visual.geometry {
        urdf_rs::Geometry::Mesh { filename, scale } => {
            let path = resolve(filename, urdf)?;
            let ext = path
                .extension()
                .and_then(|e| e.to_str())
                .unwrap_or("")
                .to_ascii_lowercase();
            if ext == "dae" {
                return Err(format!(
                    "{}: COLLADA (.dae) meshes are not read yet; convert it to STL or OBJ",
                    path.display()
                ));
            }
            let mut mesh = crate::loaders::load_mesh(&path).map_err(|e| e.to_string())?;
            mesh.materials = vec![material];
            mesh.triangle_materials = vec![0; mesh.triangles.len()];
            (mesh, scale.as_ref().map_or([1.0; 3], |s| s.0))
        }
        urdf_rs::Geometry::Box { size } => {
            let [x, y, z] = size.0.map(|v| 0.5 * v as f32);
            let mut b = MeshBuilder::new(material);
            b.cuboid(Point3::new(-x, -y, -z), Point3::new(x, y, z), 0);
            (b.finish(), [1.0; 3])
        }
        urdf_rs::Geometry::Cylinder { radius, length } => {
            let mut b = MeshBuilder::new(material);
            let h = 0.5 * *length as f32;
            crate::gripper::cylinder(&mut b, *radius as f32, -h, h, 32, 0);
            (b.finish(), [1.0; 3])
        }
        other => {
            return Err(format!(
                "visual geometry {other:?} is not drawn (mesh, box, cylinder)"
            ));
        }
    };
    for p in &mut mesh.positions {
        let scaled = Point3::new(
            p.x as f64 * scale[0],
            p.y as f64 * scale[1],
            p.z as f64 * scale[2],
        );
        *p = (origin * scaled).cast::<f32>();
    }
    mesh.normals.clear();
    mesh.compute_normals();
    Ok(mesh)
}

impl RobotGripper {
    /// The gripper `spec` describes; `base` is the folder a relative URDF
    /// path is relative to (the capture's).
    pub fn load(spec: &RobotSpec, base: &Path) -> Result<RobotGripper, SceneError> {
        let path = base.join(&spec.urdf);
        let fail = |message: String| SceneError::mesh(&path, message);
        let robot =
            urdf_rs::read_file(&path).map_err(|e| fail(format!("not a readable URDF: {e}")))?;
        let links: BTreeMap<&str, &urdf_rs::Link> =
            robot.links.iter().map(|l| (l.name.as_str(), l)).collect();
        if !links.contains_key(spec.gripper_root.as_str()) {
            return Err(fail(format!(
                "no link `{}` (--gripper-root); its links are {}",
                spec.gripper_root,
                links.keys().copied().collect::<Vec<_>>().join(", ")
            )));
        }
        let colours: BTreeMap<&str, [f32; 3]> = robot
            .materials
            .iter()
            .filter_map(|m| m.color.as_ref().map(|c| (m.name.as_str(), rgb(&c.rgba.0))))
            .collect();
        // The subtree, parents before children.
        let mut in_tree = vec![spec.gripper_root.clone()];
        let mut joints = Vec::new();
        let mut i = 0;
        while i < in_tree.len() {
            let parent = in_tree[i].clone();
            for j in robot.joints.iter().filter(|j| j.parent.link == parent) {
                if in_tree.contains(&j.child.link) {
                    return Err(fail(format!(
                        "link {} is reached twice under {} (joint {}): a URDF is a tree",
                        j.child.link, spec.gripper_root, j.name
                    )));
                }
                joints.push(joint(j).map_err(&fail)?);
                in_tree.push(j.child.link.clone());
            }
            i += 1;
        }
        for j in &joints {
            if let Some((target, _, _)) = &j.mimic
                && !joints.iter().any(|k| &k.name == target)
            {
                return Err(fail(format!(
                    "joint {} mimics {target}, which is not under {}",
                    j.name, spec.gripper_root
                )));
            }
        }
        let mut meshes = Vec::new();
        for name in &in_tree {
            let Some(link) = links.get(name.as_str()) else {
                return Err(fail(format!(
                    "a joint names link {name}, which the URDF lacks"
                )));
            };
            for visual in &link.visual {
                let colour = visual
                    .material
                    .as_ref()
                    .and_then(|m| {
                        m.color
                            .as_ref()
                            .map(|c| rgb(&c.rgba.0))
                            .or_else(|| colours.get(m.name.as_str()).copied())
                    })
                    .unwrap_or([0.6, 0.6, 0.6]);
                let mesh = visual_mesh(visual, &path, colour)
                    .map_err(|e| fail(format!("link {name}: {e}")))?;
                meshes.push(LinkMesh {
                    link: name.clone(),
                    mesh,
                });
            }
        }
        let mut gripper = RobotGripper {
            root: spec.gripper_root.clone(),
            tcp_in_root: Isometry3::identity(),
            joints,
            meshes,
            openings: Vec::new(),
            open_at_upper: true,
        };
        gripper.tcp_in_root = gripper.tcp(spec).map_err(&fail)?;
        gripper.measure_openings().map_err(&fail)?;
        Ok(gripper)
    }

    fn tcp(&self, spec: &RobotSpec) -> Result<Isometry3<f64>, String> {
        match (&spec.tcp_link, spec.tcp_offset_m) {
            (Some(link), None) => {
                let mut pose = Isometry3::identity();
                let mut current = link.clone();
                while current != self.root {
                    let j = self
                        .joints
                        .iter()
                        .find(|j| j.child == current)
                        .ok_or_else(|| {
                            format!(
                                "the TCP link {link} is not under the gripper root {}",
                                self.root
                            )
                        })?;
                    if j.motion != Motion::Fixed {
                        return Err(format!(
                            "the TCP link {link} moves with joint {}; it must be fixed to {}",
                            j.name, self.root
                        ));
                    }
                    pose = j.origin * pose;
                    current = j.parent.clone();
                }
                Ok(pose)
            }
            (None, Some([x, y, z])) if [x, y, z].iter().all(|v| v.is_finite()) => {
                Ok(Isometry3::translation(x, y, z))
            }
            (None, Some(v)) => Err(format!(
                "the TCP offset must be three finite metres, got {v:?}"
            )),
            _ => Err(
                "give the TCP as a link or as an offset from the gripper root, one of the two"
                    .into(),
            ),
        }
    }

    /// Each joint's position at `share` of the finger travel (0 closed,
    /// 1 open); mimic joints follow theirs.
    fn positions(&self, share: f64) -> BTreeMap<&str, f64> {
        let s = if self.open_at_upper {
            share
        } else {
            1.0 - share
        };
        let mut q: BTreeMap<&str, f64> = BTreeMap::new();
        for j in self
            .joints
            .iter()
            .filter(|j| j.motion != Motion::Fixed && j.mimic.is_none())
        {
            q.insert(&j.name, j.lower + s * (j.upper - j.lower));
        }
        for j in &self.joints {
            if let Some((target, multiplier, offset)) = &j.mimic {
                let v = q.get(target.as_str()).copied().unwrap_or(0.0);
                q.insert(&j.name, multiplier * v + offset);
            }
        }
        q
    }

    /// Every link's pose in the TCP frame at `share` of the travel.
    fn link_poses(&self, share: f64) -> BTreeMap<&str, Isometry3<f64>> {
        let q = self.positions(share);
        let mut poses: BTreeMap<&str, Isometry3<f64>> = BTreeMap::new();
        poses.insert(&self.root, self.tcp_in_root.inverse());
        for j in &self.joints {
            let parent = poses[j.parent.as_str()];
            let v = q.get(j.name.as_str()).copied().unwrap_or(0.0);
            let motion = match j.motion {
                Motion::Fixed => Isometry3::identity(),
                Motion::Revolute => Isometry3::from_parts(
                    Translation3::identity(),
                    UnitQuaternion::from_scaled_axis(j.axis * v),
                ),
                Motion::Prismatic => {
                    Isometry3::translation(j.axis.x * v, j.axis.y * v, j.axis.z * v)
                }
            };
            poses.insert(&j.child, parent * j.origin * motion);
        }
        poses
    }

    /// The gap along the TCP's x axis at `share`: rays from the TCP to the
    /// first finger surface each way (the smallest over a few rays).
    fn gap_at(&self, share: f64) -> Option<f64> {
        let poses = self.link_poses(share);
        let mut gap: Option<f64> = None;
        // Rays across the pads' width at the TCP's height (a slanted finger's
        // gap differs above and below it).
        for dy in [0.0, 0.002, -0.002, 0.004, -0.004] {
            let mut side = [f64::INFINITY; 2];
            for m in &self.meshes {
                let to_link = poses[m.link.as_str()].inverse();
                let origin = to_link * Point3::new(0.0, dy, 0.0);
                let direction = to_link * Vector3::x();
                for (t, _) in m.mesh.line_hits(&origin, &direction) {
                    let k = usize::from(t < 0.0);
                    side[k] = side[k].min(t.abs());
                }
            }
            let width = match (side[0].is_finite(), side[1].is_finite()) {
                (true, true) => side[0] + side[1],
                (true, false) => 2.0 * side[0],
                (false, true) => 2.0 * side[1],
                (false, false) => continue,
            };
            gap = Some(gap.map_or(width, |g: f64| g.min(width)));
        }
        gap
    }

    /// The opening at shares 0..1 of the travel, closed to open.
    fn measure_openings(&mut self) -> Result<(), String> {
        if !self
            .joints
            .iter()
            .any(|j| j.motion != Motion::Fixed && j.mimic.is_none())
        {
            return Err(format!("no finger joint moves under {}", self.root));
        }
        const SAMPLES: usize = 33;
        let table: Vec<(f64, f64)> = (0..SAMPLES)
            .map(|i| {
                let share = i as f64 / (SAMPLES - 1) as f64;
                self.gap_at(share).map(|g| (share, g)).ok_or_else(|| {
                    format!(
                        "no finger surface crosses the TCP's x axis at {:.0}% of the travel; the TCP belongs between the pads, x the closing direction",
                        share * 100.0
                    )
                })
            })
            .collect::<Result<_, _>>()?;
        let (first, last) = (table[0].1, table[SAMPLES - 1].1);
        self.open_at_upper = last >= first;
        self.openings = if self.open_at_upper {
            table
        } else {
            table.iter().rev().map(|&(s, g)| (1.0 - s, g)).collect()
        };
        Ok(())
    }

    /// The widest opening, metres.
    pub fn max_opening_m(&self) -> f64 {
        self.openings.iter().map(|o| o.1).fold(0.0, f64::max)
    }

    /// The share of the travel that opens the fingers `opening_m` apart
    /// (linear between the measured openings; clamped to the travel).
    pub fn joint_share(&self, opening_m: f64) -> f64 {
        let t = &self.openings;
        if opening_m <= t[0].1 {
            return 0.0;
        }
        for w in t.windows(2) {
            let ((s0, g0), (s1, g1)) = (w[0], w[1]);
            if opening_m <= g1 && g1 > g0 {
                return s0 + (s1 - s0) * (opening_m - g0) / (g1 - g0);
            }
        }
        1.0
    }

    /// Every link's geometry in the TCP frame with the fingers `opening_m` apart.
    pub fn placed(&self, opening_m: f64) -> Vec<(&Mesh, Isometry3<f64>)> {
        let poses = self.link_poses(self.joint_share(opening_m));
        self.meshes
            .iter()
            .map(|m| (&m.mesh, poses[m.link.as_str()]))
            .collect()
    }
}

fn rgb(rgba: &[f64; 4]) -> [f32; 3] {
    [rgba[0] as f32, rgba[1] as f32, rgba[2] as f32]
}

fn joint(j: &urdf_rs::Joint) -> Result<Joint, String> {
    let motion = match j.joint_type {
        urdf_rs::JointType::Fixed => Motion::Fixed,
        urdf_rs::JointType::Revolute | urdf_rs::JointType::Continuous => Motion::Revolute,
        urdf_rs::JointType::Prismatic => Motion::Prismatic,
        ref other => {
            return Err(format!(
                "joint {} is {other:?}; a gripper's joints are fixed, revolute, continuous or prismatic",
                j.name
            ));
        }
    };
    let axis = Vector3::from(j.axis.xyz.0);
    if motion != Motion::Fixed && (axis.norm().is_nan() || axis.norm() <= 1e-9) {
        return Err(format!("joint {} has a zero axis", j.name));
    }
    let (mut lower, mut upper) = (j.limit.lower, j.limit.upper);
    if j.joint_type == urdf_rs::JointType::Continuous {
        (lower, upper) = (0.0, std::f64::consts::TAU);
    }
    Ok(Joint {
        name: j.name.clone(),
        parent: j.parent.link.clone(),
        child: j.child.link.clone(),
        origin: pose_of(&j.origin),
        axis: if motion == Motion::Fixed {
            axis
        } else {
            axis.normalize()
        },
        motion,
        lower,
        upper,
        mimic: j.mimic.as_ref().map(|m| {
            (
                m.joint.clone(),
                m.multiplier.unwrap_or(1.0),
                m.offset.unwrap_or(0.0),
            )
        }),
    })
}
