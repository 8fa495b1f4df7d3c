//! One process at a time per output: a stage that writes a folder (or a
//! file) holds an advisory lock on `.omniscan.lock` in it (or `OUT.lock`
//! beside it), so a second run on the same output stops at once, naming the
//! first, instead of the two mixing their stages. The lock is the operating
//! system's (`flock`), so a killed process leaves no stale lock behind; the
//! file keeps the holder's process id and command for the message.

use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

use crate::error::{CoreError, Result};

/// A held lock; released when dropped (or when the process ends).
#[derive(Debug)]
pub struct OutputLock {
    _file: std::fs::File,
    path: PathBuf,
}

impl OutputLock {
    /// Locks the folder `dir` (created if missing) for `command`, and
    /// removes the temporary files a killed run left in it and its
    /// subfolders ([`remove_stale_temporaries`]).
    pub fn folder(dir: &Path, command: &str) -> Result<OutputLock> {
        std::fs::create_dir_all(dir).map_err(|e| CoreError::io(dir, e))?;
        let lock = Self::at(&dir.join(".omniscan.lock"), dir, command)?;
        remove_stale_temporaries(dir, std::time::Duration::from_secs(60))?;
        Ok(lock)
    }

    /// Locks the output file `out` for `command` (`OUT.lock` beside it).
    pub fn file(out: &Path, command: &str) -> Result<OutputLock> {
        let mut name = out.as_os_str().to_owned();
        name.push(".lock");
        let path = PathBuf::from(name);
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| CoreError::io(dir, e))?;
        }
        Self::at(&path, out, command)
    }

    fn at(path: &Path, output: &Path, command: &str) -> Result<OutputLock> {
        // A holder removes the file as it lets go (see `Drop`): a lock taken
        // on a file that was removed meanwhile guards nothing, so it is
        // taken again on the file now at `path`.
        for _ in 0..100 {
            let file = Self::try_at(path, output)?;
            if same_file(&file, path) {
                return Self::hold(file, path, command);
            }
        }
        Err(CoreError::Invalid(format!(
            "{}: the lock file keeps being replaced; is another program removing it?",
            path.display()
        )))
    }

    /// Opens (or creates) the lock file at `path` and takes its lock.
    fn try_at(path: &Path, output: &Path) -> Result<std::fs::File> {
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(path)
            .map_err(|e| CoreError::io(path, e))?;
        match file.try_lock() {
            Ok(()) => Ok(file),
            Err(std::fs::TryLockError::WouldBlock) => {
                let mut holder = String::new();
                let _ = file.read_to_string(&mut holder);
                let holder = holder.trim();
                let holder = if holder.is_empty() {
                    "another omniscan process".to_string()
                } else {
                    holder.to_string()
                };
                Err(CoreError::Busy {
                    path: output.to_path_buf(),
                    holder,
                })
            }
            Err(std::fs::TryLockError::Error(e)) => Err(CoreError::io(path, e)),
        }
    }

    /// Writes who holds the lock into its file.
    fn hold(mut file: std::fs::File, path: &Path, command: &str) -> Result<OutputLock> {
        let holder = format!("omniscan {command} (process {})", std::process::id());
        file.set_len(0)
            .and_then(|()| file.rewind())
            .and_then(|()| file.write_all(holder.as_bytes()))
            .map_err(|e| CoreError::io(path, e))?;
        Ok(OutputLock {
            _file: file,
            path: path.to_path_buf(),
        })
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// The lock file goes with the lock, so outputs are not left beside
/// `.lock` files; it is removed while still locked, and a process that
/// opened it meanwhile finds it replaced and locks the new one.
impl Drop for OutputLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Whether the open `file` is the file at `path` now.
fn same_file(file: &std::fs::File, path: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        match (file.metadata(), std::fs::metadata(path)) {
            (Ok(a), Ok(b)) => (a.dev(), a.ino()) == (b.dev(), b.ino()),
            _ => false,
        }
    }
    #[cfg(not(unix))]
    {
        let _ = file;
        path.exists()
    }
}

