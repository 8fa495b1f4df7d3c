//! Grippers from URDF: a prismatic two-finger hand and a revolute one built
//! here, and the YuMi's URDF from `../shared`. Each is loaded, its opening
//! checked against a closed form (or the YuMi's specification), simulated in
//! a scan and masked kinematically, the masks scored against the
//! simulator's ground truth.

use std::path::{Path, PathBuf};

use omniscan_core::capture::{Capture, RobotSpec};
use omniscan_core::plan::ScanPlanConfig;
use omniscan_mask::pipeline::Masker;
use omniscan_mask::{MaskSettings, evaluate_capture, mask_capture};
use omniscan_scene::gripper::GripperModel;
use omniscan_sim::builtin::builtin_object;
use omniscan_sim::grasp::{GraspSettings, plan_grasp_pair};
use omniscan_sim::{SimConfig, Simulation};

/// A binary STL of the box lo..hi, written here (not by the loaders under test).
fn write_box_stl(path: &Path, lo: [f32; 3], hi: [f32; 3]) {
    let corner = |i: usize| {
        [
            if i & 1 == 0 { lo[0] } else { hi[0] },
            if i & 2 == 0 { lo[1] } else { hi[1] },
            if i & 4 == 0 { lo[2] } else { hi[2] },
        ]
    };
    // Outward-wound quads of the cube's corner indices.
    let quads = [
        [0, 2, 3, 1],
        [4, 5, 7, 6],
        [0, 1, 5, 4],
        [2, 6, 7, 3],
        [0, 4, 6, 2],
        [1, 3, 7, 5],
    ];
    let mut bytes = vec![0u8; 80];
    bytes.extend(12u32.to_le_bytes());
    for q in quads {
        for tri in [[q[0], q[1], q[2]], [q[0], q[2], q[3]]] {
            bytes.extend([0u8; 12]);
            for c in tri {
                for v in corner(c) {
                    bytes.extend(v.to_le_bytes());
                }
            }
            bytes.extend([0u8; 2]);
        }
    }
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, bytes).unwrap();
}

/// A parallel hand: a palm box, two fingers sliding along x, the second
/// mimicking the first. Finger meshes come from a package (`package://hand/…`).
fn prismatic_hand(dir: &Path) -> PathBuf {
    write_box_stl(
        &dir.join("hand/meshes/finger.stl"),
        [0.005, -0.01, 0.0],
        [0.013, 0.01, 0.05],
    );
    let urdf = dir.join("robot/hand.urdf");
    std::fs::create_dir_all(urdf.parent().unwrap()).unwrap();
    std::fs::write(
        &urdf,
        r#"<robot name="hand">
  <material name="dark"><color rgba="0.2 0.2 0.22 1"/></material>
  <link name="flange"/>
  <joint name="mount" type="fixed"><parent link="flange"/><child link="palm"/><origin xyz="0 0 0.01"/></joint>
  <link name="palm"><visual><origin xyz="0 0 0.02"/><geometry><box size="0.07 0.03 0.04"/></geometry><material name="dark"/></visual></link>
  <joint name="finger_a_joint" type="prismatic"><parent link="palm"/><child link="finger_a"/>
    <origin xyz="0 0 0.04"/><axis xyz="1 0 0"/><limit lower="0" upper="0.03" effort="1" velocity="1"/></joint>
  <link name="finger_a"><visual><geometry><mesh filename="package://hand/meshes/finger.stl"/></geometry>
    <material name="grey"><color rgba="0.7 0.7 0.7 1"/></material></visual></link>
  <joint name="finger_b_joint" type="prismatic"><parent link="palm"/><child link="finger_b"/>
    <origin xyz="0 0 0.04" rpy="0 0 3.14159265359"/><axis xyz="1 0 0"/><limit lower="0" upper="0.03" effort="1" velocity="1"/>
    <mimic joint="finger_a_joint"/></joint>
  <link name="finger_b"><visual><geometry><mesh filename="package://hand/meshes/finger.stl"/></geometry></visual></link>
  <joint name="tcp_joint" type="fixed"><parent link="palm"/><child link="tcp"/><origin xyz="0 0 0.07"/></joint>
  <link name="tcp"/>
</robot>"#,
    )
    .unwrap();
    urdf
}

