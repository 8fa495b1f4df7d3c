//! The masking stage on small simulated captures, measured against the
//! simulator's ground truth.

use std::path::Path;

use omniscan_core::capture::Capture;
use omniscan_core::plan::ScanPlanConfig;
use omniscan_mask::pipeline::{Masker, mask_frame};
use omniscan_mask::{MaskSettings, evaluate_capture, mask_capture};
use omniscan_sim::{SimConfig, Simulation};

fn simulate(dir: &Path, object: &str, seed: u64) -> Capture {
    let config = SimConfig {
        object: object.into(),
        width: 240,
        height: 180,
        seed,
        supersample: 2,
        plan: ScanPlanConfig {
            wrist_angles: 6,
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

#[test]
fn masks_match_ground_truth_are_recorded_and_resume() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("capture");
    let mut capture = simulate(&dir, "builtin:remote", 11);
    let masker = Masker::new(&capture, None, MaskSettings::default()).unwrap();
    let summary = mask_capture(&mut capture, &masker, &|_, _| {}).unwrap();
    assert_eq!(summary.frames, 24);
    assert_eq!(summary.computed, 24);

    // The paths are in capture.json and the files load as masks of the right size.
    let reloaded = Capture::load(&dir).unwrap();
    for frame in &reloaded.file.frames {
        assert!(
            frame
                .object_mask_path
                .as_deref()
                .unwrap()
                .starts_with("masks/object/")
        );
        assert!(
            frame
                .gripper_mask_path
                .as_deref()
                .unwrap()
                .starts_with("masks/gripper/")
        );
    }
    let evaluation = evaluate_capture(&reloaded).unwrap();
    for (what, value) in [
        ("object left", evaluation.object_miou.left.unwrap()),
        ("object right", evaluation.object_miou.right.unwrap()),
        ("gripper left", evaluation.gripper_miou.left.unwrap()),
        ("gripper right", evaluation.gripper_miou.right.unwrap()),
    ] {
        assert!(value > 0.95, "{what} mIoU {value}: {evaluation:#?}");
    }
    assert!(evaluation.object_min_iou > 0.8, "{evaluation:#?}");

    // A second run with the same settings keeps every mask.
    let mut again = Capture::load(&dir).unwrap();
    let summary = mask_capture(&mut again, &masker, &|_, _| {}).unwrap();
    assert_eq!((summary.computed, summary.resumed), (0, 24));
    // Other settings recompute.
    let mut settings = MaskSettings::default();
    settings.object.non_robot_threshold_m = 0.02;
    let other = Masker::new(&again, None, settings).unwrap();
    let summary = mask_capture(&mut again, &other, &|_, _| {}).unwrap();
    assert_eq!(summary.computed, 24);
    let summary = mask_capture(&mut again, &other, &|_, _| {}).unwrap();
    assert_eq!((summary.computed, summary.resumed), (0, 24));
    // A mask emptied (a run on a full disk) is made again, not kept.
    let first_mask = dir.join(again.file.frames[0].object_mask_path.as_deref().unwrap());
    std::fs::write(&first_mask, b"").unwrap();
    let summary = mask_capture(&mut again, &other, &|_, _| {}).unwrap();
    assert_eq!((summary.computed, summary.resumed), (1, 23));
    // An edited image makes the masks again: they were made from it.
    let image = dir.join(&again.file.frames[3].file_path);
    let mut rgb = omniscan_core::image_io::read_rgb(&image).unwrap();
    rgb.data.iter_mut().for_each(|v| *v = v.saturating_add(40));
    omniscan_core::image_io::write_rgb(&image, &rgb).unwrap();
    let summary = mask_capture(&mut again, &other, &|_, _| {}).unwrap();
    assert_eq!(summary.computed, 24);
}

#[test]
fn the_non_robot_score_rejects_the_scene_when_depth_and_motion_do_not() {
    // With the foreground cues switched off (every depth counts as near,
    // no motion needed), only S_NR tells the object from the static scene
    // and the arm: with it the masks stay right, without it they take the
    // whole background.
    let tmp = tempfile::tempdir().unwrap();
    let capture = simulate(&tmp.path().join("c"), "builtin:flashlight", 3);
    let mut strict_settings = MaskSettings::default();
    strict_settings.object.near_margin_m = 10.0;
    strict_settings.object.min_moving_fraction = 0.0;
    let mut loose_settings = strict_settings.clone();
    loose_settings.object.non_robot_threshold_m = 0.0;
    let strict = Masker::new(&capture, None, strict_settings).unwrap();
    let loose = Masker::new(&capture, None, loose_settings).unwrap();
    let truth = |i: usize| {
        let rel = capture.file.frames[i]
            .gt
            .as_ref()
            .unwrap()
            .object_mask_path
            .clone()
            .unwrap();
        omniscan_mask::Plane::from_mask(
            &omniscan_core::image_io::read_mask(&capture.resolve(&rel)).unwrap(),
        )
    };
    let (mut strict_iou, mut loose_iou) = (0.0, 0.0);
    for i in [0, 5, 13, 20] {
        let t = truth(i);
        strict_iou +=
            omniscan_mask::plane::iou(&mask_frame(&strict, &capture, i).unwrap().object, &t) / 4.0;
        loose_iou +=
            omniscan_mask::plane::iou(&mask_frame(&loose, &capture, i).unwrap().object, &t) / 4.0;
    }
    assert!(strict_iou > 0.95, "{strict_iou}");
    assert!(loose_iou < 0.3, "loose {loose_iou} strict {strict_iou}");
}

#[test]
fn bad_captures_give_errors_that_name_the_problem() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("capture");
    let capture = simulate(&dir, "builtin:t_connector", 5);

    // No empty-gripper pass.
    let mut no_empty = capture.clone();
    no_empty.file.empty_frames.clear();
    let masker = Masker::new(&no_empty, None, MaskSettings::default()).unwrap();
    let e = mask_frame(&masker, &no_empty, 0).unwrap_err().to_string();
    assert!(e.contains("empty-gripper") && e.contains("left_000"), "{e}");

    // No depth.
    let mut no_depth = capture.clone();
    no_depth.file.frames[2].depth_path = None;
    let e = mask_frame(&masker, &no_depth, 2).unwrap_err().to_string();
    assert!(e.contains("depth") && e.contains("left_002"), "{e}");

    // No finger opening.
    let mut no_opening = capture.clone();
    no_opening.file.frames[1].gripper_opening_m = None;
    let e = mask_frame(&masker, &no_opening, 1).unwrap_err().to_string();
    assert!(e.contains("gripper_opening_m"), "{e}");

    // A missing image and a depth map of the wrong size.
    std::fs::remove_file(dir.join(&capture.file.frames[3].file_path)).unwrap();
    let e = mask_frame(&masker, &capture, 3).unwrap_err().to_string();
    assert!(e.contains("left_003"), "{e}");
    let depth = dir.join(capture.file.frames[4].depth_path.as_ref().unwrap());
    omniscan_core::image_io::write_depth(
        &depth,
        &omniscan_core::image_io::DepthMm {
            width: 10,
            height: 10,
            data: vec![500; 100],
        },
    )
    .unwrap();
    let e = mask_frame(&masker, &capture, 4).unwrap_err().to_string();
    assert!(e.contains("10x10") && e.contains("240x180"), "{e}");

    // A gripper directory without meshes.
    let e = Masker::new(&capture, Some(tmp.path()), MaskSettings::default())
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("finray_finger.stl") && e.contains("--gripper-dir"),
        "{e}"
    );

    // Evaluation before masking.
    let e = evaluate_capture(&capture).unwrap_err().to_string();
    assert!(e.contains("run the masking first"), "{e}");
}

