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
use crate::collision::{CollisionPart, Solid, Voxels};
use crate::mesh::{Material, Mesh, MeshBuilder};

/// How a finger joint moves.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Motion {
    Fixed,
    Revolute,
    Prismatic,
}

/// A joint: the child's pose is parent · origin · motion(q) · post.
#[derive(Debug, Clone)]
pub(crate) struct Joint {
    pub name: String,
    pub parent: String,
    pub child: String,
    pub origin: Isometry3<f64>,
    /// After the motion: MJCF's joints turn about a point of the child body
    /// (`origin` ends there, `post` comes back); identity in a URDF.
    pub post: Isometry3<f64>,
    pub axis: Vector3<f64>,
    pub motion: Motion,
    /// Travel (radians or metres).
    pub lower: f64,
    pub upper: f64,
    /// (joint, multiplier, offset): this joint = multiplier x that + offset.
    pub mimic: Option<(String, f64, f64)>,
    /// Driven by the opening (else set by a loop closure, or held at 0).
    pub actuated: bool,
}

impl Joint {
    /// A link fixed to its parent at `origin`.
    pub fn fixed(name: String, parent: &str, child: &str, origin: Isometry3<f64>) -> Joint {
        Joint {
            name,
            parent: parent.into(),
            child: child.into(),
            origin,
            post: Isometry3::identity(),
            axis: Vector3::z(),
            motion: Motion::Fixed,
            lower: 0.0,
            upper: 0.0,
            mimic: None,
            actuated: false,
        }
    }
}

/// One link's visual geometry in its own frame.
#[derive(Debug, Clone)]
pub(crate) struct LinkMesh {
    pub link: String,
    pub mesh: Mesh,
}

/// A closed kinematic loop (MJCF's `connect`): a point of one link stays on
/// a point of another.
#[derive(Debug, Clone)]
pub(crate) struct Closure {
    pub link_a: String,
    pub anchor_a: Point3<f64>,
    pub link_b: String,
    pub anchor_b: Point3<f64>,
}

/// A gripper's description, as a URDF or MJCF file gives it.
#[derive(Debug, Clone, Default)]
pub(crate) struct Tree {
    /// Joints of the subtree under the root, parents before children.
    pub joints: Vec<Joint>,
    pub meshes: Vec<LinkMesh>,
    pub closures: Vec<Closure>,
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
    closures: Vec<Closure>,
    /// (joint share, opening metres), the share rising from closed to open.
    openings: Vec<(f64, f64)>,
    /// Whether share 0 is the joints' lower limit (else the upper).
    open_at_upper: bool,
    /// Each mesh's voxels in its link's frame, for collision tests: made
    /// when the grasp planner first asks (masking never does).
    volumes: std::sync::OnceLock<Vec<LinkVolume>>,
}

