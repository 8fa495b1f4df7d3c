//! A ROS 2 recording of a scan to a capture (`docs/ros2.md`).
//!
//! One pass over the bag writes every colour and depth image as PNG into a
//! hidden folder beside the output and keeps the small messages (TF,
//! camera_info, phases, joint states); then each image is given its phase,
//! its gripper pose (TF at the image's stamp) and the depth image nearest
//! in time, the capture is validated, and the folder is renamed into place:
//! an import that fails leaves nothing at the output.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use omniscan_core::capture::{
    Arm, CAPTURE_VERSION, CameraSpec, Capture, CaptureFile, Frame, Handover, RobotSpec,
};
use omniscan_core::geometry::{Pose, RigidTransform, pose_difference};
use omniscan_core::image_io::{DepthMm, RgbImage, write_depth, write_rgb};
use omniscan_core::lens::Distortion;
use omniscan_core::{CoreError, Intrinsics};
use serde::{Deserialize, Serialize};

use crate::RosError;
use crate::bag::{Bag, BagMessage};
use crate::msgs::{self, CameraInfo, JointState, TfMessage};
use crate::tf::{TfTree, seconds};

/// Where in the recording the scan is; every field is a flag of
/// `omniscan import ros2`, and `Default` is the documented convention.
#[derive(clap::Args, Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Ros2ImportSettings {
    /// Colour images: `sensor_msgs/msg/Image` (rgb8, bgr8, rgba8, bgra8,
    /// mono8) or `sensor_msgs/msg/CompressedImage` (JPEG, PNG).
    #[arg(long, default_value_t = Ros2ImportSettings::default().image_topic)]
    pub image_topic: String,
    /// Depth images registered to the colour camera (16UC1 millimetres or
    /// 32FC1 metres); used when the bag has them.
    #[arg(long, default_value_t = Ros2ImportSettings::default().depth_topic)]
    pub depth_topic: String,
    /// The colour camera's `sensor_msgs/msg/CameraInfo`.
    #[arg(long, default_value_t = Ros2ImportSettings::default().camera_info_topic)]
    pub camera_info_topic: String,
    /// The scan's phases, `std_msgs/msg/String`, each in force from the
    /// time it was recorded on.
    #[arg(long, default_value_t = Ros2ImportSettings::default().phase_topic)]
    pub phase_topic: String,
    /// `sensor_msgs/msg/JointState`, for the finger opening; used when present.
    #[arg(long, default_value_t = Ros2ImportSettings::default().joint_states_topic)]
    pub joint_states_topic: String,
    /// The frame the capture's poses are in.
    #[arg(long, default_value_t = Ros2ImportSettings::default().world_frame)]
    pub world_frame: String,
    /// The left gripper's TCP frame (what `gripper_to_world` means).
    #[arg(long, default_value_t = Ros2ImportSettings::default().left_gripper_frame)]
    pub left_gripper_frame: String,
    /// The right gripper's TCP frame.
    #[arg(long, default_value_t = Ros2ImportSettings::default().right_gripper_frame)]
    pub right_gripper_frame: String,
    /// The longest gap between TF samples interpolated over, seconds.
    #[arg(long, default_value_t = Ros2ImportSettings::default().max_tf_gap_s)]
    pub max_tf_gap_s: f64,
    /// A depth image belongs to the colour image whose stamp is within this, seconds.
    #[arg(long, default_value_t = Ros2ImportSettings::default().depth_sync_s)]
    pub depth_sync_s: f64,
    /// The joint whose position gives the left gripper's opening.
    #[arg(long, default_value_t = Ros2ImportSettings::default().left_finger_joint)]
    pub left_finger_joint: String,
    /// The joint whose position gives the right gripper's opening.
    #[arg(long, default_value_t = Ros2ImportSettings::default().right_finger_joint)]
    pub right_finger_joint: String,
    /// Finger opening per unit of the joint's position, metres per joint
    /// unit (2 for the YuMi, whose joint is each finger's travel in metres).
    #[arg(long, default_value_t = Ros2ImportSettings::default().opening_m_per_joint_unit)]
    pub opening_m_per_joint_unit: f64,
    /// The camera must stay put: its pose may drift this much over the scan,
    /// millimetres (and a tenth of this in degrees).
    #[arg(long, default_value_t = Ros2ImportSettings::default().camera_drift_mm)]
    pub camera_drift_mm: f64,
}

