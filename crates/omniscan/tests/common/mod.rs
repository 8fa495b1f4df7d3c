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
