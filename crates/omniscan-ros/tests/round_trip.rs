//! A simulated capture written as a ROS 2 bag and imported back.
//!
//! The bags are written here independently of the importer: the messages
//! with a CDR encoder of this file (not the `cdr-encoding` crate the
//! importer reads with), the container with the `mcap` crate's writer or
//! with plain SQL in rosbag2's sqlite3 schema.

use std::collections::BTreeMap;
use std::path::Path;

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use omniscan_core::capture::{Arm, Capture, Frame};
use omniscan_core::geometry::{Pose, pose_difference};
use omniscan_core::image_io::{read_depth, read_rgb};
use omniscan_core::lens::Distortion;
use omniscan_core::plan::ScanPlanConfig;
use omniscan_ros::{Ros2ImportSettings, import_ros2};
use omniscan_sim::{SimConfig, Simulation};

/// A little-endian CDR message, alignment counted from after the 4-byte
/// encapsulation header.
struct Cdr(Vec<u8>);

impl Cdr {
    fn new() -> Cdr {
        Cdr(vec![0, 1, 0, 0])
    }
    fn align(&mut self, n: usize) {
        while !(self.0.len() - 4).is_multiple_of(n) {
            self.0.push(0);
        }
    }
    fn u8(&mut self, v: u8) -> &mut Self {
        self.0.push(v);
        self
    }
    fn u32(&mut self, v: u32) -> &mut Self {
        self.align(4);
        self.0.extend(v.to_le_bytes());
        self
    }
    fn i32(&mut self, v: i32) -> &mut Self {
        self.align(4);
        self.0.extend(v.to_le_bytes());
        self
    }
    fn f64(&mut self, v: f64) -> &mut Self {
        self.align(8);
        self.0.extend(v.to_le_bytes());
        self
    }
    fn string(&mut self, s: &str) -> &mut Self {
        self.u32(s.len() as u32 + 1);
        self.0.extend(s.as_bytes());
        self.0.push(0);
        self
    }
    fn bytes(&mut self, b: &[u8]) -> &mut Self {
        self.u32(b.len() as u32);
        self.0.extend(b);
        self
    }
    fn f64s(&mut self, v: &[f64]) -> &mut Self {
        self.u32(v.len() as u32);
        for &x in v {
            self.f64(x);
        }
        self
    }
    fn header(&mut self, t_ns: i64, frame: &str) -> &mut Self {
        self.i32((t_ns / 1_000_000_000) as i32)
            .u32((t_ns % 1_000_000_000) as u32)
            .string(frame)
    }
    fn done(&mut self) -> Vec<u8> {
        std::mem::take(&mut self.0)
    }
}

/// (topic, type, log time ns, bytes)
type Message = (String, String, i64, Vec<u8>);
/// Adds a message: topic, type, log time ns, bytes.
type Push<'a> = dyn FnMut(&str, &str, i64, Vec<u8>) + 'a;

fn image_msg(
    t: i64,
    frame: &str,
    w: u32,
    h: u32,
    encoding: &str,
    step: u32,
    data: &[u8],
) -> Vec<u8> {
    Cdr::new()
        .header(t, frame)
        .u32(h)
        .u32(w)
        .string(encoding)
        .u8(0)
        .u32(step)
        .bytes(data)
        .done()
}

fn tf_msg(t: i64, edges: &[(&str, &str, Pose)]) -> Vec<u8> {
    let mut c = Cdr::new();
    c.u32(edges.len() as u32);
    for (parent, child, pose) in edges {
        let (v, q) = (pose.translation.vector, pose.rotation.quaternion());
        c.header(t, parent).string(child);
        c.f64(v.x).f64(v.y).f64(v.z);
        c.f64(q.i).f64(q.j).f64(q.k).f64(q.w);
    }
    c.done()
}

fn camera_info_msg(t: i64, capture: &Capture, d: &[f64], model: &str) -> Vec<u8> {
    let k = capture.intrinsics();
    let mut c = Cdr::new();
    c.header(t, "camera_color_optical_frame")
        .u32(k.height)
        .u32(k.width)
        .string(model)
        .f64s(d);
    // OpenCV's K: the first pixel's centre at (0, 0).
    for v in [k.fx, 0.0, k.cx - 0.5, 0.0, k.fy, k.cy - 0.5, 0.0, 0.0, 1.0] {
        c.f64(v);
    }
    for v in [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0] {
        c.f64(v);
    }
    for v in [
        k.fx,
        0.0,
        k.cx - 0.5,
        0.0,
        0.0,
        k.fy,
        k.cy - 0.5,
        0.0,
        0.0,
        0.0,
        1.0,
        0.0,
    ] {
        c.f64(v);
    }
    c.u32(1).u32(1).u32(0).u32(0).u32(0).u32(0).u8(0);
    c.done()
}

