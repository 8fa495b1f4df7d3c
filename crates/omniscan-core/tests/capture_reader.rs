//! The capture reader on a small hand-made capture and on each kind of bad input.

use std::path::Path;

use omniscan_core::capture::Capture;
use omniscan_core::image_io::{DepthMm, Mask, RgbImage, write_depth, write_mask, write_rgb};
use serde_json::{Value, json};

const W: u32 = 8;
const H: u32 = 6;

fn identity_with(t: [f64; 3]) -> Value {
    json!([
        [1.0, 0.0, 0.0, t[0]],
        [0.0, 1.0, 0.0, t[1]],
        [0.0, 0.0, 1.0, t[2]],
        [0.0, 0.0, 0.0, 1.0]
    ])
}

/// Writes a valid capture: 2 left, 2 right and 1 empty frame with depth and masks.
fn make_capture(dir: &Path) -> Value {
    let rgb = RgbImage {
        width: W,
        height: H,
        data: vec![128; (W * H * 3) as usize],
    };
    let mask = Mask {
        width: W,
        height: H,
        data: vec![255; (W * H) as usize],
    };
    let depth = DepthMm {
        width: W,
        height: H,
        data: vec![400; (W * H) as usize],
    };
    let mut frames = Vec::new();
    for (i, arm) in ["left", "left", "right", "right"].iter().enumerate() {
        write_rgb(&dir.join(format!("images/{i}.png")), &rgb).unwrap();
        write_depth(&dir.join(format!("depth/{i}.png")), &depth).unwrap();
        write_mask(&dir.join(format!("masks/{i}.png")), &mask).unwrap();
        frames.push(json!({
            "file_path": format!("images/{i}.png"),
            "arm": arm,
            "gripper_to_world": identity_with([0.4, 0.0, 0.3 + 0.01 * i as f64]),
            "depth_path": format!("depth/{i}.png"),
            "object_mask_path": format!("masks/{i}.png"),
        }));
    }
    write_rgb(&dir.join("empty/0.png"), &rgb).unwrap();
    let file = json!({
        "version": 1,
        "camera": {"width": W, "height": H, "fx": 10.0, "fy": 10.0, "cx": 4.0, "cy": 3.0, "camera_to_world": identity_with([1.0, 0.0, 0.3])},
        "handover": {"left_gripper_to_world": identity_with([0.4, 0.0, 0.3]), "right_gripper_to_world": identity_with([0.4, 0.05, 0.3])},
        "frames": frames,
        "empty_frames": [{"file_path": "empty/0.png", "arm": "left", "gripper_to_world": identity_with([0.4, 0.0, 0.3])}],
    });
    save(dir, &file);
    file
}

fn save(dir: &Path, file: &Value) {
    std::fs::write(
        dir.join("capture.json"),
        serde_json::to_string_pretty(file).unwrap(),
    )
    .unwrap();
}

fn load_error(dir: &Path) -> String {
    Capture::load(dir)
        .expect_err("bad capture accepted")
        .to_string()
}

#[test]
fn valid_capture_loads_with_its_summary() {
    let dir = tempfile::tempdir().unwrap();
    make_capture(dir.path());
    let capture = Capture::load(dir.path()).unwrap();
    let s = capture.summary();
    assert_eq!(
        (
            s.left_frames,
            s.right_frames,
            s.empty_frames,
            s.width,
            s.height
        ),
        (2, 2, 1, W, H)
    );
    assert!(!s.ground_truth && s.depth);
    assert_eq!(s.object_masks, 4);
    // Loading through the JSON file's own path works too.
    Capture::load(&dir.path().join("capture.json")).unwrap();
}

#[test]
fn missing_image_is_named() {
    let dir = tempfile::tempdir().unwrap();
    make_capture(dir.path());
    std::fs::remove_file(dir.path().join("images/2.png")).unwrap();
    let err = load_error(dir.path());
    assert!(
        err.contains("frames[2].file_path")
            && err.contains("missing image")
            && err.contains("images/2.png"),
        "{err}"
    );
}

#[test]
fn size_mismatch_is_named() {
    let dir = tempfile::tempdir().unwrap();
    make_capture(dir.path());
    write_mask(
        &dir.path().join("masks/1.png"),
        &Mask {
            width: 4,
            height: 6,
            data: vec![0; 24],
        },
    )
    .unwrap();
    let err = load_error(dir.path());
    assert!(
        err.contains("frames[1].object_mask_path")
            && err.contains("size mismatch")
            && err.contains("4x6"),
        "{err}"
    );
}