/// Fingers on hinges about y, 40 mm apart, opening outward; the second
/// mimics the first with multiplier -1.
fn revolute_hand(dir: &Path) -> PathBuf {
    let urdf = dir.join("revolute.urdf");
    write_box_stl(
        &dir.join("meshes/finger.stl"),
        [-0.008, -0.01, 0.0],
        [-0.004, 0.01, 0.06],
    );
    std::fs::write(
        &urdf,
        r#"<robot name="claw">
  <link name="palm"><visual><origin xyz="0 0 0.015"/><geometry><cylinder radius="0.03" length="0.03"/></geometry></visual></link>
  <joint name="right" type="revolute"><parent link="palm"/><child link="right_finger"/>
    <origin xyz="0.02 0 0.03"/><axis xyz="0 1 0"/><limit lower="0" upper="0.5" effort="1" velocity="1"/></joint>
  <link name="right_finger"><visual><geometry><mesh filename="meshes/finger.stl"/></geometry></visual></link>
  <joint name="left" type="revolute"><parent link="palm"/><child link="left_finger"/>
    <origin xyz="-0.02 0 0.03" rpy="0 0 3.14159265359"/><axis xyz="0 -1 0"/><limit lower="-0.5" upper="0" effort="1" velocity="1"/>
    <mimic joint="right" multiplier="-1"/></joint>
  <link name="left_finger"><visual><geometry><mesh filename="meshes/finger.stl"/></geometry></visual></link>
</robot>"#,
    )
    .unwrap();
    urdf
}

fn spec(
    urdf: &Path,
    root: &str,
    tcp_link: Option<&str>,
    tcp_offset_m: Option<[f64; 3]>,
) -> RobotSpec {
    RobotSpec {
        description: urdf.display().to_string(),
        gripper_root: root.into(),
        tcp_link: tcp_link.map(String::from),
        tcp_offset_m,
    }
}

#[test]
fn a_prismatic_hands_opening_is_its_joint_travel() {
    let tmp = tempfile::tempdir().unwrap();
    let urdf = prismatic_hand(tmp.path());
    let model =
        GripperModel::from_robot(&spec(&urdf, "palm", Some("tcp"), None), Path::new("/")).unwrap();
    let robot = model.robot().unwrap();
    // Pads at ±(5 mm + q): 10 mm closed, 70 mm at the 30 mm limit.
    assert!(
        (robot.max_opening_m() - 0.07).abs() < 1e-6,
        "{}",
        robot.max_opening_m()
    );
    assert!((robot.joint_share(0.04) - 0.5).abs() < 1e-6);
    // From a recorded joint position (joint_states) back to the opening.
    assert!((robot.opening_at("finger_a_joint", 0.015).unwrap() - 0.04).abs() < 1e-6);
    assert!((robot.opening_at("finger_a_joint", 0.5).unwrap() - 0.07).abs() < 1e-6);
    assert_eq!(
        robot.opening_at("finger_b_joint", 0.01),
        None,
        "a mimic joint is not driven"
    );
    assert_eq!(model.parts(0.04).len(), 3);
}