fn string_msg(s: &str) -> Vec<u8> {
    Cdr::new().string(s).done()
}

fn joint_msg(t: i64, names: &[&str], positions: &[f64]) -> Vec<u8> {
    let mut c = Cdr::new();
    c.header(t, "");
    c.u32(names.len() as u32);
    for n in names {
        c.string(n);
    }
    c.f64s(positions).f64s(&[]).f64s(&[]);
    c.done()
}

fn simulate(dir: &Path) -> Capture {
    let config = SimConfig {
        object: "builtin:remote".into(),
        width: 160,
        height: 120,
        seed: 5,
        supersample: 1,
        plan: ScanPlanConfig {
            wrist_angles: 3,
            latitudes: 2,
            ..ScanPlanConfig::default()
        },
        ..SimConfig::default()
    };
    Simulation::new(config)
        .unwrap()
        .run(dir, &|_, _| {})
        .unwrap();
    Capture::load(dir).unwrap()
}

/// A robot base between the world and the grippers, so lookups compose.
fn base_to_world() -> Pose {
    Pose::from_parts(
        Translation3::new(0.2, -0.1, 0.05),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3),
    )
}

const SECOND: i64 = 1_000_000_000;

/// The capture as a recording: every frame an image 100 ms after the last,
/// with TF, depth, joint states and the phases around them.
fn recording(capture: &Capture, distortion: &[f64]) -> Vec<Message> {
    let mut out: Vec<Message> = Vec::new();
    let mut push =
        |topic: &str, ty: &str, t: i64, data: Vec<u8>| out.push((topic.into(), ty.into(), t, data));
    let k = capture.intrinsics();
    let camera = "camera_color_optical_frame";
    push(
        "/tf_static",
        "tf2_msgs/msg/TFMessage",
        0,
        tf_msg(
            0,
            &[
                ("world", camera, capture.camera_to_world()),
                ("world", "robot_base", base_to_world()),
            ],
        ),
    );
    push(
        "/camera/color/camera_info",
        "sensor_msgs/msg/CameraInfo",
        0,
        camera_info_msg(0, capture, distortion, "plumb_bob"),
    );
    let handover = capture.file.handover;
    let mut poses = (
        handover.left_gripper_to_world.0,
        handover.right_gripper_to_world.0,
    );
    let mut t = 10 * SECOND;
    let groups: Vec<(&str, Vec<&Frame>)> = vec![
        (
            "left",
            capture.arm_frames(Arm::Left).map(|(_, f)| f).collect(),
        ),
        ("handover", vec![]),
        (
            "right",
            capture.arm_frames(Arm::Right).map(|(_, f)| f).collect(),
        ),
        (
            "empty_left",
            capture
                .file
                .empty_frames
                .iter()
                .filter(|f| f.arm == Arm::Left)
                .collect(),
        ),
        (
            "empty_right",
            capture
                .file
                .empty_frames
                .iter()
                .filter(|f| f.arm == Arm::Right)
                .collect(),
        ),
    ];
    let tf_at = |t: i64, poses: (Pose, Pose), push: &mut Push| {
        let base = base_to_world().inverse();
        push(
            "/tf",
            "tf2_msgs/msg/TFMessage",
            t,
            tf_msg(
                t,
                &[
                    ("robot_base", "left_gripper", base * poses.0),
                    ("robot_base", "right_gripper", base * poses.1),
                ],
            ),
        );
    };
    for (phase, frames) in groups {
        push(
            "/omniscan/phase",
            "std_msgs/msg/String",
            t,
            string_msg(phase),
        );
        if phase == "handover" {
            tf_at(
                t,
                (
                    handover.left_gripper_to_world.0,
                    handover.right_gripper_to_world.0,
                ),
                &mut push,
            );
        }
        t += SECOND / 20;
        for frame in frames {
            match frame.arm {
                Arm::Left => poses.0 = frame.gripper_to_world.0,
                Arm::Right => poses.1 = frame.gripper_to_world.0,
            }
            tf_at(t, poses, &mut push);
            let rgb = read_rgb(&capture.resolve(&frame.file_path)).unwrap();
            // bgr8 with a padded row, as some drivers publish.
            let step = k.width * 3 + 4;
            let mut data = Vec::new();
            for row in rgb.data.chunks(k.width as usize * 3) {
                for px in row.chunks(3) {
                    data.extend([px[2], px[1], px[0]]);
                }
                data.extend([0; 4]);
            }
            push(
                "/camera/color/image_raw",
                "sensor_msgs/msg/Image",
                t,
                image_msg(t, camera, k.width, k.height, "bgr8", step, &data),
            );
            let depth = read_depth(&capture.resolve(frame.depth_path.as_ref().unwrap())).unwrap();
            let bytes: Vec<u8> = depth.data.iter().flat_map(|d| d.to_le_bytes()).collect();
            // The depth camera's stamp lags the colour's by 2 ms.
            push(
                "/camera/depth/image_raw",
                "sensor_msgs/msg/Image",
                t + 2_000_000,
                image_msg(
                    t + 2_000_000,
                    camera,
                    k.width,
                    k.height,
                    "16UC1",
                    k.width * 2,
                    &bytes,
                ),
            );
            let open = frame.gripper_opening_m.unwrap() / 2.0;
            push(
                "/joint_states",
                "sensor_msgs/msg/JointState",
                t,
                joint_msg(t, &["gripper_l_joint", "gripper_r_joint"], &[open, open]),
            );
            t += SECOND / 10;
        }
    }
    out
}