impl Default for Ros2ImportSettings {
    fn default() -> Self {
        Ros2ImportSettings {
            image_topic: "/camera/color/image_raw".into(),
            depth_topic: "/camera/depth/image_raw".into(),
            camera_info_topic: "/camera/color/camera_info".into(),
            phase_topic: "/omniscan/phase".into(),
            joint_states_topic: "/joint_states".into(),
            world_frame: "world".into(),
            left_gripper_frame: "left_gripper".into(),
            right_gripper_frame: "right_gripper".into(),
            max_tf_gap_s: 0.1,
            depth_sync_s: 0.01,
            left_finger_joint: "gripper_l_joint".into(),
            right_finger_joint: "gripper_r_joint".into(),
            opening_m_per_joint_unit: 2.0,
            camera_drift_mm: 1.0,
        }
    }
}

/// A phase of the scan, as published on the phase topic.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    Left,
    Handover,
    Right,
    EmptyLeft,
    EmptyRight,
}

impl Phase {
    fn parse(text: &str) -> Option<Phase> {
        Some(match text.trim() {
            "left" => Phase::Left,
            "handover" => Phase::Handover,
            "right" => Phase::Right,
            "empty_left" => Phase::EmptyLeft,
            "empty_right" => Phase::EmptyRight,
            _ => return None,
        })
    }
}

/// What the import made.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ImportReport {
    pub capture: PathBuf,
    pub left_frames: usize,
    pub right_frames: usize,
    pub empty_frames: usize,
    /// Images before the first phase message, or during the handover.
    pub skipped_images: usize,
    pub frames_with_depth: usize,
    pub frames_with_opening: usize,
    /// The lens model recorded, `None` for a pinhole.
    pub distortion: Option<Distortion>,
    pub seconds: f64,
}

/// An image of the bag, already written as PNG.
#[derive(Debug, Clone)]
struct Stamped {
    stamp_ns: i64,
    frame_id: String,
    path: String,
    size: (u32, u32),
}

/// Everything kept from the pass over the bag.
#[derive(Debug, Default)]
struct Recording {
    images: Vec<Stamped>,
    depths: Vec<Stamped>,
    camera_info: Option<CameraInfo>,
    tf: TfTree,
    tf_messages: usize,
    phases: Vec<(i64, Phase)>,
    joints: BTreeMap<String, Vec<(i64, f64)>>,
    joint_names: Vec<String>,
    /// Decoded images not yet written (PNG encoding runs in parallel).
    pending: Vec<(PathBuf, Decoded)>,
}

#[derive(Debug)]
enum Decoded {
    Rgb(RgbImage),
    Depth(DepthMm),
}

/// Images encoded together: enough for both cores, little memory.
const PENDING_IMAGES: usize = 16;

impl Recording {
    fn write_pending(&mut self) -> Result<(), RosError> {
        use rayon::prelude::*;
        std::mem::take(&mut self.pending)
            .par_iter()
            .try_for_each(|(path, image)| match image {
                Decoded::Rgb(rgb) => write_rgb(path, rgb),
                Decoded::Depth(depth) => write_depth(path, depth),
            })?;
        Ok(())
    }

    /// Records a decoded image as the next of its kind (`images/` or
    /// `depth/NNNNNN.png`) and queues it to be written under `staging`.
    fn stage(
        &mut self,
        staging: &Path,
        stamp_ns: i64,
        frame_id: String,
        image: Decoded,
    ) -> Result<(), RosError> {
        let (list, folder, size) = match &image {
            Decoded::Rgb(rgb) => (&mut self.images, "images", (rgb.width, rgb.height)),
            Decoded::Depth(depth) => (&mut self.depths, "depth", (depth.width, depth.height)),
        };
        let path = format!("{folder}/{:06}.png", list.len());
        list.push(Stamped {
            stamp_ns,
            frame_id,
            path: path.clone(),
            size,
        });
        self.pending.push((staging.join(path), image));
        if self.pending.len() >= PENDING_IMAGES {
            self.write_pending()?;
        }
        Ok(())
    }
}

