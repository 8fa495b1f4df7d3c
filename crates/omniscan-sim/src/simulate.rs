//! The scan procedure (paper, "Scanning Procedure"): grasp the object with
//! the left gripper, run the 100-view trajectory, hand over to the right
//! gripper (which takes a grasp exposing what the left fingers covered, with
//! optional seeded slip), run the trajectory again, then the empty-gripper
//! pass for both arms. Writes a capture (format v1) with ground truth.
//!
//! Output is a pure function of the settings: the same seed gives the same
//! bytes, and an interrupted run resumes where it stopped (frames whose files
//! all exist are kept; capture.json is written last).

use std::path::{Path, PathBuf};
use std::str::FromStr;

use nalgebra::{Point3, Translation3, UnitQuaternion};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use omniscan_core::capture::{
    CameraSpec, CaptureFile, CaptureGroundTruth, Frame, FrameGroundTruth, Handover, TrajectoryIndex,
};
use omniscan_core::image_io::{self, DepthMm, Mask, RgbImage};
use omniscan_core::plan::ScanPlanConfig;
use omniscan_core::{Arm, Intrinsics, Pose, RigidTransform};

use crate::SimError;
use crate::builtin::{BUILTIN_OBJECTS, builtin_object};
use crate::defect::{DefectRecord, DefectSpec, plant_defect};
use crate::grasp::{Grasp, GraspSettings, plan_grasp_pair};
use crate::gripper::{GripperModel, TCP_FROM_BASE_M};
use crate::mesh::Mesh;
use crate::raster::{Decal, Instance, Label, Lighting, RenderedView, render};

/// Everything that determines a simulated capture.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimConfig {
    /// `builtin:NAME` or a mesh file (.obj with .mtl and texture, .stl, .ply).
    pub object: String,
    /// Metres per mesh-file unit (0.01 for centimetres); builtins are in metres.
    pub object_scale: Option<f64>,
    pub width: u32,
    pub height: u32,
    pub seed: u64,
    pub defect: Option<String>,
    /// Rotation of the object in the right gripper at handover, degrees.
    pub slip_deg: f64,
    /// Translation of the object in the right gripper at handover, millimetres.
    pub slip_mm: f64,
    /// Samples per pixel along each axis (2 = 4 samples per pixel).
    pub supersample: u32,
    /// Standard deviation of sensor depth noise at 1 m, metres; it grows with
    /// the square of the distance like a stereo camera's. 0 = clean depth.
    pub depth_noise_m_at_1m: f64,
    pub plan: ScanPlanConfig,
    /// Directory with the YuMi meshes (`meshes/finray_finger.stl` ...); built-in approximation if absent.
    pub gripper_dir: Option<PathBuf>,
    /// Camera distance from the scan point, metres; chosen from the object's size if absent.
    pub camera_distance_m: Option<f64>,
    /// Render the empty-gripper pass.
    pub empty_pass: bool,
    /// Calibration error of the recorded gripper poses: each frame's
    /// `gripper_to_world` is recorded turned by a seeded random rotation of
    /// this RMS angle, degrees (the images keep the true pose, which goes
    /// into the frame's `gt`).
    #[serde(default)]
    pub pose_noise_deg: f64,
    /// The same for translation: RMS offset, millimetres.
    #[serde(default)]
    pub pose_noise_mm: f64,
    /// Another robot's gripper, from its URDF (the path absolute or
    /// relative to the working folder); the YuMi when absent.
    #[serde(default)]
    pub robot: Option<omniscan_core::capture::RobotSpec>,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            object: "builtin:flashlight".into(),
            object_scale: None,
            width: 640,
            height: 480,
            seed: 0,
            defect: None,
            slip_deg: 0.0,
            slip_mm: 0.0,
            supersample: 2,
            depth_noise_m_at_1m: 0.002,
            plan: ScanPlanConfig::default(),
            gripper_dir: None,
            camera_distance_m: None,
            empty_pass: true,
            pose_noise_deg: 0.0,
            pose_noise_mm: 0.0,
            robot: None,
        }
    }
}

