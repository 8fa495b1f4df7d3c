//! The twin's and the inspection's `report.html` in a real browser
//! (headless Chromium, see `omniscan_view::browser`): each loads with no
//! error and no request leaving the page, its viewer draws the model, and
//! the inspection's defect markers are drawn where the report puts them.

use std::path::Path;
use std::process::Output;

mod common;

/// Runs omniscan, asserting that it succeeds.
fn omniscan(args: &[&str]) -> Output {
    let output = common::omniscan(args);
    assert!(
        output.status.success(),
        "omniscan {args:?}: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

fn screenshot(page: &Path, out: &Path, options: &[&str]) -> image::RgbImage {
    let shot = omniscan_view::browser::screenshot(page, out, options).unwrap();
    shot.clean().unwrap();
    image::open(out).unwrap().to_rgb8()
}

/// Not one flat colour: the viewer drew something.
fn drawn(image: &image::RgbImage) -> bool {
    let first = image.get_pixel(0, 0);
    image
        .pixels()
        .filter(|p| p.0.iter().zip(first.0).any(|(a, b)| a.abs_diff(b) > 24))
        .count()
        > 200
}

#[test]
#[ignore = "needs Chromium and web/node_modules (.ci/run installs them)"]
fn the_twin_report_shows_the_twin() {
    let tmp = tempfile::tempdir().unwrap();
    let capture = tmp.path().join("cap");
    let capture_arg = capture.to_str().unwrap();
    omniscan(&[
        "sim",
        "--object",
        "builtin:remote",
        "--out",
        capture_arg,
        "--supersample",
        "1",
        "--no-empty-pass",
        "--width",
        "64",
        "--height",
        "48",
        "--wrist-angles",
        "6",
        "--latitudes",
        "2",
    ]);
    let out = tmp.path().join("twin");
    omniscan(&[
        "twin",
        "--use-ground-truth-masks",
        capture_arg,
        "--out",
        out.to_str().unwrap(),
        "--steps",
        "300",
        "--downscale",
        "1",
        "--backend",
        "cpu",
    ]);
    let page = out.join("report.html");
    let html = std::fs::read_to_string(&page).unwrap();
    for part in [
        "Stages",
        "against the simulator",
        "<svg",
        "data:image/png;base64,",
        "omniscan-viewer-config",
    ] {
        assert!(html.contains(part), "the report has no {part}");
    }
    let image = screenshot(&page, &tmp.path().join("twin.png"), &[]);
    assert!(drawn(&image), "the twin's viewer is blank");
}

#[test]
#[ignore = "needs Chromium and web/node_modules (.ci/run installs them)"]
fn the_inspection_report_marks_the_defect_in_3d() {
    let dir = tempfile::tempdir().unwrap();
    let [a, b, c] = common::part_copies(dir.path());
    let path = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    let report = path("report");
    omniscan(&[
        "inspect", &a, &b, &c, "--out", &report, "--views", "40", "--width", "128", "--height",
        "96",
    ]);
    let page = Path::new(&report).join("report.html");
    // The defective copy alone, with and without its markers.
    let show = ["--show", "1", "--markers"];
    let on = screenshot(
        &page,
        &dir.path().join("on.png"),
        &[&show[..], &["on"]].concat(),
    );
    let off = screenshot(
        &page,
        &dir.path().join("off.png"),
        &[&show[..], &["off"]].concat(),
    );
    assert!(drawn(&off), "the copy is not drawn");
    let red = |image: &image::RgbImage| {
        image
            .pixels()
            .filter(|p| p.0[0] > 180 && p.0[1] < 90 && p.0[2] < 90)
            .count()
    };
    assert!(
        red(&on) > red(&off) + 30,
        "no marker drawn: {} red pixels with markers, {} without",
        red(&on),
        red(&off)
    );
}