fn write_mcap(path: &Path, messages: &[Message]) {
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut writer = mcap::Writer::new(file).unwrap();
    let mut channels: BTreeMap<String, u16> = BTreeMap::new();
    for (sequence, (topic, ty, t, data)) in messages.iter().enumerate() {
        let id = match channels.get(topic) {
            Some(&id) => id,
            None => {
                let schema = writer.add_schema(ty, "ros2msg", b"").unwrap();
                let id = writer
                    .add_channel(schema, topic, "cdr", &BTreeMap::new())
                    .unwrap();
                channels.insert(topic.clone(), id);
                id
            }
        };
        let header = mcap::records::MessageHeader {
            channel_id: id,
            sequence: sequence as u32,
            log_time: *t as u64,
            publish_time: *t as u64,
        };
        writer.write_to_known_channel(&header, data).unwrap();
    }
    writer.finish().unwrap();
}

fn write_sqlite(dir: &Path, messages: &[Message]) {
    std::fs::create_dir_all(dir).unwrap();
    let db = rusqlite::Connection::open(dir.join("scan_0.db3")).unwrap();
    db.execute_batch(
        "CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL, serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL);
         CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp INTEGER NOT NULL, data BLOB NOT NULL);",
    )
    .unwrap();
    let mut ids: BTreeMap<String, i64> = BTreeMap::new();
    for (topic, ty, t, data) in messages {
        let next = ids.len() as i64 + 1;
        let id = *ids.entry(topic.clone()).or_insert_with(|| {
            db.execute(
                "INSERT INTO topics VALUES (?1, ?2, ?3, 'cdr', '')",
                rusqlite::params![next, topic, ty],
            )
            .unwrap();
            next
        });
        db.execute(
            "INSERT INTO messages(topic_id, timestamp, data) VALUES (?1, ?2, ?3)",
            rusqlite::params![id, t, data],
        )
        .unwrap();
    }
    std::fs::write(
        dir.join("metadata.yaml"),
        "rosbag2_bagfile_information:\n  storage_identifier: sqlite3\n",
    )
    .unwrap();
}

fn assert_same_frames(original: &Capture, imported: &Capture, list: fn(&Capture) -> &Vec<Frame>) {
    let (a, b) = (list(original), list(imported));
    assert_eq!(a.len(), b.len());
    for (fa, fb) in a.iter().zip(b) {
        assert_eq!(fa.arm, fb.arm);
        let (rad, m) = pose_difference(&fa.gripper_to_world.0, &fb.gripper_to_world.0);
        assert!(
            rad < 1e-6 && m < 1e-6,
            "{} vs {}: {rad} rad, {m} m",
            fa.file_path,
            fb.file_path
        );
        assert_eq!(
            read_rgb(&original.resolve(&fa.file_path)).unwrap(),
            read_rgb(&imported.resolve(&fb.file_path)).unwrap()
        );
        assert_eq!(
            read_depth(&original.resolve(fa.depth_path.as_ref().unwrap())).unwrap(),
            read_depth(&imported.resolve(fb.depth_path.as_ref().unwrap())).unwrap()
        );
        let (oa, ob) = (fa.gripper_opening_m.unwrap(), fb.gripper_opening_m.unwrap());
        assert!((oa - ob).abs() < 1e-12, "opening {oa} vs {ob}");
    }
}