/// Another robot than the YuMi: what the capture records, and the finger
/// opening (metres) at a finger joint's position, `None` for a joint that
/// is not one of the gripper's finger joints.
pub struct Robot<'a> {
    pub spec: RobotSpec,
    pub opening_m: &'a dyn Fn(&str, f64) -> Option<f64>,
}

/// Imports the bag at `bag` into a new capture at `out` (which must not
/// exist), with `robot`'s gripper (the YuMi when `None`, its opening
/// `--opening-m-per-joint-unit` times the joint's position).
/// `progress(images)` is called as images are read.
pub fn import_ros2(
    bag: &Path,
    out: &Path,
    settings: &Ros2ImportSettings,
    robot: Option<&Robot>,
    progress: &dyn Fn(usize),
) -> Result<ImportReport, RosError> {
    let start = Instant::now();
    check_settings(settings)?;
    if out.exists() {
        return Err(RosError::Invalid(format!(
            "{} already exists; choose another --out (an import never writes into an existing folder)",
            out.display()
        )));
    }
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(parent).map_err(|e| CoreError::io(parent, e))?;
    let staging = tempfile::Builder::new()
        .prefix(".omniscan-import-")
        .tempdir_in(parent)
        .map_err(|e| CoreError::io(parent, e))?;
    let bag = Bag::open(bag)?;
    let recording = read_recording(&bag, staging.path(), settings, progress)?;
    let (mut file, mut report) = assemble(&bag, &recording, settings, robot)?;
    file.robot = robot.map(|r| r.spec.clone());
    for unused in unused_images(&recording, &file) {
        let path = staging.path().join(unused);
        std::fs::remove_file(&path).map_err(|e| CoreError::io(&path, e))?;
    }
    let capture = Capture {
        dir: staging.path().to_path_buf(),
        file,
    };
    capture.save()?;
    Capture::load(staging.path())?;
    let staged = staging.keep();
    std::fs::rename(&staged, out).map_err(|e| {
        let _ = std::fs::remove_dir_all(&staged);
        CoreError::io(out, e)
    })?;
    report.capture = out.to_path_buf();
    report.seconds = start.elapsed().as_secs_f64();
    Ok(report)
}

fn check_settings(s: &Ros2ImportSettings) -> Result<(), RosError> {
    let positive = [
        ("--max-tf-gap-s", s.max_tf_gap_s),
        ("--depth-sync-s", s.depth_sync_s),
        ("--opening-m-per-joint-unit", s.opening_m_per_joint_unit),
        ("--camera-drift-mm", s.camera_drift_mm),
    ];
    for (flag, v) in positive {
        if !(v.is_finite() && v > 0.0) {
            return Err(RosError::Invalid(format!(
                "{flag} must be a positive number, got {v}"
            )));
        }
    }
    if s.left_gripper_frame == s.right_gripper_frame {
        return Err(RosError::Invalid(format!(
            "the left and right gripper frames are both {}",
            s.left_gripper_frame
        )));
    }
    Ok(())
}

/// Where a message went wrong: the bag, topic and time.
fn at(bag: &Bag, m: &BagMessage, message: impl std::fmt::Display) -> RosError {
    RosError::bag(
        &bag.path,
        format!("{} at {:.6} s: {message}", m.topic, seconds(m.log_time_ns)),
    )
}

fn expect_type(bag: &Bag, m: &BagMessage, types: &[&str]) -> Result<(), RosError> {
    if types.contains(&m.type_name) {
        return Ok(());
    }
    Err(at(
        bag,
        m,
        format!("is {}, expected {}", m.type_name, types.join(" or ")),
    ))
}