/// The largest slip at handover the simulator takes: rotation, degrees,
/// and translation, millimetres (a finger pad is about 20 mm wide).
pub const MAX_SLIP_DEG: f64 = 45.0;
/// The largest simulated calibration error of the recorded gripper poses
/// (RMS per frame): rotation, degrees, and translation, millimetres.
pub const MAX_POSE_NOISE_DEG: f64 = 10.0;
pub const MAX_POSE_NOISE_MM: f64 = 50.0;
pub const MAX_SLIP_MM: f64 = 20.0;

/// The object as the simulator holds it.
pub struct SimObject {
    pub mesh: Mesh,
    pub decals: Vec<Decal>,
    pub name: String,
    /// Metres per file unit.
    pub scale: f64,
    /// Translation applied (after scaling) to centre the mesh, metres.
    pub offset_m: [f64; 3],
}

/// Loads `builtin:NAME` or a mesh file, in metres, centred on its bounding box.
pub fn load_object(spec: &str, scale: Option<f64>) -> Result<SimObject, SimError> {
    if let Some(name) = spec.strip_prefix("builtin:") {
        let mesh = builtin_object(name).ok_or_else(|| {
            SimError::Invalid(format!(
                "unknown built-in object `{name}`; built-ins: {}",
                BUILTIN_OBJECTS.join(", ")
            ))
        })?;
        return Ok(SimObject {
            mesh,
            decals: vec![],
            name: name.into(),
            scale: 1.0,
            offset_m: [0.0; 3],
        });
    }
    let path = Path::new(spec);
    // `t_connector` for `builtin:t_connector`: say so rather than "no such file".
    if !path.exists() && BUILTIN_OBJECTS.contains(&spec) {
        return Err(SimError::Invalid(format!(
            "no mesh file `{spec}`; did you mean the built-in object `builtin:{spec}`?"
        )));
    }
    let mut mesh = crate::loaders::load_mesh(path)?;
    let (lo, hi) = mesh.bounds();
    let extent = (hi - lo).max() as f64;
    let scale = match scale {
        Some(s) if s.is_finite() && s > 0.0 => s,
        Some(s) => {
            return Err(SimError::Invalid(format!(
                "--object-scale must be a positive number, got {s}"
            )));
        }
        None if extent > 0.5 => {
            return Err(SimError::mesh(
                path,
                format!(
                    "the mesh is {extent:.3} units across, too big for metres: pass --object-scale \
                     (metres per unit, e.g. 0.01 for centimetres, 0.001 for millimetres)"
                ),
            ));
        }
        None => 1.0,
    };
    let centre = (lo.coords + hi.coords) * 0.5 * scale as f32;
    mesh.scale_translate(scale as f32, -centre);
    let size = (hi - lo).max() as f64 * scale;
    if !(0.01..=0.4).contains(&size) {
        return Err(SimError::mesh(
            path,
            format!(
                "the object is {:.1} cm across after scaling; the simulator handles 1-40 cm",
                size * 100.0
            ),
        ));
    }
    let name = path
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("object")
        .to_string();
    let name = if name == "model" {
        path.parent()
            .and_then(|p| p.file_name())
            .and_then(|s| s.to_str())
            .unwrap_or("model")
            .to_string()
    } else {
        name
    };
    Ok(SimObject {
        mesh,
        decals: vec![],
        name,
        scale,
        offset_m: (-centre.cast::<f64>()).into(),
    })
}

/// A random pose error in the gripper's frame: rotation vector and
/// translation with independent normal components, of RMS angle `deg`
/// degrees and RMS offset `mm` millimetres.
fn calibration_error(rng: &mut ChaCha8Rng, deg: f64, mm: f64) -> Pose {
    let mut normal3 = |rms: f64| {
        let sigma = rms / 3f64.sqrt();
        nalgebra::Vector3::from_fn(|_, _| {
            let u1: f64 = rng.random::<f64>().max(1e-300);
            let u2: f64 = rng.random();
            sigma * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        })
    };
    let rotation = normal3(deg.to_radians());
    let translation = normal3(mm * 1e-3);
    Pose::from_parts(
        Translation3::from(translation),
        UnitQuaternion::from_scaled_axis(rotation),
    )
}