fn assert_round_trip(original: &Capture, imported: &Capture) {
    let (ka, kb) = (original.intrinsics(), imported.intrinsics());
    assert_eq!((ka.width, ka.height), (kb.width, kb.height));
    for (x, y) in [
        (ka.fx, kb.fx),
        (ka.fy, kb.fy),
        (ka.cx, kb.cx),
        (ka.cy, kb.cy),
    ] {
        assert!((x - y).abs() < 1e-9, "{x} vs {y}");
    }
    let (rad, m) = pose_difference(&original.camera_to_world(), &imported.camera_to_world());
    assert!(rad < 1e-6 && m < 1e-6);
    let (ha, hb) = (original.file.handover, imported.file.handover);
    for (a, b) in [
        (ha.left_gripper_to_world, hb.left_gripper_to_world),
        (ha.right_gripper_to_world, hb.right_gripper_to_world),
    ] {
        let (rad, m) = pose_difference(&a.0, &b.0);
        assert!(rad < 1e-6 && m < 1e-6);
    }
    assert_same_frames(original, imported, |c| &c.file.frames);
    assert_same_frames(original, imported, |c| &c.file.empty_frames);
}

#[test]
fn a_simulated_capture_comes_back_from_mcap_and_sqlite_bags() {
    let tmp = tempfile::tempdir().unwrap();
    let original = simulate(&tmp.path().join("sim"));
    assert!(!original.file.empty_frames.is_empty());
    let messages = recording(&original, &[0.0; 5]);

    let mcap_path = tmp.path().join("scan.mcap");
    write_mcap(&mcap_path, &messages);
    let out = tmp.path().join("from-mcap");
    let report = import_ros2(
        &mcap_path,
        &out,
        &Ros2ImportSettings::default(),
        None,
        &|_| {},
    )
    .unwrap();
    assert_eq!(report.skipped_images, 0);
    assert_eq!(report.distortion, None);
    assert_round_trip(&original, &Capture::load(&out).unwrap());

    let sqlite_dir = tmp.path().join("scan_bag");
    write_sqlite(&sqlite_dir, &messages);
    let out = tmp.path().join("from-sqlite");
    import_ros2(
        &sqlite_dir,
        &out,
        &Ros2ImportSettings::default(),
        None,
        &|_| {},
    )
    .unwrap();
    assert_round_trip(&original, &Capture::load(&out).unwrap());
}

#[test]
fn camera_info_distortion_is_recorded_in_the_capture() {
    let tmp = tempfile::tempdir().unwrap();
    let original = simulate(&tmp.path().join("sim"));
    let d = [-0.12, 0.03, 0.001, -0.0005, 0.0];
    let path = tmp.path().join("scan.mcap");
    write_mcap(&path, &recording(&original, &d));
    let out = tmp.path().join("capture");
    let hand = omniscan_core::capture::RobotSpec {
        description: "/robots/hand.urdf".into(),
        gripper_root: "palm".into(),
        tcp_link: None,
        tcp_offset_m: Some([0.0, 0.0, 0.07]),
    };
    // The robot's opening at a joint position replaces the linear default.
    let opening_m =
        |joint: &str, position: f64| joint.starts_with("gripper_").then_some(3.0 * position);
    let robot = omniscan_ros::Robot {
        spec: hand.clone(),
        opening_m: &opening_m,
    };
    import_ros2(
        &path,
        &out,
        &Ros2ImportSettings::default(),
        Some(&robot),
        &|_| {},
    )
    .unwrap();
    let imported = Capture::load(&out).unwrap();
    assert_eq!(imported.file.robot.as_ref().unwrap(), &hand);
    for (a, b) in original.file.frames.iter().zip(&imported.file.frames) {
        let (oa, ob) = (a.gripper_opening_m.unwrap(), b.gripper_opening_m.unwrap());
        assert!((1.5 * oa - ob).abs() < 1e-12, "{oa} -> {ob}");
    }
    // A finger joint the robot's gripper does not have is named.
    let none = |_: &str, _: f64| None;
    let robot = omniscan_ros::Robot {
        spec: hand,
        opening_m: &none,
    };
    let again = tmp.path().join("again");
    let e = import_ros2(
        &path,
        &again,
        &Ros2ImportSettings::default(),
        Some(&robot),
        &|_| {},
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains(
            "gripper_l_joint (the left finger joint) is not a finger joint of /robots/hand.urdf"
        ),
        "{e}"
    );
    assert_eq!(
        imported.distortion(),
        Some(&Distortion::RadialTangential {
            k1: -0.12,
            k2: 0.03,
            p1: 0.001,
            p2: -0.0005,
            k3: 0.0
        })
    );
}

