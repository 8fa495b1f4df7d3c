//! Keeping the paths a file names inside the folder it describes.
//!
//! A capture's `capture.json` and a photo set's `transforms.json` or
//! `cameras.json` name their images relative to their own folder. A file
//! from someone else must not make omniscan read, probe or hard-link
//! `/etc/hostname` or `../../secret.png`, nor write a mask through a
//! symbolic link to another folder: every such path goes through
//! [`confine`] when the file is read, before anything is opened.
//!
//! A path is refused when it is absolute, when it has a `..` component, or
//! when the deepest part of it that exists (the file, or the folder it will
//! be written into) resolves, symbolic links followed, outside the folder.
//! All three are told by the path alone or by a `canonicalize` of something
//! under the folder, so the error says the same whether an outside file
//! exists or not. A user who keeps a capture's images elsewhere on purpose
//! passes `--allow-outside-paths`, which [`set_allow_outside`] records for
//! the process.

use std::path::{Component, Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

static ALLOW_OUTSIDE: AtomicBool = AtomicBool::new(false);

/// Lets every later [`confine`] accept paths outside their folder (the
/// CLI's `--allow-outside-paths`). Process-wide, since the capture and
/// photo-set readers it governs are called from every stage.
pub fn set_allow_outside(allow: bool) {
    ALLOW_OUTSIDE.store(allow, Ordering::Relaxed);
}

/// Whether [`set_allow_outside`] was given `true`.
pub fn outside_allowed() -> bool {
    ALLOW_OUTSIDE.load(Ordering::Relaxed)
}

/// `dir/relative`, or why `relative` may not be read as part of `dir`.
/// The error names the path as written; the caller adds the file and key.
pub fn confine(dir: &Path, relative: &str) -> Result<PathBuf, String> {
    confine_with(dir, relative, outside_allowed())
}

/// [`confine`] with the policy given instead of the process's.
pub fn confine_with(dir: &Path, relative: &str, allow_outside: bool) -> Result<PathBuf, String> {
    let joined = dir.join(relative);
    if allow_outside {
        return Ok(joined);
    }
    let hint = "(paths must stay inside the folder; --allow-outside-paths accepts them)";
    let path = Path::new(relative);
    if path.is_absolute() || path.has_root() {
        return Err(format!("`{relative}` is an absolute path {hint}"));
    }
    if path.components().any(|c| matches!(c, Component::ParentDir)) {
        return Err(format!(
            "`{relative}` leads out of its folder through `..` {hint}"
        ));
    }
    if !resolves_inside(dir, &joined) {
        return Err(format!(
            "`{relative}` leads out of its folder through a symbolic link {hint}"
        ));
    }
    Ok(joined)
}

/// `dir` with its links followed; `""` (the folder of a bare `capture.json`)
/// is the working directory.
pub fn canonical_folder(dir: &Path) -> std::io::Result<PathBuf> {
    Path::new(".").join(dir).canonicalize()
}

/// Whether the deepest existing ancestor of `joined` (itself included),
/// links followed, lies under `dir`. A link that cannot be followed (it
/// dangles, or loops) counts as outside.
fn resolves_inside(dir: &Path, joined: &Path) -> bool {
    let Ok(root) = canonical_folder(dir) else {
        // The folder itself is not there: nothing under it can be reached.
        return true;
    };
    let mut probe = joined;
    loop {
        if probe.symlink_metadata().is_ok() {
            return probe
                .canonicalize()
                .is_ok_and(|real| real.starts_with(&root));
        }
        match probe.parent() {
            Some(parent) if parent.starts_with(dir) && parent != probe => probe = parent,
            _ => return true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_relative_paths_are_joined() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("images")).unwrap();
        std::fs::write(dir.path().join("images/a.png"), b"x").unwrap();
        for rel in [
            "images/a.png",
            "images/not-yet.png",
            "masks/new/b.png",
            "./images/a.png",
        ] {
            assert_eq!(
                confine_with(dir.path(), rel, false).unwrap(),
                dir.path().join(rel)
            );
        }
    }

    #[test]
    fn absolute_and_parent_paths_are_refused_without_touching_them() {
        let dir = tempfile::tempdir().unwrap();
        for (rel, says) in [
            ("/etc/hostname", "absolute"),
            ("/no/such/file.png", "absolute"),
            ("../outside/secret.png", "`..`"),
            ("images/../../secret.png", "`..`"),
            ("images/../a.png", "`..`"),
        ] {
            let error = confine_with(dir.path(), rel, false).unwrap_err();
            assert!(error.contains(says), "{rel}: {error}");
            assert!(error.contains("--allow-outside-paths"), "{error}");
        }
        // Whether the outside file exists does not change the answer.
        assert_eq!(
            confine_with(dir.path(), "/etc/hostname", false)
                .unwrap_err()
                .replace("/etc/hostname", "X"),
            confine_with(dir.path(), "/no/such/file", false)
                .unwrap_err()
                .replace("/no/such/file", "X"),
        );
    }

    #[cfg(unix)]
    #[test]
    fn links_out_of_the_folder_are_refused_and_links_inside_kept() {
        let outside = tempfile::tempdir().unwrap();
        std::fs::write(outside.path().join("secret.png"), b"x").unwrap();
        let dir = tempfile::tempdir().unwrap();
        let link = |target: &Path, name: &str| {
            std::os::unix::fs::symlink(target, dir.path().join(name)).unwrap()
        };
        link(&outside.path().join("secret.png"), "file.png");
        link(outside.path(), "folder");
        link(&dir.path().join("nowhere"), "dangling.png");
        std::fs::write(dir.path().join("real.png"), b"x").unwrap();
        link(&dir.path().join("real.png"), "inside.png");
        for rel in [
            "file.png",
            "folder/secret.png",
            "folder/new-mask.png",
            "dangling.png",
        ] {
            let error = confine_with(dir.path(), rel, false).unwrap_err();
            assert!(error.contains("symbolic link"), "{rel}: {error}");
        }
        assert!(confine_with(dir.path(), "inside.png", false).is_ok());
        assert!(confine_with(dir.path(), "folder/secret.png", true).is_ok());
    }

    #[test]
    fn the_process_policy_is_off_until_asked() {
        assert!(!outside_allowed());
    }
}