fn read_recording(
    bag: &Bag,
    staging: &Path,
    settings: &Ros2ImportSettings,
    progress: &dyn Fn(usize),
) -> Result<Recording, RosError> {
    let s = settings;
    let topics = [
        s.image_topic.as_str(),
        s.depth_topic.as_str(),
        s.camera_info_topic.as_str(),
        s.phase_topic.as_str(),
        s.joint_states_topic.as_str(),
        "/tf",
        "/tf_static",
    ];
    let mut rec = Recording::default();
    let all_topics = bag.for_each(&|topic| topics.contains(&topic), &mut |m| {
        read_message(bag, &m, staging, settings, &mut rec)?;
        if m.topic == s.image_topic {
            progress(rec.images.len());
        }
        Ok(())
    })?;
    rec.write_pending()?;
    rec.tf.finish();
    rec.phases.sort_by_key(|(t, _)| *t);
    rec.images.sort_by_key(|i| i.stamp_ns);
    rec.depths.sort_by_key(|i| i.stamp_ns);
    for series in rec.joints.values_mut() {
        series.sort_by_key(|a| a.0);
    }
    let missing = [
        (s.image_topic.as_str(), rec.images.is_empty()),
        (s.camera_info_topic.as_str(), rec.camera_info.is_none()),
        ("/tf or /tf_static", rec.tf_messages == 0),
        (s.phase_topic.as_str(), rec.phases.is_empty()),
    ];
    if let Some((topic, _)) = missing.iter().find(|(_, empty)| *empty) {
        let listed: Vec<String> = all_topics
            .iter()
            .map(|(name, ty)| format!("{name} ({ty})"))
            .collect();
        return Err(RosError::bag(
            &bag.path,
            format!(
                "no messages on {topic}; the bag has: {} (each topic is a flag of `omniscan import ros2`)",
                if listed.is_empty() {
                    "nothing".to_string()
                } else {
                    listed.join(", ")
                }
            ),
        ));
    }
    Ok(rec)
}

fn read_message(
    bag: &Bag,
    m: &BagMessage,
    staging: &Path,
    s: &Ros2ImportSettings,
    rec: &mut Recording,
) -> Result<(), RosError> {
    let decode_error = |e: String| at(bag, m, e);
    if m.topic == s.image_topic {
        expect_type(
            bag,
            m,
            &["sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"],
        )?;
        let (stamp, frame_id, image) = decode_colour(m).map_err(decode_error)?;
        rec.stage(staging, stamp, frame_id, Decoded::Rgb(image))?;
    } else if m.topic == s.depth_topic {
        expect_type(bag, m, &["sensor_msgs/msg/Image"])?;
        let (stamp, frame_id, depth) = decode_depth(m.data).map_err(decode_error)?;
        rec.stage(staging, stamp, frame_id, Decoded::Depth(depth))?;
    } else if m.topic == s.camera_info_topic {
        expect_type(bag, m, &["sensor_msgs/msg/CameraInfo"])?;
        let info: CameraInfo = msgs::decode(m.data).map_err(decode_error)?;
        if rec.camera_info.is_none() {
            rec.camera_info = Some(info);
        }
    } else if m.topic == "/tf" || m.topic == "/tf_static" {
        expect_type(bag, m, &["tf2_msgs/msg/TFMessage"])?;
        let tf: TfMessage = msgs::decode(m.data).map_err(decode_error)?;
        for t in &tf.transforms {
            rec.tf
                .add(t, m.topic == "/tf_static")
                .map_err(decode_error)?;
        }
        rec.tf_messages += 1;
    } else if m.topic == s.phase_topic {
        expect_type(bag, m, &["std_msgs/msg/String"])?;
        let text: msgs::StringMessage = msgs::decode(m.data).map_err(decode_error)?;
        let phase = Phase::parse(&text.data).ok_or_else(|| {
            at(
                bag,
                m,
                format!(
                    "unknown phase `{}`; one of left, handover, right, empty_left, empty_right",
                    text.data
                ),
            )
        })?;
        rec.phases.push((m.log_time_ns, phase));
    } else if m.topic == s.joint_states_topic {
        expect_type(bag, m, &["sensor_msgs/msg/JointState"])?;
        let state: JointState = msgs::decode(m.data).map_err(decode_error)?;
        if state.position.len() < state.name.len() {
            return Err(at(bag, m, "has fewer positions than joint names"));
        }
        for (name, &position) in state.name.iter().zip(&state.position) {
            if !rec.joint_names.contains(name) {
                rec.joint_names.push(name.clone());
            }
            if [&s.left_finger_joint, &s.right_finger_joint].contains(&name) {
                rec.joints
                    .entry(name.clone())
                    .or_default()
                    .push((state.header.stamp.ns(), position));
            }
        }
    }
    Ok(())
}

