//! The simulator is the ground truth for every later stage, so its own
//! ground truth is checked here against independent computations: separate
//! renders of each layer, the mesh surface, and the pose algebra.

use nalgebra::Point3;
use omniscan_core::capture::{Arm, Capture};
use omniscan_core::geometry::pose_difference;
use omniscan_core::image_io;
use omniscan_core::plan::ScanPlanConfig;
use omniscan_core::poses::{camera_to_object, handover_right_to_left};
use omniscan_sim::gripper::gripper_boxes;
use omniscan_sim::raster::Label;
use omniscan_sim::simulate::Layers;
use omniscan_sim::{SimConfig, Simulation};

fn small_config(object: &str) -> SimConfig {
    SimConfig {
        object: object.into(),
        width: 96,
        height: 72,
        supersample: 1,
        depth_noise_m_at_1m: 0.0,
        plan: ScanPlanConfig {
            wrist_angles: 3,
            latitudes: 2,
            ..ScanPlanConfig::default()
        },
        empty_pass: false,
        ..SimConfig::default()
    }
}

#[test]
fn object_mask_is_exactly_where_the_object_is_nearest() {
    let sim = Simulation::new(small_config("builtin:wire_connector")).unwrap();
    let mut object_pixels = 0;
    for frame in sim.frames.iter().step_by(2) {
        let all = sim.render_frame(frame, Layers::ALL, 1);
        let only = |layers| sim.render_frame(frame, layers, 1);
        let object = only(Layers {
            scene: false,
            object: true,
            gripper: false,
        });
        let gripper = only(Layers {
            scene: false,
            object: false,
            gripper: true,
        });
        let scene = only(Layers {
            scene: true,
            object: false,
            gripper: false,
        });
        let nearer = |a: f32, b: f32| a > 0.0 && (b == 0.0 || a < b);
        for i in 0..all.labels.len() {
            let is_nearest = nearer(object.depth[i], gripper.depth[i])
                && nearer(object.depth[i], scene.depth[i]);
            assert_eq!(
                all.labels[i] == Label::Object,
                is_nearest,
                "pixel {i} of {}",
                frame.stem()
            );
            if is_nearest {
                object_pixels += 1;
                assert_eq!(all.depth[i], object.depth[i]);
            }
            // The gripper mask likewise covers what the gripper shows in front.
            let gripper_nearest = nearer(gripper.depth[i], object.depth[i])
                && nearer(gripper.depth[i], scene.depth[i]);
            assert_eq!(
                matches!(all.labels[i], Label::Gripper | Label::Arm),
                gripper_nearest,
                "pixel {i}"
            );
        }
    }
    assert!(
        object_pixels > 500,
        "the object barely shows: {object_pixels} pixels"
    );
}

