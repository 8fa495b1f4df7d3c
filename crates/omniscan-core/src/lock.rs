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
    /// Locks the folder `dir` (created if missing) for `command`.
    pub fn folder(dir: &Path, command: &str) -> Result<OutputLock> {
        std::fs::create_dir_all(dir).map_err(|e| CoreError::io(dir, e))?;
        Self::at(&dir.join(".omniscan.lock"), dir, command)
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
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(path)
            .map_err(|e| CoreError::io(path, e))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let mut holder = String::new();
                let _ = file.read_to_string(&mut holder);
                let holder = holder.trim();
                let holder = if holder.is_empty() {
                    "another omniscan process".to_string()
                } else {
                    holder.to_string()
                };
                return Err(CoreError::Invalid(format!(
                    "{} is in use by {holder}: wait for it to finish or stop it (a second run on the same output would mix their results)",
                    output.display()
                )));
            }
            Err(std::fs::TryLockError::Error(e)) => return Err(CoreError::io(path, e)),
        }
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