#[test]
fn the_learned_gripper_path_trains_saves_and_masks() {
    use omniscan_mask::plane::iou;
    use omniscan_mask::unet::{TrainSettings, UNet, train};
    let tmp = tempfile::tempdir().unwrap();
    let capture = simulate(&tmp.path().join("c"), "builtin:remote", 8);
    let mut net = UNet::new(64, 48, [4, 8, 8], 0).unwrap();
    let (examples, held_out) =
        omniscan_mask::pipeline::gripper_training_set(&net, std::slice::from_ref(&capture), 1)
            .unwrap();
    assert_eq!(examples.len() + held_out.len(), 48);
    let settings = TrainSettings {
        steps: 200,
        batch: 4,
        learning_rate: 1e-2,
        seed: 2,
    };
    train(&mut net, &examples, &settings, &|_, _| {}).unwrap();
    let held_out_iou = held_out
        .iter()
        .map(|(image, truth)| iou(&net.mask(image), truth))
        .sum::<f64>()
        / held_out.len() as f64;
    assert!(held_out_iou > 0.6, "held-out gripper IoU {held_out_iou}");

    let file = tmp.path().join("gripper.safetensors");
    net.save(&file).unwrap();
    let truth = |i: usize| {
        let rel = capture.file.frames[i]
            .gt
            .as_ref()
            .unwrap()
            .gripper_mask_path
            .clone()
            .unwrap();
        omniscan_mask::Plane::from_mask(
            &omniscan_core::image_io::read_mask(&capture.resolve(&rel)).unwrap(),
        )
    };
    let kinematic = Masker::new(&capture, None, MaskSettings::default()).unwrap();
    let learned = Masker::new(&capture, None, MaskSettings::default())
        .unwrap()
        .with_unet(&file, false, None)
        .unwrap();
    let both = Masker::new(&capture, None, MaskSettings::default())
        .unwrap()
        .with_unet(&file, true, None)
        .unwrap();
    assert!(learned.settings.gripper_method.starts_with("unet:"));
    let (mut learned_iou, mut kinematic_iou) = (0.0, 0.0);
    for i in [1, 7, 14, 20] {
        let k = mask_frame(&kinematic, &capture, i).unwrap();
        let l = mask_frame(&learned, &capture, i).unwrap();
        let b = mask_frame(&both, &capture, i).unwrap();
        learned_iou += iou(&l.gripper, &truth(i)) / 4.0;
        kinematic_iou += iou(&k.gripper, &truth(i)) / 4.0;
        // `both` only adds to the kinematic mask, and only next to it.
        assert!(
            k.gripper
                .data
                .iter()
                .zip(&b.gripper.data)
                .all(|(&k, &b)| !k || b)
        );
        let reach = k.gripper.dilate(4);
        assert!(
            b.gripper
                .data
                .iter()
                .zip(&reach.data)
                .all(|(&b, &r)| !b || r)
        );
    }
    // A U-Net this small and briefly trained is far from the kinematic mask.
    assert!(learned_iou > 0.5, "learned {learned_iou}");
    assert!(
        kinematic_iou > 0.95 && kinematic_iou > learned_iou,
        "kinematic {kinematic_iou}"
    );
}