/// One image to render.
#[derive(Debug, Clone)]
pub struct FramePlan {
    pub arm: Arm,
    pub empty: bool,
    pub index: usize,
    pub trajectory: TrajectoryIndex,
    pub gripper_to_world: Pose,
    /// The pose the capture records: `gripper_to_world` with the
    /// configured calibration error (the same without one).
    pub recorded_gripper_to_world: Pose,
    /// Object pose in the holding gripper (None for empty frames).
    pub object_to_gripper: Option<Pose>,
    pub opening_m: f64,
}

impl FramePlan {
    pub fn stem(&self) -> String {
        format!("{}_{:03}", self.arm, self.index)
    }
    fn prefix(&self) -> &'static str {
        if self.empty { "empty/" } else { "" }
    }
    pub fn image_path(&self) -> String {
        format!("{}images/{}.png", self.prefix(), self.stem())
    }
    pub fn depth_path(&self, noisy: bool) -> String {
        if noisy {
            format!("{}depth/{}.png", self.prefix(), self.stem())
        } else {
            self.gt_depth_path()
        }
    }
    pub fn gt_depth_path(&self) -> String {
        format!("{}gt/depth/{}.png", self.prefix(), self.stem())
    }
    pub fn gt_object_mask_path(&self) -> String {
        format!("{}gt/object_mask/{}.png", self.prefix(), self.stem())
    }
    pub fn gt_gripper_mask_path(&self) -> String {
        format!("{}gt/gripper_mask/{}.png", self.prefix(), self.stem())
    }
}

/// Which parts of the scene to draw (all for a capture; subsets for checks).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Layers {
    pub scene: bool,
    pub object: bool,
    pub gripper: bool,
}

impl Layers {
    pub const ALL: Layers = Layers {
        scene: true,
        object: true,
        gripper: true,
    };
}

/// A prepared simulation: object, grasps, robot, scene, camera and frames.
pub struct Simulation {
    pub config: SimConfig,
    pub object: SimObject,
    pub gripper: GripperModel,
    pub scene: Mesh,
    pub lighting: Lighting,
    pub intrinsics: Intrinsics,
    pub camera_to_world: Pose,
    pub left_grasp: Grasp,
    pub right_grasp: Grasp,
    pub object_to_left: Pose,
    /// Where the robot believes the object is in the right gripper (no slip).
    pub object_to_right_commanded: Pose,
    /// Where it really is (with slip).
    pub object_to_right: Pose,
    pub left_handover: Pose,
    pub right_handover: Pose,
    pub defect: Option<DefectRecord>,
    pub slip: serde_json::Value,
    pub frames: Vec<FramePlan>,
}

/// What a run wrote.
#[derive(Debug, Clone, Serialize)]
pub struct SimSummary {
    pub capture: PathBuf,
    pub frames: usize,
    pub empty_frames: usize,
    pub rendered: usize,
    pub resumed: usize,
    pub seconds: f64,
}