/// A link mesh's voxels in the link's own frame, and whether the link moves
/// with the fingers (else it is part of the palm).
#[derive(Debug, Clone)]
struct LinkVolume {
    link: String,
    voxels: Voxels,
    moves: bool,
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
        let path = base.join(&spec.description);
        let fail = |message: String| SceneError::mesh(&path, message);
        let text = std::fs::read_to_string(&path)
            .map_err(|e| SceneError::Core(omniscan_core::CoreError::io(&path, e)))?;
        let tree = if text.contains("<mujoco") {
            crate::mjcf::tree(&text, &path, &spec.gripper_root).map_err(&fail)?
        } else {
            urdf_tree(&text, &path, &spec.gripper_root).map_err(&fail)?
        };
        let mut gripper = RobotGripper {
            root: spec.gripper_root.clone(),
            tcp_in_root: Isometry3::identity(),
            joints: tree.joints,
            meshes: tree.meshes,
            closures: tree.closures,
            openings: Vec::new(),
            open_at_upper: true,
            volumes: std::sync::OnceLock::new(),
        };
        gripper.tcp_in_root = gripper.tcp(spec).map_err(&fail)?;
        gripper.measure_openings().map_err(&fail)?;
        Ok(gripper)
    }

    /// The voxels of every non-empty mesh; a link moves if its pose differs
    /// between the closed and the open gripper.
    fn link_volumes(&self) -> Vec<LinkVolume> {
        let (closed, open) = (self.link_poses(0.0), self.link_poses(1.0));
        self.meshes
            .iter()
            .filter(|m| !m.mesh.positions.is_empty())
            .map(|m| {
                let (a, b) = (closed[m.link.as_str()], open[m.link.as_str()]);
                let moves = (a.translation.vector - b.translation.vector).norm() > 1e-9
                    || a.rotation.angle_to(&b.rotation) > 1e-9;
                LinkVolume {
                    link: m.link.clone(),
                    voxels: Voxels::of_mesh(&m.mesh),
                    moves,
                }
            })
            .collect()
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
                "the TCP offset must be three finite numbers of metres, X,Y,Z (got {v:?})"
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
        for j in self.joints.iter().filter(|j| j.actuated) {
            q.insert(&j.name, j.lower + s * (j.upper - j.lower));
        }
        self.follow_mimics(&mut q);
        if !self.closures.is_empty() {
            self.close_loops(&mut q);
        }
        q
    }

    fn follow_mimics<'s>(&'s self, q: &mut BTreeMap<&'s str, f64>) {
        for j in &self.joints {
            if let Some((target, multiplier, offset)) = &j.mimic {
                let v = q.get(target.as_str()).copied().unwrap_or(0.0);
                q.insert(&j.name, multiplier * v + offset);
            }
        }
    }

    /// The loop closures' residual: each closure's two points apart, metres.
    fn closure_residual(&self, q: &BTreeMap<&str, f64>) -> Vec<f64> {
        let poses = self.forward(q);
        self.closures
            .iter()
            .flat_map(|c| {
                let a = poses[c.link_a.as_str()] * c.anchor_a;
                let b = poses[c.link_b.as_str()] * c.anchor_b;
                (a - b).iter().copied().collect::<Vec<_>>()
            })
            .collect()
    }

    /// Sets the joints neither driven nor mimicking so that every loop
    /// closes: damped Gauss-Newton from the rest pose, the smallest motion
    /// of those joints among the solutions (an underactuated finger's
    /// spring keeps it near its rest pose too).
    fn close_loops<'s>(&'s self, q: &mut BTreeMap<&'s str, f64>) {
        let free: Vec<&str> = self
            .joints
            .iter()
            .filter(|j| j.motion != Motion::Fixed && !j.actuated && j.mimic.is_none())
            .map(|j| j.name.as_str())
            .collect();
        let n = free.len();
        if n == 0 {
            return;
        }
        const H: f64 = 1e-7;
        // Small: it picks among the exact closures, it must not trade one off.
        const DAMPING: f64 = 1e-10;
        let set = |q: &mut BTreeMap<&'s str, f64>, x: &nalgebra::DVector<f64>| {
            for (k, name) in free.iter().enumerate() {
                q.insert(name, x[k]);
            }
            self.follow_mimics(q);
        };
        let mut x = nalgebra::DVector::<f64>::zeros(n);
        for _ in 0..50 {
            set(q, &x);
            let r = nalgebra::DVector::from_vec(self.closure_residual(q));
            if r.norm() < 1e-9 {
                break;
            }
            let mut jac = nalgebra::DMatrix::<f64>::zeros(r.len(), n);
            for k in 0..n {
                let mut xh = x.clone();
                xh[k] += H;
                set(q, &xh);
                let rh = nalgebra::DVector::from_vec(self.closure_residual(q));
                jac.set_column(k, &((rh - &r) / H));
            }
            // Minimise |r + J dx|² + DAMPING |x + dx|².
            let lhs = jac.transpose() * &jac + nalgebra::DMatrix::<f64>::identity(n, n) * DAMPING;
            let rhs = -(jac.transpose() * &r) - &x * DAMPING;
            let Some(dx) = lhs.lu().solve(&rhs) else {
                break;
            };
            x += dx;
        }
        set(q, &x);
    }

    /// Every link's pose in the root frame at joint positions `q`.
    fn forward(&self, q: &BTreeMap<&str, f64>) -> BTreeMap<&str, Isometry3<f64>> {
        let mut poses: BTreeMap<&str, Isometry3<f64>> = BTreeMap::new();
        poses.insert(&self.root, Isometry3::identity());
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
            poses.insert(&j.child, parent * j.origin * motion * j.post);
        }
        poses
    }

    /// Every link's pose in the TCP frame at `share` of the travel.
    fn link_poses(&self, share: f64) -> BTreeMap<&str, Isometry3<f64>> {
        let to_tcp = self.tcp_in_root.inverse();
        self.forward(&self.positions(share))
            .into_iter()
            .map(|(link, pose)| (link, to_tcp * pose))
            .collect()
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
        if !self.joints.iter().any(|j| j.actuated) {
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

    /// The opening, metres, with the finger joint `joint` (a driven one) at
    /// `position`; `None` if `joint` is not one.
    pub fn opening_at(&self, joint: &str, position: f64) -> Option<f64> {
        let j = self.joints.iter().find(|j| j.actuated && j.name == joint)?;
        let travel = j.upper - j.lower;
        let s = if travel.abs() > 0.0 {
            ((position - j.lower) / travel).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let share = if self.open_at_upper { s } else { 1.0 - s };
        let t = &self.openings;
        let k = t.partition_point(|(s, _)| *s < share).clamp(1, t.len() - 1);
        let ((s0, g0), (s1, g1)) = (t[k - 1], t[k]);
        Some(g0 + (g1 - g0) * (share - s0) / (s1 - s0))
    }

    /// Every link mesh's voxels placed in the TCP frame with the fingers
    /// `opening_m` apart.
    pub fn collision_parts(&self, opening_m: f64) -> Vec<CollisionPart<'_>> {
        let poses = self.link_poses(self.joint_share(opening_m));
        self.volumes
            .get_or_init(|| self.link_volumes())
            .iter()
            .map(|v| CollisionPart {
                tcp_to_part: poses[v.link.as_str()],
                solid: Solid::Voxels(&v.voxels),
                finger: v.moves,
            })
            .collect()
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
        post: Isometry3::identity(),
        actuated: motion != Motion::Fixed && j.mimic.is_none(),
    })
}