#[test]
fn a_revolute_hands_opening_follows_its_hinges() {
    let tmp = tempfile::tempdir().unwrap();
    let urdf = revolute_hand(tmp.path());
    let z_tcp = 0.03; // above the hinges
    let model = GripperModel::from_robot(
        &spec(&urdf, "palm", None, Some([0.0, 0.0, 0.03 + z_tcp])),
        Path::new("/"),
    )
    .unwrap();
    let robot = model.robot().unwrap();
    // The inner face x = -8 mm of a finger turned by θ about its hinge,
    // where it crosses the TCP's height h: z_l = (h - 0.008 sin θ) / cos θ,
    // x = 20 mm - 8 mm cos θ + z_l sin θ.
    let gap = |theta: f64| {
        let z_l = (z_tcp - 0.008 * theta.sin()) / theta.cos();
        2.0 * (0.02 - 0.008 * theta.cos() + z_l * theta.sin())
    };
    assert!(
        (robot.max_opening_m() - gap(0.5)).abs() < 1e-5,
        "{} vs {}",
        robot.max_opening_m(),
        gap(0.5)
    );
    let half = gap(0.25);
    assert!(
        (robot.joint_share(half) - 0.5).abs() < 0.01,
        "{}",
        robot.joint_share(half)
    );
}

#[test]
fn bad_urdfs_are_refused_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let urdf = prismatic_hand(tmp.path());
    let error = |s: RobotSpec| {
        GripperModel::from_robot(&s, Path::new("/"))
            .err()
            .unwrap()
            .to_string()
    };
    let e = error(spec(&urdf, "wrist", Some("tcp"), None));
    assert!(e.contains("no link `wrist`") && e.contains("palm"), "{e}");
    let e = error(spec(&urdf, "palm", Some("finger_a"), None));
    assert!(e.contains("moves with joint finger_a_joint"), "{e}");
    let e = error(spec(&urdf, "palm", None, None));
    assert!(e.contains("as a link or as an offset"), "{e}");
    // The TCP must lie between the pads.
    let e = error(spec(&urdf, "palm", None, Some([0.0, 0.0, 0.5])));
    assert!(
        e.contains("no finger surface crosses the TCP's x axis"),
        "{e}"
    );
    std::fs::remove_file(tmp.path().join("hand/meshes/finger.stl")).unwrap();
    let e = error(spec(&urdf, "palm", Some("tcp"), None));
    assert!(
        e.contains("link finger_a") && e.contains("package `hand` has no such file"),
        "{e}"
    );
    let text = std::fs::read_to_string(&urdf)
        .unwrap()
        .replace("\"prismatic\"", "\"screw\"");
    std::fs::write(&urdf, text).unwrap();
    let e = error(spec(&urdf, "palm", Some("tcp"), None));
    assert!(
        e.contains("hand.urdf") && e.contains("not a readable URDF"),
        "{e}"
    );
}

/// Whether `p` lies inside the closed `mesh`: the parity of a ray's
/// crossings, by majority over three skew rays (a ray along an edge
/// miscounts). Independent of the planner's voxels and boxes.
fn inside_mesh(mesh: &omniscan_scene::mesh::Mesh, p: &nalgebra::Point3<f64>) -> bool {
    let rays = [
        nalgebra::Vector3::new(1.0, 0.013, 0.021),
        nalgebra::Vector3::new(-0.017, 1.0, 0.031),
        nalgebra::Vector3::new(0.023, -0.011, 1.0),
    ];
    let odd = rays
        .iter()
        .filter(|d| {
            mesh.line_hits(p, &d.normalize())
                .iter()
                .filter(|(t, _)| *t > 0.0)
                .count()
                % 2
                == 1
        })
        .count();
    odd >= 2
}

/// Whether `p` is inside `mesh` by more than 0.5 mm: it and its six
/// neighbours 0.5 mm away along the axes are inside. The planner lets
/// shallower grazes pass (its 1 mm voxels round by as much; the fingers give).
fn deep_inside_mesh(mesh: &omniscan_scene::mesh::Mesh, p: &nalgebra::Point3<f64>) -> bool {
    let (lo, hi) = mesh.bounds();
    let q = p.cast::<f32>();
    if (0..3).any(|a| q[a] < lo[a] || q[a] > hi[a]) {
        return false;
    }
    let steps = [-0.0005, 0.0005];
    inside_mesh(mesh, p)
        && (0..3).all(|axis| {
            steps.iter().all(|&d| {
                let mut q = *p;
                q[axis] += d;
                inside_mesh(mesh, &q)
            })
        })
}