/// Removes the temporary files of atomic writes (`.omniscan-tmp-*`) under
/// `dir` not written to for `age`: a run killed mid-write leaves its
/// temporary file behind. Called with the folder's lock held, so no other
/// omniscan stage of that folder is writing; a file written to within `age`
/// is left, in case a lone `train` writes beside it. Returns how many went.
pub fn remove_stale_temporaries(dir: &Path, age: std::time::Duration) -> Result<usize> {
    let mut removed = 0;
    let entries = std::fs::read_dir(dir).map_err(|e| CoreError::io(dir, e))?;
    for entry in entries {
        let entry = entry.map_err(|e| CoreError::io(dir, e))?;
        let path = entry.path();
        let kind = entry.file_type().map_err(|e| CoreError::io(&path, e))?;
        if kind.is_dir() {
            removed += remove_stale_temporaries(&path, age)?;
            continue;
        }
        let temporary = entry
            .file_name()
            .to_string_lossy()
            .starts_with(".omniscan-tmp-");
        let stale = entry
            .metadata()
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|elapsed| elapsed >= age);
        if kind.is_file() && temporary && stale {
            std::fs::remove_file(&path).map_err(|e| CoreError::io(&path, e))?;
            removed += 1;
        }
    }
    Ok(removed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_killed_runs_temporary_files_go_when_the_folder_is_locked_again() {
        let dir = tempfile::tempdir().unwrap();
        let images = dir.path().join("images");
        std::fs::create_dir_all(&images).unwrap();
        let stale = images.join(".omniscan-tmp-killed");
        let fresh = dir.path().join(".omniscan-tmp-writing");
        let kept = images.join("left_000.png");
        for file in [&stale, &fresh, &kept] {
            std::fs::write(file, b"x").unwrap();
        }
        let old = std::time::SystemTime::now() - std::time::Duration::from_secs(3600);
        for file in [&stale, &kept] {
            std::fs::File::options()
                .write(true)
                .open(file)
                .unwrap()
                .set_modified(old)
                .unwrap();
        }
        let _lock = OutputLock::folder(dir.path(), "sim").unwrap();
        assert!(!stale.exists());
        assert!(
            fresh.exists(),
            "a file written to just now may be another writer's"
        );
        assert!(kept.exists());
    }

    #[test]
    fn a_second_holder_is_refused_naming_the_first_until_it_lets_go() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("twin");
        let first = OutputLock::folder(&out, "twin").unwrap();
        let err = OutputLock::folder(&out, "twin").unwrap_err().to_string();
        assert!(
            err.contains("is in use by omniscan twin (process "),
            "{err}"
        );
        assert!(err.contains(&std::process::id().to_string()), "{err}");
        drop(first);
        let again = OutputLock::folder(&out, "mask").unwrap();
        assert!(again.path().ends_with(".omniscan.lock"));
        // A file's lock is its own: another output in the folder is free.
        let model = out.join("left.ply");
        let _file = OutputLock::file(&model, "train").unwrap();
        assert!(OutputLock::file(&model, "train").is_err());
        assert!(OutputLock::file(&out.join("right.ply"), "train").is_ok());
    }

    /// The lock file goes with its lock, and removing it as the holder lets
    /// go never lets two holders in at once: threads hold flock locks as
    /// processes do (one per open file).
    #[test]
    fn lock_files_go_with_their_lock_and_one_holder_holds_at_a_time() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        let dir = tempfile::tempdir().unwrap();
        let model = dir.path().join("m.ply");
        let lock = OutputLock::file(&model, "train").unwrap();
        assert!(lock.path().exists());
        let path = lock.path().to_path_buf();
        drop(lock);
        assert!(!path.exists(), "the lock file outlived its lock");

        let holders = AtomicUsize::new(0);
        let held = AtomicUsize::new(0);
        std::thread::scope(|scope| {
            for _ in 0..4 {
                scope.spawn(|| {
                    for _ in 0..300 {
                        if let Ok(lock) = OutputLock::file(&model, "train") {
                            assert_eq!(holders.fetch_add(1, Ordering::SeqCst), 0, "two holders");
                            held.fetch_add(1, Ordering::SeqCst);
                            std::thread::yield_now();
                            holders.fetch_sub(1, Ordering::SeqCst);
                            drop(lock);
                        }
                    }
                });
            }
        });
        assert!(held.load(Ordering::SeqCst) > 0);
        assert!(!path.exists());
    }
}