fn urdf_tree(text: &str, path: &Path, root: &str) -> Result<Tree, String> {
    let fail = |m: String| m;
    let robot = urdf_rs::read_from_string(text).map_err(|e| format!("not a readable URDF: {e}"))?;
    let links: BTreeMap<&str, &urdf_rs::Link> =
        robot.links.iter().map(|l| (l.name.as_str(), l)).collect();
    if !links.contains_key(root) {
        return Err(fail(format!(
            "no link `{}` (--gripper-root); its links are {}",
            root,
            links.keys().copied().collect::<Vec<_>>().join(", ")
        )));
    }
    let colours: BTreeMap<&str, [f32; 3]> = robot
        .materials
        .iter()
        .filter_map(|m| m.color.as_ref().map(|c| (m.name.as_str(), rgb(&c.rgba.0))))
        .collect();
    // The subtree, parents before children.
    let mut in_tree = vec![root.to_string()];
    let mut joints = Vec::new();
    let mut i = 0;
    while i < in_tree.len() {
        let parent = in_tree[i].clone();
        for j in robot.joints.iter().filter(|j| j.parent.link == parent) {
            if in_tree.contains(&j.child.link) {
                return Err(fail(format!(
                    "link {} is reached twice under {} (joint {}): a URDF is a tree",
                    j.child.link, root, j.name
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
                j.name, root
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
            let mesh =
                visual_mesh(visual, path, colour).map_err(|e| fail(format!("link {name}: {e}")))?;
            meshes.push(LinkMesh {
                link: name.clone(),
                mesh,
            });
        }
    }
    Ok(Tree {
        joints,
        meshes,
        closures: Vec::new(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The 2F-85's four-bar linkage from `../shared` closes at every
    /// opening: the follower's pin stays on the coupler's.
    #[test]
    #[ignore = "needs ../shared"]
    fn the_2f85_linkage_closes_along_the_travel() {
        let shared = std::env::var("OMNISCAN_SHARED").map_or_else(
            |_| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared"),
            PathBuf::from,
        );
        let spec = RobotSpec {
            description: shared
                .join("data/grippers/robotiq_2f85/2f85.xml")
                .display()
                .to_string(),
            gripper_root: "base_mount".into(),
            tcp_link: None,
            tcp_offset_m: Some([0.0, 0.0, 0.13]),
        };
        let gripper = RobotGripper::load(&spec, Path::new("/")).unwrap();
        assert_eq!(gripper.closures.len(), 1);
        let mut previous = f64::INFINITY;
        for i in 0..=10 {
            let share = f64::from(i) / 10.0;
            let q = gripper.positions(share);
            let r = gripper.closure_residual(&q);
            let gap = r.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!(gap < 1e-7, "share {share}: the loop is {gap} m open");
            // Share 0 is closed: the opening only grows.
            let opening = gripper.gap_at(share).unwrap();
            assert!(
                i == 0 || opening > previous - 1e-9,
                "{opening} after {previous}"
            );
            previous = opening;
        }
    }
}
