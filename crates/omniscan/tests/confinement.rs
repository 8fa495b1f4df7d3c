//! A capture or photo set from someone else cannot make omniscan read,
//! probe or link files outside its folder, and `validate` finds what the
//! stages would fail on (docs/security.md).

use std::path::Path;

mod common;
use common::{assert_refused, omniscan, tiny_capture, tiny_left_export};

fn edit_json(path: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let mut value: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    edit(&mut value);
    std::fs::write(path, serde_json::to_string_pretty(&value).unwrap()).unwrap();
}

fn set_first_image(capture: &Path, file_path: &str) {
    edit_json(&capture.join("capture.json"), |c| {
        c["frames"][0]["file_path"] = file_path.into();
    });
}

fn first_image(capture: &Path) -> std::path::PathBuf {
    let c: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(capture.join("capture.json")).unwrap())
            .unwrap();
    capture.join(c["frames"][0]["file_path"].as_str().unwrap())
}

fn stderr(out: &std::process::Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn capture_paths_outside_the_folder_are_refused_unless_asked_for() {
    let tmp = tempfile::tempdir().unwrap();
    let capture = tmp.path().join("cap");
    tiny_capture(&capture);
    let outside = tmp.path().join("outside");
    std::fs::create_dir(&outside).unwrap();
    std::fs::copy(first_image(&capture), outside.join("secret.png")).unwrap();
    let cap = capture.to_str().unwrap();

    set_first_image(&capture, "../outside/secret.png");
    let model = tmp.path().join("unused.ply");
    let model = model.to_str().unwrap();
    for command in [vec!["validate", cap], vec!["train", cap, "--out", model]] {
        let out = omniscan(&command);
        assert_refused(
            &out,
            "frames[0].file_path: `../outside/secret.png` leads out",
        );
        assert!(stderr(&out).contains("capture.json"), "{}", stderr(&out));
    }
    let out = omniscan(&["validate", cap, "--allow-outside-paths"]);
    assert!(out.status.success(), "{}", stderr(&out));

    // An absolute path is refused before it is opened: an existing and a
    // missing file get the same answer, so nothing about them leaks.
    let refusal = |path: &str| {
        set_first_image(&capture, path);
        let out = omniscan(&["validate", cap]);
        assert_refused(&out, "is an absolute path");
        stderr(&out).replace(path, "PATH")
    };
    assert_eq!(refusal("/etc/hostname"), refusal("/no/such/file.png"));
}

#[cfg(unix)]
#[test]
fn links_out_of_a_capture_are_refused_and_an_export_copies_what_it_may_not_link() {
    use std::os::unix::fs::MetadataExt;
    let tmp = tempfile::tempdir().unwrap();
    let capture = tmp.path().join("cap");
    tiny_capture(&capture);
    let outside = tmp.path().join("outside.png");
    let image = first_image(&capture);
    std::fs::rename(&image, &outside).unwrap();
    std::os::unix::fs::symlink(&outside, &image).unwrap();
    let cap = capture.to_str().unwrap();
    assert_refused(&omniscan(&["validate", cap]), "through a symbolic link");

    let export = tmp.path().join("ns");
    let out = omniscan(&[
        "export-nerfstudio",
        cap,
        "--arm",
        "both",
        "--out",
        export.to_str().unwrap(),
        "--allow-outside-paths",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let inode = |p: &Path| std::fs::metadata(p).unwrap().ino();
    let exported = |n: usize| {
        let t: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(export.join("transforms.json")).unwrap())
                .unwrap();
        export.join(t["frames"][n]["file_path"].as_str().unwrap())
    };
    let first = exported(0);
    assert!(!first.symlink_metadata().unwrap().is_symlink());
    assert_ne!(
        inode(&first),
        inode(&outside),
        "an outside file was hard-linked"
    );
    assert_eq!(
        std::fs::read(&first).unwrap(),
        std::fs::read(&outside).unwrap()
    );
}

#[test]
fn photo_set_paths_are_kept_inside_the_set() {
    let tmp = tempfile::tempdir().unwrap();
    let (_, export) = tiny_left_export(tmp.path());
    let transforms = export.join("transforms.json");
    for (key, path, says) in [
        (
            "file_path",
            "../cap/capture.json",
            "leads out of its folder",
        ),
        ("mask_path", "/etc/hostname", "is an absolute path"),
    ] {
        edit_json(&transforms, |t| t["frames"][1][key] = path.into());
        let out = omniscan(&["validate", transforms.to_str().unwrap()]);
        assert_refused(&out, &format!("frames[1]: {key}: `{path}` {says}"));
        assert!(stderr(&out).contains("transforms.json"), "{}", stderr(&out));
        edit_json(&transforms, |t| {
            t["frames"][1][key] = t["frames"][0][key].clone();
        });
    }
}

#[test]
fn validate_decodes_every_image_to_its_last_pixel() {
    let tmp = tempfile::tempdir().unwrap();
    let capture = tmp.path().join("cap");
    tiny_capture(&capture);
    let image = first_image(&capture);
    let bytes = std::fs::read(&image).unwrap();
    // The header (and the IHDR chunk with the size) stays; the pixels go.
    std::fs::write(&image, &bytes[..bytes.len() / 2]).unwrap();
    let out = omniscan(&["validate", capture.to_str().unwrap()]);
    assert_refused(&out, "frames[0].file_path");
    assert!(stderr(&out).contains("cannot decode"), "{}", stderr(&out));

    // One flipped byte inside a chunk fails its CRC.
    let mut flipped = bytes.clone();
    let at = bytes.len() - 20;
    flipped[at] ^= 0x55;
    std::fs::write(&image, &flipped).unwrap();
    assert_refused(
        &omniscan(&["validate", capture.to_str().unwrap()]),
        "cannot decode",
    );
}