#[test]
fn wrong_pixel_formats_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    make_capture(dir.path());
    // An 8-bit image where 16-bit depth belongs, an RGB image where a mask belongs.
    write_mask(
        &dir.path().join("depth/0.png"),
        &Mask {
            width: W,
            height: H,
            data: vec![1; 48],
        },
    )
    .unwrap();
    write_rgb(
        &dir.path().join("masks/3.png"),
        &RgbImage {
            width: W,
            height: H,
            data: vec![0; 144],
        },
    )
    .unwrap();
    let err = load_error(dir.path());
    assert!(
        err.contains("frames[0].depth_path") && err.contains("16-bit"),
        "{err}"
    );
    assert!(
        err.contains("frames[3].object_mask_path") && err.contains("8-bit greyscale"),
        "{err}"
    );
    // A corrupt file.
    std::fs::write(dir.path().join("images/1.png"), b"\x89PNG broken").unwrap();
    assert!(load_error(dir.path()).contains("frames[1].file_path"));
}

#[test]
fn non_rigid_and_non_finite_matrices_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut file = make_capture(dir.path());
    file["frames"][1]["gripper_to_world"][0][0] = json!(2.0);
    save(dir.path(), &file);
    let err = load_error(dir.path());
    assert!(
        err.contains("frames[1].gripper_to_world") && err.contains("not rigid"),
        "{err}"
    );

    let mut file = make_capture(dir.path());
    file["camera"]["camera_to_world"][2][3] = json!("NaN");
    save(dir.path(), &file);
    let err = load_error(dir.path());
    assert!(err.contains("camera.camera_to_world"), "{err}");
    // JSON has no NaN; a number too large for f64 is the nearest thing.
    let text = std::fs::read_to_string(dir.path().join("capture.json"))
        .unwrap()
        .replace("\"NaN\"", "1e999");
    std::fs::write(dir.path().join("capture.json"), text).unwrap();
    let err = load_error(dir.path());
    assert!(err.contains("capture.json"), "{err}");

    let mut file = make_capture(dir.path());
    file["handover"]["right_gripper_to_world"][3] = json!([0.0, 0.0, 0.5, 1.0]);
    save(dir.path(), &file);
    let err = load_error(dir.path());
    assert!(
        err.contains("handover.right_gripper_to_world") && err.contains("bottom row"),
        "{err}"
    );
}

#[test]
fn unknown_arm_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut file = make_capture(dir.path());
    file["frames"][0]["arm"] = json!("middle");
    save(dir.path(), &file);
    let err = load_error(dir.path());
    assert!(
        err.contains("frames[0].arm") && err.contains("middle") && err.contains("left"),
        "{err}"
    );
}

#[test]
fn empty_trajectory_and_structural_problems_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut file = make_capture(dir.path());
    file["frames"] = json!([]);
    save(dir.path(), &file);
    assert!(load_error(dir.path()).contains("`frames` is empty"));

    let mut file = make_capture(dir.path());
    file["version"] = json!(7);
    file["camera"]["fx"] = json!(-3.0);
    save(dir.path(), &file);
    let err = load_error(dir.path());
    assert!(err.contains("version 7") && err.contains("fx"), "{err}");

    let mut file = make_capture(dir.path());
    file.as_object_mut().unwrap().remove("handover");
    save(dir.path(), &file);
    assert!(load_error(dir.path()).contains("handover"));

    std::fs::write(dir.path().join("capture.json"), "{ not json").unwrap();
    assert!(load_error(dir.path()).contains("capture.json"));

    let empty = tempfile::tempdir().unwrap();
    let err = load_error(empty.path());
    assert!(
        err.contains("capture.json") && err.contains("no such file"),
        "{err}"
    );
}

#[test]
fn every_problem_is_reported_at_once() {
    let dir = tempfile::tempdir().unwrap();
    make_capture(dir.path());
    for i in 0..4 {
        std::fs::remove_file(dir.path().join(format!("masks/{i}.png"))).unwrap();
    }
    let err = load_error(dir.path());
    for i in 0..4 {
        assert!(
            err.contains(&format!("frames[{i}].object_mask_path")),
            "{err}"
        );
    }
}