fn import_error(bag: &Path, out: &Path, settings: &Ros2ImportSettings) -> String {
    let e = import_ros2(bag, out, settings, None, &|_| {})
        .unwrap_err()
        .to_string();
    assert!(!out.exists(), "a failed import left {}", out.display());
    let parent = out.parent().unwrap();
    let staging: Vec<_> = std::fs::read_dir(parent)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| {
            e.file_name()
                .to_string_lossy()
                .starts_with(".omniscan-import-")
        })
        .collect();
    assert!(
        staging.is_empty(),
        "a failed import left its staging folder"
    );
    e
}

#[test]
fn bad_recordings_are_refused_by_topic_frame_and_time_and_leave_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let original = simulate(&tmp.path().join("sim"));
    let messages = recording(&original, &[0.0; 5]);
    let out = tmp.path().join("out").join("capture");
    let write = |name: &str, messages: &[Message]| {
        let path = tmp.path().join(name);
        write_mcap(&path, messages);
        path
    };
    let defaults = Ros2ImportSettings::default();

    // A topic the bag lacks: named, with what the bag has.
    let bag = write("all.mcap", &messages);
    let e = import_error(
        &bag,
        &out,
        &Ros2ImportSettings {
            phase_topic: "/scan/phase".into(),
            ..defaults.clone()
        },
    );
    assert!(
        e.contains("no messages on /scan/phase")
            && e.contains("/omniscan/phase (std_msgs/msg/String)"),
        "{e}"
    );

    // A gripper frame TF does not have.
    let e = import_error(
        &bag,
        &out,
        &Ros2ImportSettings {
            left_gripper_frame: "tool0".into(),
            ..defaults.clone()
        },
    );
    assert!(e.contains("no TF names frame tool0"), "{e}");

    // A TF gap: drop the gripper samples of the middle of the left scan.
    let left_images: Vec<i64> = messages
        .iter()
        .filter(|m| m.0 == "/camera/color/image_raw")
        .map(|m| m.2)
        .collect();
    let gap_at = left_images[2];
    let gappy: Vec<Message> = messages
        .iter()
        .filter(|m| !(m.0 == "/tf" && m.2 == gap_at))
        .cloned()
        .collect();
    let e = import_error(&write("gap.mcap", &gappy), &out, &defaults);
    assert!(
        e.contains("gap of 0.200 s") && e.contains("left_gripper"),
        "{e}"
    );
    // A longer limit interpolates across it.
    import_ros2(
        &write("gap2.mcap", &gappy),
        &out,
        &Ros2ImportSettings {
            max_tf_gap_s: 0.5,
            ..defaults.clone()
        },
        None,
        &|_| {},
    )
    .unwrap();
    std::fs::remove_dir_all(&out).unwrap();

    // An image whose size differs from camera_info.
    let mut resized = messages.clone();
    let (w, h) = (original.intrinsics().width, original.intrinsics().height);
    let i = resized
        .iter()
        .position(|m| m.0 == "/camera/color/image_raw")
        .unwrap();
    let t = resized[i].2;
    resized[i].3 = image_msg(
        t,
        "camera_color_optical_frame",
        w / 2,
        h,
        "mono8",
        w / 2,
        &vec![7; (w / 2 * h) as usize],
    );
    let e = import_error(&write("size.mcap", &resized), &out, &defaults);
    assert!(
        e.contains("/camera/color/image_raw at 10.050000 s")
            && e.contains(&format!("is {}x{h}", w / 2)),
        "{e}"
    );

    // An unknown phase.
    let mut phases = messages.clone();
    let i = phases
        .iter()
        .position(|m| m.0 == "/omniscan/phase")
        .unwrap();
    phases[i].3 = string_msg("scan");
    let e = import_error(&write("phase.mcap", &phases), &out, &defaults);
    assert!(e.contains("unknown phase `scan`"), "{e}");

    // Truncated bytes in a message.
    let mut cut = messages.clone();
    let i = cut
        .iter()
        .position(|m| m.0 == "/camera/color/camera_info")
        .unwrap();
    cut[i].3.truncate(30);
    let e = import_error(&write("cut.mcap", &cut), &out, &defaults);
    assert!(e.contains("/camera/color/camera_info at 0.000000 s"), "{e}");

    // Not a bag, and an output that exists.
    let e = import_error(&tmp.path().join("sim/capture.json"), &out, &defaults);
    assert!(e.contains("neither an .mcap nor a .db3"), "{e}");
    std::fs::create_dir_all(&out).unwrap();
    let e = import_ros2(&bag, &out, &defaults, None, &|_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("already exists"), "{e}");
}