impl Simulation {
    /// Loads the object and robot and plans the grasps, handover and frames.
    pub fn new(config: SimConfig) -> Result<Simulation, SimError> {
        config.plan.validate().map_err(SimError::Invalid)?;
        if config.width < 16 || config.height < 16 || config.width > 4096 || config.height > 4096 {
            return Err(SimError::Invalid(format!(
                "image size {}x{} is outside 16-4096 pixels",
                config.width, config.height
            )));
        }
        if !(1..=4).contains(&config.supersample) {
            return Err(SimError::Invalid("supersample must be 1-4".into()));
        }
        for (name, v) in [
            ("slip_deg", config.slip_deg),
            ("slip_mm", config.slip_mm),
            ("depth noise", config.depth_noise_m_at_1m),
            ("pose_noise_deg", config.pose_noise_deg),
            ("pose_noise_mm", config.pose_noise_mm),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(SimError::Invalid(format!(
                    "{name} must be a non-negative number, got {v}"
                )));
            }
        }
        // A slip is the part moving in the fingers, not leaving them: past
        // these the right arm's scan no longer sees the part at all.
        // Calibration error, not a different robot: past these the recorded
        // poses stop describing the scan.
        if config.pose_noise_deg > MAX_POSE_NOISE_DEG || config.pose_noise_mm > MAX_POSE_NOISE_MM {
            return Err(SimError::Invalid(format!(
                "a pose error of {}° / {} mm is no calibration error: at most {MAX_POSE_NOISE_DEG}° and {MAX_POSE_NOISE_MM} mm",
                config.pose_noise_deg, config.pose_noise_mm
            )));
        }
        if config.slip_deg > MAX_SLIP_DEG || config.slip_mm > MAX_SLIP_MM {
            return Err(SimError::Invalid(format!(
                "a slip of {}° / {} mm would move the part out of the gripper: at most {MAX_SLIP_DEG}° and {MAX_SLIP_MM} mm",
                config.slip_deg, config.slip_mm
            )));
        }
        if let Some(scale) = config.object_scale
            && !(scale.is_finite() && scale > 0.0)
        {
            return Err(SimError::Invalid(format!(
                "--object-scale must be a positive number of metres per mesh unit, got {scale}"
            )));
        }
        let defect_spec: Option<DefectSpec> = config
            .defect
            .as_deref()
            .map(DefectSpec::from_str)
            .transpose()
            .map_err(SimError::Invalid)?;
        let mut object = load_object(&config.object, config.object_scale)?;
        let gripper = match (&config.robot, &config.gripper_dir) {
            (Some(_), Some(_)) => {
                return Err(SimError::Invalid(
                    "give the gripper as a robot description or as the YuMi's meshes (--gripper-dir), not both".into(),
                ));
            }
            (Some(robot), None) => GripperModel::from_robot(robot, Path::new("."))?,
            (None, Some(dir)) => GripperModel::from_yumi_dir(dir)?,
            (None, None) => GripperModel::builtin(),
        };
        let settings = GraspSettings::for_gripper(&gripper, config.seed ^ 0x6a5b);
        let (left_grasp, right_grasp) = plan_grasp_pair(&gripper, &object.mesh, &settings)?;
        let defect = match defect_spec {
            Some(spec) => {
                let avoid: Vec<Point3<f64>> = left_grasp
                    .contacts
                    .iter()
                    .chain(&right_grasp.contacts)
                    .map(|c| Point3::from(*c))
                    .collect();
                let (record, decals) = plant_defect(
                    &mut object.mesh,
                    &spec,
                    config.seed ^ 0xd3f3c7,
                    &avoid,
                    0.012 + spec.size_mm * 1e-3,
                )?;
                object.decals = decals;
                Some(record)
            }
            None => None,
        };

        let mut plan = config.plan;
        let (lo, hi) = object.mesh.bounds();
        let radius = 0.5 * (hi - lo).cast::<f64>().norm();
        plan.camera_distance_m = config
            .camera_distance_m
            .unwrap_or_else(|| (5.5 * radius + 0.05).clamp(0.25, 0.9));
        plan.validate().map_err(SimError::Invalid)?;
        let intrinsics = plan.intrinsics(config.width, config.height);
        let camera_to_world = plan.camera_to_world();

