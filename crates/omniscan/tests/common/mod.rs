//! What the command-line tests share: running the binary, reading its
//! refusals, and the smallest simulated capture.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub fn omniscan(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_omniscan"))
        .args(args)
        .output()
        .expect("run omniscan")
}

/// Runs `omniscan` and parses its JSON report, failing with its stderr.
pub fn omniscan_json(args: &[&str]) -> serde_json::Value {
    let out = omniscan(args);
    assert!(
        out.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// Asserts that a run failed and that its error says `message`.
pub fn assert_refused(out: &Output, message: &str) {
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains(message), "{err}");
}

/// Simulates a 64x48 capture of the built-in remote, 6 frames an arm.
pub fn tiny_capture(dir: &Path) {
    let out = omniscan(&[
        "sim",
        "--object",
        "builtin:remote",
        "--out",
        dir.to_str().unwrap(),
        "--width",
        "64",
        "--height",
        "48",
        "--wrist-angles",
        "3",
        "--latitudes",
        "2",
        "--supersample",
        "1",
        "--seed",
        "5",
    ]);
    assert!(
        out.status.success(),
        "sim failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// [`tiny_capture`] in `dir/cap` and its left arm exported for nerfstudio
/// to `dir/ns`.
pub fn tiny_left_export(dir: &Path) -> (PathBuf, PathBuf) {
    let capture = dir.join("cap");
    tiny_capture(&capture);
    let export = dir.join("ns");
    let out = omniscan(&[
        "export-nerfstudio",
        capture.to_str().unwrap(),
        "--arm",
        "left",
        "--out",
        export.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    (capture, export)
}

/// Three copies of a generated 6x4x2.5 cm part in `dir` (a.ply, b.ply with
/// a 7 mm bump, c.ply), made by `omniscan make-copy`; their paths.
pub fn part_copies(dir: &Path) -> [String; 3] {
    let part = omniscan_inspect::generate::test_part([0.06, 0.04, 0.025], 0.0012);
    let original = dir.join("part.ply");
    omniscan_splat::ply::write_splats(&original, &part).unwrap();
    let path = |name: &str| dir.join(name).to_str().unwrap().to_string();
    for (name, seed, defect) in [
        ("a.ply", "1", None),
        ("b.ply", "2", Some("bump")),
        ("c.ply", "3", None),
    ] {
        let out = path(name);
        let mut args = vec![
            "make-copy",
            original.to_str().unwrap(),
            "--seed",
            seed,
            "--out",
            &out,
        ];
        if let Some(d) = defect {
            args.extend(["--defect", d, "--size-mm", "7"]);
        }
        let o = omniscan(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    [path("a.ply"), path("b.ply"), path("c.ply")]
}