#[test]
fn object_depth_lies_on_the_mesh_in_both_grippers_and_handover_truth_holds() {
    let dir = tempfile::tempdir().unwrap();
    let config = SimConfig {
        slip_deg: 6.0,
        slip_mm: 4.0,
        ..small_config("builtin:flashlight")
    };
    let sim = Simulation::new(config).unwrap();
    sim.run(dir.path(), &|_, _| {}).unwrap();
    let capture = Capture::load(dir.path()).unwrap();
    let gt = capture.file.gt.as_ref().unwrap();
    let k = capture.intrinsics();
    let camera = capture.camera_to_world();
    let mut checked = 0;
    for frame in &capture.file.frames {
        let gt_frame = frame.gt.as_ref().unwrap();
        let depth =
            image_io::read_depth(&capture.resolve(gt_frame.depth_path.as_ref().unwrap())).unwrap();
        let mask =
            image_io::read_mask(&capture.resolve(gt_frame.object_mask_path.as_ref().unwrap()))
                .unwrap();
        let t_ic = camera_to_object(&frame.gripper_to_world.0, &camera);
        let object_to_gripper = match frame.arm {
            Arm::Left => gt.object_to_left_gripper.0,
            Arm::Right => gt.object_to_right_gripper.0,
        };
        let camera_to_mesh = object_to_gripper.inverse() * t_ic;
        let pixels: Vec<u32> = (0..depth.data.len() as u32)
            .filter(|&i| mask.data[i as usize] == 255)
            .collect();
        for &i in pixels.iter().step_by((pixels.len() / 25).max(1)) {
            let (x, y) = (i % k.width, i / k.width);
            let z = depth.metres(x, y).unwrap();
            let p = k.unproject(x as f64 + 0.5, y as f64 + 0.5, z);
            let on_mesh = camera_to_mesh * p;
            let d = sim.object.mesh.distance_to_surface(&on_mesh.cast());
            // Depth PNGs hold whole millimetres.
            assert!(
                d < 0.0008,
                "{} pixel ({x},{y}) is {:.2} mm off the surface",
                frame.file_path,
                d * 1e3
            );
            checked += 1;
        }
    }
    assert!(checked > 100);
    // The recorded handover (what a robot knows) misses the true transform by the slip.
    let h = &capture.file.handover;
    let estimate = handover_right_to_left(&h.left_gripper_to_world.0, &h.right_gripper_to_world.0);
    let (angle, _) = pose_difference(&estimate, &gt.right_to_left.0);
    assert!(
        (angle.to_degrees() - 6.0).abs() < 1e-4,
        "{}",
        angle.to_degrees()
    );
    // And the truth is consistent with the object's poses in each gripper.
    let truth = gt.object_to_left_gripper.0 * gt.object_to_right_gripper.0.inverse();
    let (a, t) = pose_difference(&truth, &gt.right_to_left.0);
    assert!(a < 1e-6 && t < 1e-8, "{a} {t}");
    // Without slip the handover estimate is exact.
    let no_slip = Simulation::new(small_config("builtin:flashlight"))
        .unwrap()
        .capture_file();
    let h = &no_slip.handover;
    let estimate = handover_right_to_left(&h.left_gripper_to_world.0, &h.right_gripper_to_world.0);
    let (a, t) = pose_difference(&estimate, &no_slip.gt.unwrap().right_to_left.0);
    assert!(a < 1e-6 && t < 1e-8, "no slip: {a} {t}");
}