/// The rows of an uncompressed image, `channels` bytes per pixel.
fn rows(image: &msgs::Image, channels: u32) -> Result<Vec<&[u8]>, String> {
    let row = image.width as usize * channels as usize;
    let step = image.step as usize;
    let needed = step * image.height as usize;
    if image.width == 0 || image.height == 0 || step < row || image.data.len() < needed {
        return Err(format!(
            "a {}x{} {} image with step {} needs {needed} bytes, has {}",
            image.width,
            image.height,
            image.encoding,
            image.step,
            image.data.len()
        ));
    }
    Ok((0..image.height as usize)
        .map(|r| &image.data[r * step..r * step + row])
        .collect())
}

fn decode_colour(m: &BagMessage) -> Result<(i64, String, RgbImage), String> {
    if m.type_name == "sensor_msgs/msg/CompressedImage" {
        let c: msgs::CompressedImage = msgs::decode(m.data)?;
        let decoded = image::load_from_memory(&c.data)
            .map_err(|e| format!("compressed image ({}) does not decode: {e}", c.format))?
            .to_rgb8();
        let (width, height) = decoded.dimensions();
        return Ok((
            c.header.stamp.ns(),
            c.header.frame_id,
            RgbImage {
                width,
                height,
                data: decoded.into_raw(),
            },
        ));
    }
    let image: msgs::Image = msgs::decode(m.data)?;
    // Byte order of the channels in each pixel: where R, G, B are.
    let (channels, order): (u32, [usize; 3]) = match image.encoding.as_str() {
        "rgb8" => (3, [0, 1, 2]),
        "bgr8" => (3, [2, 1, 0]),
        "rgba8" => (4, [0, 1, 2]),
        "bgra8" => (4, [2, 1, 0]),
        "mono8" | "8UC1" => (1, [0, 0, 0]),
        other => {
            return Err(format!(
                "colour encoding `{other}` is not read (rgb8, bgr8, rgba8, bgra8, mono8)"
            ));
        }
    };
    let mut data = Vec::with_capacity(image.width as usize * image.height as usize * 3);
    for row in rows(&image, channels)? {
        for px in row.chunks_exact(channels as usize) {
            data.extend(order.iter().map(|&c| px[c]));
        }
    }
    Ok((
        image.header.stamp.ns(),
        image.header.frame_id.clone(),
        RgbImage {
            width: image.width,
            height: image.height,
            data,
        },
    ))
}