/// Plans both arms' grasps of the builtin remote with `robot`'s gripper and
/// checks, on the gripper's own meshes at each grasp's opening, that no
/// vertex of the object is inside the gripper.
fn assert_grasps_clear_the_gripper(name: &str, robot: &RobotSpec) {
    let model = GripperModel::from_robot(robot, Path::new("/")).unwrap();
    let object = builtin_object("remote").unwrap();
    let settings = GraspSettings::for_gripper(&model, 7);
    let (left, right) = plan_grasp_pair(&model, &object, &settings).unwrap();
    for grasp in [left, right] {
        let to_gripper = grasp.object_to_gripper();
        // The planner lets the object reach 1.5 mm past the contacts (the
        // fingers give).
        let parts = model.parts(grasp.width_m + 0.003);
        let inside = object
            .positions
            .iter()
            .map(|v| to_gripper * v.cast::<f64>())
            .filter(|p| {
                parts.iter().any(|part| {
                    deep_inside_mesh(part.mesh, &part.tcp_to_part.inverse_transform_point(p))
                })
            })
            .count();
        assert_eq!(
            inside,
            0,
            "{name}: {inside} of the object's vertices inside the gripper at a {:.1} mm grasp",
            grasp.width_m * 1e3
        );
    }
}

#[test]
fn grasps_keep_the_object_out_of_urdf_grippers() {
    let tmp = tempfile::tempdir().unwrap();
    let prismatic = spec(&prismatic_hand(tmp.path()), "palm", Some("tcp"), None);
    assert_grasps_clear_the_gripper("prismatic", &prismatic);
    let revolute = spec(
        &revolute_hand(tmp.path()),
        "palm",
        None,
        Some([0.0, 0.0, 0.06]),
    );
    assert_grasps_clear_the_gripper("revolute", &revolute);
}

/// Simulates a scan held by `robot`, masks it kinematically and returns the
/// mean IoU of (gripper, object) masks against the ground truth.
fn scan_and_mask(dir: &Path, robot: RobotSpec) -> (f64, f64) {
    let config = SimConfig {
        object: "builtin:remote".into(),
        width: 320,
        height: 240,
        seed: 2,
        supersample: 2,
        plan: ScanPlanConfig {
            wrist_angles: 4,
            latitudes: 2,
            ..ScanPlanConfig::default()
        },
        robot: Some(robot),
        ..SimConfig::default()
    };
    Simulation::new(config)
        .unwrap()
        .run(dir, &|_, _| {})
        .unwrap();
    let mut capture = Capture::load(dir).unwrap();
    assert!(
        capture.file.robot.is_some(),
        "the capture records its robot"
    );
    let masker = Masker::new(&capture, None, MaskSettings::default()).unwrap();
    mask_capture(&mut capture, &masker, &|_, _| {}).unwrap();
    let e = evaluate_capture(&Capture::load(dir).unwrap()).unwrap();
    let mean = |m: &omniscan_mask::pipeline::PerArm| 0.5 * (m.left.unwrap() + m.right.unwrap());
    let (gripper, object) = (mean(&e.gripper_miou), mean(&e.object_miou));
    eprintln!(
        "{}: gripper mIoU {gripper:.4}, object mIoU {object:.4}",
        dir.display()
    );
    (gripper, object)
}

#[test]
fn scans_held_by_urdf_grippers_are_masked_as_well_as_the_yumi() {
    let tmp = tempfile::tempdir().unwrap();
    let hands = [
        (
            "prismatic",
            spec(&prismatic_hand(tmp.path()), "palm", Some("tcp"), None),
        ),
        (
            "revolute",
            spec(
                &revolute_hand(tmp.path()),
                "palm",
                None,
                Some([0.0, 0.0, 0.06]),
            ),
        ),
    ];
    for (name, robot) in hands {
        let (gripper, object) = scan_and_mask(&tmp.path().join(name), robot);
        assert!(
            gripper >= 0.97 && object >= 0.95,
            "{name}: gripper mIoU {gripper}, object {object}"
        );
    }
}

