//! `train --refine-poses` on a simulated capture whose recorded gripper
//! poses carry calibration error (`sim --pose-noise-*`): the report's
//! corrections bring the poses closer to the simulator's truth.

mod common;

use common::omniscan_json as json;

#[test]
fn refined_poses_come_closer_to_the_truth() {
    let tmp = tempfile::tempdir().unwrap();
    let capture = tmp.path().join("cap");
    let capture = capture.to_str().unwrap();
    #[rustfmt::skip]
    let sim = [
        "sim", "--object", "builtin:remote", "--out", capture, "--width", "160", "--height", "120",
        "--wrist-angles", "6", "--latitudes", "3", "--supersample", "1", "--no-empty-pass",
        "--pose-noise-deg", "1", "--pose-noise-mm", "3", "--seed", "2", "--json",
    ];
    json(&sim);
    let model = tmp.path().join("m.ply");
    #[rustfmt::skip]
    let report = json(&[
        "train", capture, "--arm", "left", "--use-ground-truth-masks", "--out", model.to_str().unwrap(),
        "--steps", "600", "--downscale", "1", "--hold-out-every", "6", "--sh-degree", "0",
        "--initial-points", "2000", "--backend", "cpu", "--refine-poses", "--pose-fit-steps", "40",
        "--json",
    ]);
    let poses = &report["poses"];
    assert_eq!(poses["train"].as_array().unwrap().len(), 15, "{poses}");
    assert_eq!(poses["held_out"].as_array().unwrap().len(), 3, "{poses}");
    assert_eq!(poses["groups"][0]["group"], "left");
    let truth = &poses["against_truth"];
    let figure = |set: &str, what: &str| truth[set][what].as_f64().unwrap();
    let recorded = figure("recorded", "rms_translation_mm");
    assert!(
        (2.0..4.0).contains(&recorded),
        "the simulated error is about 3 mm: {truth}"
    );
    // The part of the error the images show, across the view, shrinks;
    // along the optical axis it hardly shows (docs/train.md).
    let across = figure("recorded", "rms_across_view_mm");
    assert!(across > 1.5, "{truth}");
    // Training views move less far than held-out ones, which fit a frozen
    // model at full rate.
    for (set, share) in [("train", 0.75), ("held_out", 0.5)] {
        let refined = figure(set, "rms_across_view_mm");
        assert!(
            refined < share * across,
            "{set}: {refined} mm of {across}: {truth}"
        );
    }
    // Every training view has its own correction, and the frame it is.
    let frames: Vec<u64> = (poses["train"].as_array().unwrap().iter())
        .map(|v| v["frame"].as_u64().unwrap())
        .collect();
    assert!(frames.windows(2).all(|w| w[0] < w[1]), "{frames:?}");
    // `eval --fit-poses` scores views after fitting them as training's
    // report does: better than at their recorded, wrong poses.
    let eval = |fit: bool| {
        let mut args = vec!["eval", model.to_str().unwrap(), capture, "--arm", "left"];
        args.extend(["--held-out-every", "6", "--json"]);
        if fit {
            args.extend(["--fit-poses", "--pose-fit-steps", "40"]);
        }
        json(&args)
    };
    let (recorded, fitted) = (eval(false), eval(true));
    let psnr = |r: &serde_json::Value| r["psnr_masked"].as_f64().unwrap();
    assert!(
        psnr(&fitted) > psnr(&recorded) + 0.5,
        "{fitted} vs {recorded}"
    );
    assert_eq!(fitted["poses"].as_array().unwrap().len(), 3, "{fitted}");
    assert!(recorded.get("poses").is_none());
    // The twin refines in each of its trainings; the merged model's
    // views are in two groups, one camera-side correction per arm, and its
    // right arm's corrections are compared in the left gripper's frame.
    let twin = tmp.path().join("twin");
    #[rustfmt::skip]
    let twin_report = json(&[
        "twin", capture, "--out", twin.to_str().unwrap(), "--steps", "300", "--downscale", "1",
        "--use-ground-truth-masks", "--backend", "cpu", "--refine-poses", "--pose-fit-steps", "20",
        "--json",
    ]);
    let stages = &twin_report["stages"];
    for (stage, groups) in [
        ("left", vec!["left"]),
        ("right", vec!["right"]),
        ("twin", vec!["left", "right"]),
    ] {
        let poses = &stages[stage]["report"]["poses"];
        let names: Vec<&str> = (poses["groups"].as_array().unwrap().iter())
            .map(|g| g["group"].as_str().unwrap())
            .collect();
        assert_eq!(names, groups, "{stage}: {poses}");
        let truth = &poses["against_truth"];
        let across = |set: &str| truth[set]["rms_across_view_mm"].as_f64().unwrap();
        assert!(across("train") < across("recorded"), "{stage}: {truth}");
    }
}