fn decode_depth(bytes: &[u8]) -> Result<(i64, String, DepthMm), String> {
    let image: msgs::Image = msgs::decode(bytes)?;
    let big = image.is_bigendian != 0;
    let data: Vec<u16> = match image.encoding.as_str() {
        "16UC1" | "mono16" => rows(&image, 2)?
            .iter()
            .flat_map(|row| row.chunks_exact(2))
            .map(|b| {
                let b = [b[0], b[1]];
                if big {
                    u16::from_be_bytes(b)
                } else {
                    u16::from_le_bytes(b)
                }
            })
            .collect(),
        "32FC1" => rows(&image, 4)?
            .iter()
            .flat_map(|row| row.chunks_exact(4))
            .map(|b| {
                let b = [b[0], b[1], b[2], b[3]];
                let metres = if big {
                    f32::from_be_bytes(b)
                } else {
                    f32::from_le_bytes(b)
                };
                // No measurement (NaN, 0, negative) and beyond 65.535 m are 0.
                let mm = (f64::from(metres) * 1000.0).round();
                if mm.is_finite() && mm > 0.0 && mm <= f64::from(u16::MAX) {
                    mm as u16
                } else {
                    0
                }
            })
            .collect(),
        other => {
            return Err(format!(
                "depth encoding `{other}` is not read (16UC1 millimetres, 32FC1 metres)"
            ));
        }
    };
    Ok((
        image.header.stamp.ns(),
        image.header.frame_id.clone(),
        DepthMm {
            width: image.width,
            height: image.height,
            data,
        },
    ))
}

/// The camera's intrinsics and lens from camera_info. ROS's `K` puts the
/// first pixel's centre at (0, 0) (OpenCV's convention); a capture's
/// intrinsics put it at (0.5, 0.5).
fn camera_model(
    info: &CameraInfo,
    topic: &str,
) -> Result<(Intrinsics, Option<Distortion>), String> {
    let k = &info.k;
    let intrinsics = Intrinsics {
        width: info.width,
        height: info.height,
        fx: k[0],
        fy: k[4],
        cx: k[2] + 0.5,
        cy: k[5] + 0.5,
    };
    intrinsics.validate().map_err(|e| format!("{topic}: {e}"))?;
    if info.binning_x > 1 || info.binning_y > 1 || info.roi.width != 0 || info.roi.height != 0 {
        return Err(format!(
            "{topic}: binning and a region of interest are not supported; record the full image"
        ));
    }
    let d = |i: usize| info.d.get(i).copied().unwrap_or(0.0);
    if info.d.iter().all(|&c| c == 0.0) {
        return Ok((intrinsics, None));
    }
    let distortion = match info.distortion_model.as_str() {
        "plumb_bob" | "rational_polynomial" => {
            if (5..8).any(|i| d(i) != 0.0) {
                return Err(format!(
                    "{topic}: the rational model's k4, k5, k6 ({}, {}, {}) are not supported",
                    d(5),
                    d(6),
                    d(7)
                ));
            }
            Distortion::RadialTangential {
                k1: d(0),
                k2: d(1),
                p1: d(2),
                p2: d(3),
                k3: d(4),
            }
        }
        "equidistant" => Distortion::Fisheye {
            k1: d(0),
            k2: d(1),
            k3: d(2),
            k4: d(3),
        },
        other => {
            return Err(format!(
                "{topic}: distortion model `{other}` is not read (plumb_bob, rational_polynomial, equidistant)"
            ));
        }
    };
    omniscan_core::lens::check_distortion(&distortion, &intrinsics)
        .map_err(|e| format!("{topic}: {e}"))?;
    Ok((intrinsics, Some(distortion)))
}

/// The phase in force at `t_ns`: the last one recorded at or before it.
fn phase_at(phases: &[(i64, Phase)], t_ns: i64) -> Option<Phase> {
    let n = phases.partition_point(|(t, _)| *t <= t_ns);
    n.checked_sub(1).map(|i| phases[i].1)
}

/// A joint's position at `t_ns`, linear between its samples, held past the ends.
fn joint_at(series: &[(i64, f64)], t_ns: i64) -> Option<f64> {
    let after = series.partition_point(|(t, _)| *t < t_ns);
    match (after.checked_sub(1).map(|i| series[i]), series.get(after)) {
        (_, Some(&(t1, p1))) if t1 == t_ns => Some(p1),
        (Some((t0, p0)), Some(&(t1, p1))) => {
            let s = (t_ns - t0) as f64 / (t1 - t0) as f64;
            Some(p0 + s * (p1 - p0))
        }
        (Some((_, p)), None) | (None, Some(&(_, p))) => Some(p),
        (None, None) => None,
    }
}