/// The YuMi's own URDF (`../shared/data/grippers/yumi/yumi.urdf`), its
/// `package://yumi_description/…` meshes laid out as a ROS package would.
#[test]
#[ignore = "needs ../shared"]
fn the_yumi_urdf_opens_50_mm_and_its_scans_mask() {
    let shared = std::env::var("OMNISCAN_SHARED").map_or_else(
        |_| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared"),
        PathBuf::from,
    );
    let yumi = shared.join("data/grippers/yumi");
    let tmp = tempfile::tempdir().unwrap();
    let package = tmp.path().join("yumi_description/meshes/gripper");
    std::fs::create_dir_all(&package).unwrap();
    std::os::unix::fs::symlink(
        yumi.join("meshes/gripper_base.stl"),
        package.join("base.stl"),
    )
    .unwrap();
    std::os::unix::fs::symlink(
        yumi.join("meshes/finray_finger.stl"),
        package.join("yumi_finray_finger.stl"),
    )
    .unwrap();
    let urdf = tmp.path().join("yumi.urdf");
    std::fs::copy(yumi.join("yumi.urdf"), &urdf).unwrap();
    // The TCP midway between the pads, 118 mm out from the gripper base.
    let robot = spec(&urdf, "gripper_l_base", None, Some([0.0, 0.0, 0.118]));
    let model = GripperModel::from_robot(&robot, Path::new("/")).unwrap();
    let opening = model.max_opening_m();
    // The YuMi's specification: 2 x 25 mm of finger travel.
    assert!((opening - 0.050).abs() < 0.003, "{opening}");
    assert_grasps_clear_the_gripper("YuMi URDF", &robot);
    let (gripper, object) = scan_and_mask(&tmp.path().join("scan"), robot);
    assert!(
        gripper >= 0.97 && object >= 0.95,
        "gripper mIoU {gripper}, object {object}"
    );
}

fn shared() -> PathBuf {
    std::env::var("OMNISCAN_SHARED").map_or_else(
        |_| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared"),
        PathBuf::from,
    )
}

/// The Robotiq 2F-85 from MuJoCo Menagerie's MJCF in `../shared` (one
/// finger's four-bar linkage, closed by its `connect` equality): it opens
/// about as wide as specified, and scans held by it mask.
#[test]
#[ignore = "needs ../shared"]
fn the_robotiq_2f85_mjcf_opens_as_specified_and_its_scans_mask() {
    let mjcf = shared().join("data/grippers/robotiq_2f85/2f85.xml");
    // The TCP 130 mm above the mount, on the fingertips' inner faces (this
    // model has no pads; its pinch site is above the tips); the mount's x
    // is the base's y, the fingers' closing direction.
    let robot = spec(&mjcf, "base_mount", None, Some([0.0, 0.0, 0.13]));
    let model = GripperModel::from_robot(&robot, Path::new("/")).unwrap();
    let opening = model.max_opening_m();
    eprintln!("2F-85: widest opening {opening} m");
    assert_grasps_clear_the_gripper("2F-85", &robot);
    // 85 mm is the stroke between the pads, which this model leaves out
    // (Menagerie's full model puts a pad of about 7 mm on each fingertip):
    // the bare fingertips open that much wider.
    assert!((0.085..0.105).contains(&opening), "{opening}");
    let tmp = tempfile::tempdir().unwrap();
    let (gripper, object) = scan_and_mask(&tmp.path().join("scan"), robot);
    assert!(
        gripper >= 0.97 && object >= 0.95,
        "gripper mIoU {gripper}, object {object}"
    );
}