/// Through a lens, the gripper lands where the lens model (its forward map,
/// independent of the Newton inverse the projection uses) puts the pinhole
/// projection's pixels.
#[test]
fn the_kinematic_projection_follows_the_lens() {
    use omniscan_core::lens::Distortion;
    use omniscan_mask::gripper::{GripperSettings, KinematicGripper, LensMap};
    use omniscan_scene::gripper::GripperModel;
    let tmp = tempfile::tempdir().unwrap();
    let capture = simulate(&tmp.path().join("capture"), "builtin:remote", 3);
    let k = *capture.intrinsics();
    let lens = Distortion::RadialTangential {
        k1: -0.25,
        k2: 0.05,
        k3: 0.0,
        p1: 0.002,
        p2: -0.001,
    };
    let gripper = |lens: Option<LensMap>| KinematicGripper {
        model: GripperModel::builtin(),
        intrinsics: k,
        camera_to_world: capture.camera_to_world(),
        settings: GripperSettings {
            supersample: 1,
            ..GripperSettings::default()
        },
        lens,
    };
    let frame = &capture.file.frames[0];
    let opening = frame.gripper_opening_m.unwrap();
    let pinhole = gripper(None).project(&frame.gripper_to_world.0, opening);
    let through =
        gripper(Some(LensMap::new(&lens, &k))).project(&frame.gripper_to_world.0, opening);
    assert!(pinhole.mask.data != through.mask.data);
    let (mut checked, mut agree) = (0, 0);
    let at = |m: &omniscan_mask::plane::Plane<bool>, x: usize, y: usize| m.data[y * m.width + x];
    for y in 1..k.height as usize - 1 {
        for x in 1..k.width as usize - 1 {
            // Pixels inside the pinhole mask, away from its edge.
            let inside = (0..9).all(|n| at(&pinhole.mask, x + n % 3 - 1, y + n / 3 - 1));
            if !inside {
                continue;
            }
            let xn = (x as f64 + 0.5 - k.cx) / k.fx;
            let yn = (y as f64 + 0.5 - k.cy) / k.fy;
            let [xd, yd] = lens.distort(xn, yn);
            let (u, v) = (k.fx * xd + k.cx, k.fy * yd + k.cy);
            if u < 0.0 || v < 0.0 || u >= k.width as f64 || v >= k.height as f64 {
                continue;
            }
            checked += 1;
            agree += usize::from(at(&through.mask, u as usize, v as usize));
        }
    }
    assert!(checked > 200, "{checked} pixels checked");
    assert!(
        agree as f64 >= 0.98 * checked as f64,
        "{agree} of {checked}"
    );
}