fn assemble(
    bag: &Bag,
    rec: &Recording,
    s: &Ros2ImportSettings,
    robot: Option<&Robot>,
) -> Result<(CaptureFile, ImportReport), RosError> {
    let fail = |message: String| RosError::bag(&bag.path, message);
    let info = rec.camera_info.as_ref().expect("checked by read_recording");
    let (intrinsics, distortion) = camera_model(info, &s.camera_info_topic).map_err(fail)?;
    for (topic, list) in [(&s.image_topic, &rec.images), (&s.depth_topic, &rec.depths)] {
        if let Some(bad) = list.iter().find(|i| i.size != (info.width, info.height)) {
            return Err(fail(format!(
                "{topic} at {:.6} s: the image is {}x{}, but {} says {}x{}",
                seconds(bad.stamp_ns),
                bad.size.0,
                bad.size.1,
                s.camera_info_topic,
                info.width,
                info.height
            )));
        }
    }
    let gap = (s.max_tf_gap_s * 1e9) as i64;
    let lookup = |frame: &str, t: i64| {
        rec.tf.lookup(&s.world_frame, frame, t, gap).map_err(|e| {
            fail(format!(
                "looking up {frame} in {} at {:.6} s: {e}",
                s.world_frame,
                seconds(t)
            ))
        })
    };
    let gripper_frame = |arm: Arm| match arm {
        Arm::Left => &s.left_gripper_frame,
        Arm::Right => &s.right_gripper_frame,
    };
    let finger_joint = |arm: Arm| match arm {
        Arm::Left => &s.left_finger_joint,
        Arm::Right => &s.right_finger_joint,
    };
    if !rec.joint_names.is_empty() {
        for arm in [Arm::Left, Arm::Right] {
            if !rec.joints.contains_key(finger_joint(arm)) {
                return Err(fail(format!(
                    "{} has no joint {} (the {arm} finger joint); it names {}",
                    s.joint_states_topic,
                    finger_joint(arm),
                    rec.joint_names.join(", ")
                )));
            }
        }
    }

    let mut frames = Vec::new();
    let mut empty_frames = Vec::new();
    let mut skipped = 0;
    let mut camera: Option<(Pose, &Stamped)> = None;
    for image in &rec.images {
        let (arm, empty) = match phase_at(&rec.phases, image.stamp_ns) {
            Some(Phase::Left) => (Arm::Left, false),
            Some(Phase::Right) => (Arm::Right, false),
            Some(Phase::EmptyLeft) => (Arm::Left, true),
            Some(Phase::EmptyRight) => (Arm::Right, true),
            Some(Phase::Handover) | None => {
                skipped += 1;
                continue;
            }
        };
        let camera_pose = lookup(&image.frame_id, image.stamp_ns)?;
        match &camera {
            None => camera = Some((camera_pose, image)),
            Some((first, first_image)) => {
                let (rad, metres) = pose_difference(first, &camera_pose);
                let (deg, mm) = (rad.to_degrees(), metres * 1000.0);
                if mm > s.camera_drift_mm || deg > 0.1 * s.camera_drift_mm {
                    return Err(fail(format!(
                        "the camera ({}) moves by {mm:.2} mm, {deg:.3}° between {:.6} s and {:.6} s; a capture's camera is fixed (--camera-drift-mm)",
                        image.frame_id,
                        seconds(first_image.stamp_ns),
                        seconds(image.stamp_ns)
                    )));
                }
            }
        }
        let gripper_to_world = lookup(gripper_frame(arm), image.stamp_ns)?;
        let depth = nearest(&rec.depths, image.stamp_ns, (s.depth_sync_s * 1e9) as i64);
        let joint = finger_joint(arm);
        let opening = match rec.joints.get(joint).and_then(|q| joint_at(q, image.stamp_ns)) {
            None => None,
            Some(p) => Some(match robot {
                None => (p * s.opening_m_per_joint_unit).max(0.0),
                Some(r) => (r.opening_m)(joint, p).ok_or_else(|| {
                    fail(format!(
                        "{joint} (the {arm} finger joint) is not a finger joint of {}'s gripper under {}",
                        r.spec.description, r.spec.gripper_root
                    ))
                })?,
            }),
        };
        let frame = Frame {
            file_path: image.path.clone(),
            arm,
            gripper_to_world: RigidTransform(gripper_to_world),
            depth_path: depth.map(|d| d.path.clone()),
            object_mask_path: None,
            gripper_mask_path: None,
            gripper_opening_m: opening,
            trajectory: None,
            gt: None,
        };
        if empty {
            empty_frames.push(frame);
        } else {
            frames.push(frame);
        }
    }
    let Some((camera_to_world, _)) = camera else {
        return Err(fail(format!(
            "none of the {} images on {} falls in a left, right or empty phase of {}",
            rec.images.len(),
            s.image_topic,
            s.phase_topic
        )));
    };
    let handover = handover(rec, s, &lookup)?;
    let report = ImportReport {
        capture: PathBuf::new(),
        left_frames: frames.iter().filter(|f| f.arm == Arm::Left).count(),
        right_frames: frames.iter().filter(|f| f.arm == Arm::Right).count(),
        empty_frames: empty_frames.len(),
        skipped_images: skipped,
        frames_with_depth: frames.iter().filter(|f| f.depth_path.is_some()).count(),
        frames_with_opening: frames
            .iter()
            .filter(|f| f.gripper_opening_m.is_some())
            .count(),
        distortion,
        seconds: 0.0,
    };
    let file = CaptureFile {
        version: CAPTURE_VERSION,
        camera: CameraSpec {
            intrinsics,
            camera_to_world: RigidTransform(camera_to_world),
            distortion,
        },
        handover,
        frames,
        empty_frames,
        gt: None,
        robot: None,
        generator: Some(serde_json::json!({
            "name": "omniscan import ros2",
            "version": env!("CARGO_PKG_VERSION"),
            "bag": bag.path.display().to_string(),
            "settings": s,
        })),
    };
    Ok((file, report))
}