        let object_to_left = left_grasp.object_to_gripper();
        let object_to_right_commanded = right_grasp.object_to_gripper();
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed ^ 0x511b);
        let slip_axis = omniscan_core::geometry::random_unit_vector(&mut rng);
        let slip_direction = omniscan_core::geometry::random_unit_vector(&mut rng);
        let slip = Pose::from_parts(
            Translation3::from(slip_direction * config.slip_mm * 1e-3),
            UnitQuaternion::from_axis_angle(
                &nalgebra::Unit::new_normalize(slip_axis),
                config.slip_deg.to_radians(),
            ),
        );
        let object_to_right = slip * object_to_right_commanded;
        let left_handover = plan.left_handover_pose();
        // The robot closes the right gripper where the planned grasp is.
        let right_handover = left_handover * object_to_left * object_to_right_commanded.inverse();

        let mut frames = Vec::new();
        for empty in [false, true] {
            if empty && !config.empty_pass {
                continue;
            }
            for arm in [Arm::Left, Arm::Right] {
                for (index, p) in plan.trajectory(arm).into_iter().enumerate() {
                    let (object_to_gripper, opening_m) = match (empty, arm) {
                        (true, _) => (None, 0.0),
                        (false, Arm::Left) => (Some(object_to_left), left_grasp.width_m),
                        (false, Arm::Right) => (Some(object_to_right), right_grasp.width_m),
                    };
                    frames.push(FramePlan {
                        arm,
                        empty,
                        index,
                        trajectory: p.trajectory,
                        gripper_to_world: p.gripper_to_world.0,
                        recorded_gripper_to_world: p.gripper_to_world.0,
                        object_to_gripper,
                        opening_m,
                    });
                }
            }
        }
        if config.pose_noise_deg > 0.0 || config.pose_noise_mm > 0.0 {
            let mut noise = ChaCha8Rng::seed_from_u64(config.seed ^ 0x9053);
            for f in &mut frames {
                f.recorded_gripper_to_world = f.gripper_to_world
                    * calibration_error(&mut noise, config.pose_noise_deg, config.pose_noise_mm);
            }
        }
        let slip_record = serde_json::json!({
            "rotation_deg": config.slip_deg,
            "translation_mm": config.slip_mm,
            "rotation_axis": slip_axis.as_slice(),
            "translation_direction": slip_direction.as_slice(),
            "in_right_gripper": RigidTransform(slip),
        });
        Ok(Simulation {
            config,
            object,
            gripper,
            scene: crate::scene::scene_mesh(7),
            lighting: crate::scene::lighting(),
            intrinsics,
            camera_to_world,
            left_grasp,
            right_grasp,
            object_to_left,
            object_to_right_commanded,
            object_to_right,
            left_handover,
            right_handover,
            defect,
            slip: slip_record,
            frames,
        })
    }

    /// Renders one frame with the chosen layers at the given supersampling.
    pub fn render_frame(
        &self,
        frame: &FramePlan,
        layers: Layers,
        supersample: u32,
    ) -> RenderedView {
        let parts = self.gripper.parts(frame.opening_m);
        let mut instances = Vec::with_capacity(parts.len() + 2);
        if layers.scene {
            instances.push(Instance {
                mesh: &self.scene,
                to_world: Pose::identity(),
                label: Label::Scene,
                decals: &[],
            });
        }
        if layers.object
            && let Some(object_to_gripper) = frame.object_to_gripper
        {
            instances.push(Instance {
                mesh: &self.object.mesh,
                to_world: frame.gripper_to_world * object_to_gripper,
                label: Label::Object,
                decals: &self.object.decals,
            });
        }
        if layers.gripper {
            for part in &parts {
                instances.push(Instance {
                    mesh: part.mesh,
                    to_world: frame.gripper_to_world * part.tcp_to_part,
                    label: if part.is_arm {
                        Label::Arm
                    } else {
                        Label::Gripper
                    },
                    decals: &[],
                });
            }
        }
        render(
            &instances,
            &self.lighting,
            &self.intrinsics,
            &self.camera_to_world,
            supersample,
        )
    }

    fn noisy(&self) -> bool {
        self.config.depth_noise_m_at_1m > 0.0
    }

    fn frame_files(&self, frame: &FramePlan) -> Vec<String> {
        let mut files = vec![
            frame.image_path(),
            frame.gt_depth_path(),
            frame.gt_gripper_mask_path(),
        ];
        if !frame.empty {
            files.push(frame.gt_object_mask_path());
        }
        if self.noisy() {
            files.push(frame.depth_path(true));
        }
        files
    }

    /// Converts a rendered view into the files of one frame.
    fn encode(&self, frame: &FramePlan, view: &RenderedView) -> Vec<(String, Encoded)> {
        let (w, h) = (view.width, view.height);
        let to_mm = |d: f32| {
            if d > 0.0 {
                (d as f64 * 1000.0).round().clamp(1.0, 65535.0) as u16
            } else {
                0
            }
        };
        let depth = DepthMm {
            width: w,
            height: h,
            data: view.depth.iter().map(|&d| to_mm(d)).collect(),
        };
        let mask = |label: Label| Mask {
            width: w,
            height: h,
            data: view
                .labels
                .iter()
                .map(|&l| if l == label { 255 } else { 0 })
                .collect(),
        };
        let mut out = vec![
            (
                frame.image_path(),
                Encoded::Rgb(RgbImage {
                    width: w,
                    height: h,
                    data: view.rgb.clone(),
                }),
            ),
            (frame.gt_depth_path(), Encoded::Depth(depth)),
            (
                frame.gt_gripper_mask_path(),
                Encoded::Mask(mask(Label::Gripper)),
            ),
        ];
        if !frame.empty {
            out.push((
                frame.gt_object_mask_path(),
                Encoded::Mask(mask(Label::Object)),
            ));
        }
        if self.noisy() {
            // Seeded per frame, so that resuming gives the same bytes.
            let id = frame.index as u64
                + if frame.arm == Arm::Right { 1 << 20 } else { 0 }
                + if frame.empty { 1 << 21 } else { 0 };
            let mut rng = ChaCha8Rng::seed_from_u64(
                self.config.seed ^ 0xde9 ^ id.wrapping_mul(0x9e3779b97f4a7c15),
            );
            let k = self.config.depth_noise_m_at_1m;
            let data = view
                .depth
                .iter()
                .map(|&d| {
                    if d <= 0.0 {
                        return 0;
                    }
                    let z = d as f64;
                    // Box-Muller normal deviate.
                    let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
                    let n = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
                    to_mm((z + n * k * z * z) as f32)
                })
                .collect();
            out.push((
                frame.depth_path(true),
                Encoded::Depth(DepthMm {
                    width: w,
                    height: h,
                    data,
                }),
            ));
        }
        out
    }

    /// The capture description for this simulation.
    pub fn capture_file(&self) -> CaptureFile {
        let noisy = self.noisy();
        let noisy_poses = self.config.pose_noise_deg > 0.0 || self.config.pose_noise_mm > 0.0;
        let to_frame = |f: &FramePlan| Frame {
            file_path: f.image_path(),
            arm: f.arm,
            gripper_to_world: RigidTransform(f.recorded_gripper_to_world),
            depth_path: Some(f.depth_path(noisy)),
            object_mask_path: None,
            gripper_mask_path: None,
            gripper_opening_m: Some(f.opening_m),
            trajectory: Some(f.trajectory),
            gt: Some(FrameGroundTruth {
                object_mask_path: (!f.empty).then(|| f.gt_object_mask_path()),
                gripper_mask_path: Some(f.gt_gripper_mask_path()),
                depth_path: Some(f.gt_depth_path()),
                gripper_to_world: noisy_poses.then_some(RigidTransform(f.gripper_to_world)),
            }),
        };
        let (lo, hi) = self.object.mesh.bounds();
        let mut extra = serde_json::Map::new();
        extra.insert(
            "object".into(),
            serde_json::json!({
                "source": self.config.object,
                "name": self.object.name,
                "scale_m_per_unit": self.object.scale,
                "mesh_offset_m": self.object.offset_m,
                "extent_m": (hi - lo).cast::<f64>().as_slice(),
                "triangles": self.object.mesh.triangles.len(),
            }),
        );
        extra.insert(
            "object_to_right_gripper_commanded".into(),
            serde_json::to_value(RigidTransform(self.object_to_right_commanded)).unwrap(),
        );
        extra.insert(
            "grasps".into(),
            serde_json::json!({ "left": self.left_grasp, "right": self.right_grasp }),
        );
        extra.insert("slip".into(), self.slip.clone());
        extra.insert("defect".into(), serde_json::to_value(&self.defect).unwrap());
        extra.insert(
            "gripper".into(),
            serde_json::json!({ "model": self.gripper.source, "tcp_from_base_m": self.gripper.robot().is_none().then_some(TCP_FROM_BASE_M), "max_opening_m": self.gripper.max_opening_m() }),
        );
        extra.insert(
            "masks".into(),
            serde_json::json!({
                "object": "pixels where most of the supersamples see the object",
                "gripper": "fingers, gripper body and wrist link; the forearm is not included",
                "depth": "z-depth (along the optical axis) of the pixel's majority label, millimetres",
            }),
        );
        CaptureFile {
            version: omniscan_core::capture::CAPTURE_VERSION,
            camera: CameraSpec {
                distortion: None,
                intrinsics: self.intrinsics,
                camera_to_world: RigidTransform(self.camera_to_world),
            },
            handover: Handover {
                left_gripper_to_world: RigidTransform(self.left_handover),
                right_gripper_to_world: RigidTransform(self.right_handover),
            },
            frames: self
                .frames
                .iter()
                .filter(|f| !f.empty)
                .map(to_frame)
                .collect(),
            empty_frames: self
                .frames
                .iter()
                .filter(|f| f.empty)
                .map(to_frame)
                .collect(),
            robot: self
                .config
                .robot
                .as_ref()
                .map(|r| omniscan_core::capture::RobotSpec {
                    // Recorded absolute, so the capture's later stages find it.
                    description: std::path::absolute(&r.description)
                        .map_or_else(|_| r.description.clone(), |p| p.display().to_string()),
                    ..r.clone()
                }),
            gt: Some(CaptureGroundTruth {
                object_to_left_gripper: RigidTransform(self.object_to_left),
                object_to_right_gripper: RigidTransform(self.object_to_right),
                right_to_left: RigidTransform(self.object_to_left * self.object_to_right.inverse()),
                extra,
            }),
            generator: Some(serde_json::json!({
                "name": "omniscan sim",
                "version": env!("CARGO_PKG_VERSION"),
                "config": self.config,
            })),
        }
    }

    /// Renders every frame into `out` and writes `capture.json` last.
    /// `progress(done, total)` is called after each frame.
    pub fn run(
        &self,
        out: &Path,
        progress: &(dyn Fn(usize, usize) + Sync),
    ) -> Result<SimSummary, SimError> {
        let start = std::time::Instant::now();
        std::fs::create_dir_all(out).map_err(|e| omniscan_core::CoreError::io(out, e))?;
        let marker = out.join(".omniscan-sim.json");
        let config_json = serde_json::to_value(&self.config).unwrap();
        if marker.exists() {
            let previous: serde_json::Value = omniscan_core::io::read_json(&marker)?;
            if previous != config_json {
                return Err(SimError::Invalid(format!(
                    "{} holds a simulation with other settings ({}); choose another --out directory or delete it",
                    out.display(),
                    marker.display()
                )));
            }
        } else if out.join(omniscan_core::capture::CAPTURE_FILE).exists() {
            return Err(SimError::Invalid(format!(
                "{} already holds a capture; choose another --out directory",
                out.display()
            )));
        }
        omniscan_core::io::write_json_atomic(&marker, &config_json)?;

        let total = self.frames.len();
        let mut rendered = 0;
        let mut resumed = 0;
        let mut done = 0;
        // Render a few frames (each in parallel), then encode them and
        // write their files in parallel. (Encoding frame by frame on one
        // thread, the noisy depth's two random draws, logarithm and cosine
        // per pixel, was 5 s of a 33 s simulation while the others waited.)
        for chunk in self.frames.chunks(6) {
            let mut views = Vec::new();
            for frame in chunk {
                if self
                    .frame_files(frame)
                    .iter()
                    .all(|f| out.join(f).is_file())
                {
                    resumed += 1;
                } else {
                    let view = self.render_frame(frame, Layers::ALL, self.config.supersample);
                    views.push((frame, view));
                    rendered += 1;
                }
            }
            views
                .par_iter()
                .flat_map_iter(|(frame, view)| self.encode(frame, view))
                .try_for_each(|(rel, data)| data.write(&out.join(rel)))?;
            done += chunk.len();
            progress(done, total);
        }
        let capture = out.join(omniscan_core::capture::CAPTURE_FILE);
        omniscan_core::io::write_json_atomic(&capture, &self.capture_file())?;
        Ok(SimSummary {
            capture,
            frames: self.frames.iter().filter(|f| !f.empty).count(),
            empty_frames: self.frames.iter().filter(|f| f.empty).count(),
            rendered,
            resumed,
            seconds: start.elapsed().as_secs_f64(),
        })
    }
}

/// An image ready to be written.
pub enum Encoded {
    Rgb(RgbImage),
    Mask(Mask),
    Depth(DepthMm),
}

impl Encoded {
    fn write(&self, path: &Path) -> Result<(), SimError> {
        match self {
            Encoded::Rgb(i) => image_io::write_rgb(path, i)?,
            Encoded::Mask(m) => image_io::write_mask(path, m)?,
            Encoded::Depth(d) => image_io::write_depth(path, d)?,
        }
        Ok(())
    }
}