fn files(dir: &std::path::Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push((
                    p.strip_prefix(dir).unwrap().display().to_string(),
                    std::fs::read(&p).unwrap(),
                ));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn same_seed_same_bytes_resume_and_refusing_foreign_directories() {
    let config = SimConfig {
        width: 64,
        height: 48,
        supersample: 2,
        seed: 42,
        defect: Some("visual:tape,size_mm=8".into()),
        plan: ScanPlanConfig {
            wrist_angles: 2,
            latitudes: 1,
            ..ScanPlanConfig::default()
        },
        ..SimConfig::default()
    };
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    Simulation::new(config.clone())
        .unwrap()
        .run(a.path(), &|_, _| {})
        .unwrap();
    Simulation::new(config.clone())
        .unwrap()
        .run(b.path(), &|_, _| {})
        .unwrap();
    let (fa, fb) = (files(a.path()), files(b.path()));
    assert!(fa.len() > 20);
    assert!(fa == fb, "two runs with one seed differ");
    // Interrupted run: some outputs and capture.json missing.
    std::fs::remove_file(b.path().join("images/right_001.png")).unwrap();
    std::fs::remove_file(b.path().join("empty/gt/depth/left_000.png")).unwrap();
    std::fs::remove_file(b.path().join("capture.json")).unwrap();
    let summary = Simulation::new(config.clone())
        .unwrap()
        .run(b.path(), &|_, _| {})
        .unwrap();
    assert_eq!(summary.rendered, 2);
    assert_eq!(summary.resumed, 6);
    assert!(
        files(b.path()) == fa,
        "resumed run differs from a fresh one"
    );
    // Another seed must not overwrite this capture.
    let other = SimConfig { seed: 43, ..config };
    let err = Simulation::new(other)
        .unwrap()
        .run(b.path(), &|_, _| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("other settings"), "{err}");
    // The capture is valid and its defect is recorded.
    let capture = Capture::load(a.path()).unwrap();
    let s = capture.summary();
    assert_eq!((s.left_frames, s.right_frames, s.empty_frames), (2, 2, 4));
    let defect = &capture.file.gt.unwrap().extra["defect"];
    assert_eq!(defect["kind"], "tape");
    assert_eq!(defect["category"], "visual");
}

#[test]
fn every_builtin_can_be_grasped_and_handed_over() {
    for name in omniscan_sim::builtin::BUILTIN_OBJECTS {
        let sim = Simulation::new(small_config(&format!("builtin:{name}")))
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        // The right fingers stay off where the left fingers touched, so the
        // handover exposes those places.
        let to_right = sim.right_grasp.object_to_gripper();
        for contact in sim.left_grasp.contacts {
            let p = to_right * Point3::from(contact);
            for (lo, hi) in gripper_boxes(sim.right_grasp.width_m + 0.004) {
                let inside = p.x > lo.x
                    && p.y > lo.y
                    && p.z > lo.z
                    && p.x < hi.x
                    && p.y < hi.y
                    && p.z < hi.z;
                assert!(!inside, "{name}: right gripper covers a left contact");
            }
        }
        assert_eq!(sim.frames.len(), 12);
    }
}

/// `--pose-noise-deg/--pose-noise-mm`: the recorded poses carry an error of
/// the asked RMS size, seeded; the images and the truth in `gt` are those of
/// the noise-free scan.
#[test]
fn pose_noise_perturbs_the_recorded_poses_only() {
    let plan = ScanPlanConfig {
        wrist_angles: 20,
        latitudes: 5,
        ..ScanPlanConfig::default()
    };
    let clean = Simulation::new(SimConfig {
        plan,
        ..small_config("builtin:remote")
    })
    .unwrap();
    let noisy_config = SimConfig {
        plan,
        pose_noise_deg: 0.5,
        pose_noise_mm: 1.0,
        ..small_config("builtin:remote")
    };
    let noisy = Simulation::new(noisy_config.clone()).unwrap();
    let again = Simulation::new(noisy_config).unwrap().capture_file();
    let (a, b) = (clean.capture_file(), noisy.capture_file());
    assert_eq!(b, again, "the same seed gives the same errors");
    let (mut sum_deg2, mut sum_mm2) = (0.0, 0.0);
    for (fa, fb) in a.frames.iter().zip(&b.frames) {
        assert!(fa.gt.as_ref().unwrap().gripper_to_world.is_none());
        let truth = fb.gt.as_ref().unwrap().gripper_to_world.unwrap();
        assert_eq!(truth, fa.gripper_to_world);
        let (rad, m) = pose_difference(&truth.0, &fb.gripper_to_world.0);
        sum_deg2 += rad.to_degrees().powi(2);
        sum_mm2 += (m * 1000.0).powi(2);
    }
    let n = a.frames.len() as f64;
    let (rms_deg, rms_mm) = ((sum_deg2 / n).sqrt(), (sum_mm2 / n).sqrt());
    assert!(
        (rms_deg - 0.5).abs() < 0.06,
        "RMS {rms_deg}° over {n} frames"
    );
    assert!(
        (rms_mm - 1.0).abs() < 0.12,
        "RMS {rms_mm} mm over {n} frames"
    );
    // What the camera saw is the noise-free scan's.
    let frame = &noisy.frames[7];
    assert_eq!(
        noisy.render_frame(frame, Layers::ALL, 1).rgb,
        clean.render_frame(&clean.frames[7], Layers::ALL, 1).rgb
    );
    let too_much = SimConfig {
        pose_noise_deg: 20.0,
        ..small_config("builtin:remote")
    };
    let e = Simulation::new(too_much).err().unwrap().to_string();
    assert!(e.contains("no calibration error"), "{e}");
}