/// Both grippers' poses at the (first) handover phase's time.
fn handover(
    rec: &Recording,
    s: &Ros2ImportSettings,
    lookup: &dyn Fn(&str, i64) -> Result<Pose, RosError>,
) -> Result<Handover, RosError> {
    let Some(&(t, _)) = rec.phases.iter().find(|(_, p)| *p == Phase::Handover) else {
        return Err(RosError::Invalid(format!(
            "{} never says `handover`: the capture needs both grippers' poses at the handover",
            s.phase_topic
        )));
    };
    Ok(Handover {
        left_gripper_to_world: RigidTransform(lookup(&s.left_gripper_frame, t)?),
        right_gripper_to_world: RigidTransform(lookup(&s.right_gripper_frame, t)?),
    })
}

/// The image whose stamp is nearest `t_ns`, if within `tolerance_ns`.
fn nearest(list: &[Stamped], t_ns: i64, tolerance_ns: i64) -> Option<&Stamped> {
    let after = list.partition_point(|i| i.stamp_ns < t_ns);
    [after.checked_sub(1), Some(after)]
        .into_iter()
        .flatten()
        .filter_map(|i| list.get(i))
        .min_by_key(|i| (i.stamp_ns - t_ns).abs())
        .filter(|i| (i.stamp_ns - t_ns).abs() <= tolerance_ns)
}

/// The staged images no frame uses (handover, before the first phase, or
/// depth without a colour image).
fn unused_images<'a>(rec: &'a Recording, file: &CaptureFile) -> Vec<&'a str> {
    let used: std::collections::HashSet<&str> = file
        .frames
        .iter()
        .chain(&file.empty_frames)
        .flat_map(|f| std::iter::once(f.file_path.as_str()).chain(f.depth_path.as_deref()))
        .collect();
    rec.images
        .iter()
        .chain(&rec.depths)
        .map(|i| i.path.as_str())
        .filter(|p| !used.contains(p))
        .collect()
}
