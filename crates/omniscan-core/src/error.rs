//! Errors of the core crate. Every error that concerns a file names it, so a
//! user can tell which of a capture's hundreds of files is at fault.

use std::path::PathBuf;

/// An error from reading or writing omniscan files.
#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    /// The cause is in the message and not chained as a `source` too, or
    /// a report that prints the chain (`{:#}`) would say it twice.
    #[error("{path}: {}", plain_words(.cause))]
    Io {
        path: PathBuf,
        cause: std::io::Error,
    },
    #[error("{path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Image { path: PathBuf, message: String },
    #[error("{path} is not a valid capture:\n{}", format_problems(.problems))]
    InvalidCapture {
        path: PathBuf,
        problems: Vec<String>,
    },
    #[error("{0}")]
    Invalid(String),
    /// An output another process holds the lock of ([`crate::lock`]).
    #[error(
        "{path} is in use by {holder}: wait for it to finish or stop it (a second run on the same output would mix their results)"
    )]
    Busy { path: PathBuf, holder: String },
}

/// The OS's error in words a user reads without knowing error numbers
/// ("Is a directory (os error 21)" said of a model path means the user gave
/// a folder where a file belongs).
fn plain_words(cause: &std::io::Error) -> String {
    use std::io::ErrorKind;
    match cause.kind() {
        ErrorKind::NotFound => "no such file or directory".into(),
        ErrorKind::IsADirectory => "is a directory, where a file was expected".into(),
        ErrorKind::NotADirectory => "a part of the path is a file, not a directory".into(),
        ErrorKind::PermissionDenied => "permission denied".into(),
        ErrorKind::StorageFull => "no space left on the device".into(),
        ErrorKind::FileTooLarge => {
            "the file is larger than this process may write (a file-size limit)".into()
        }
        _ => cause.to_string(),
    }
}

fn format_problems(problems: &[String]) -> String {
    const SHOWN: usize = 25;
    let mut text = problems
        .iter()
        .take(SHOWN)
        .map(|p| format!("  - {p}"))
        .collect::<Vec<_>>()
        .join("\n");
    if problems.len() > SHOWN {
        text.push_str(&format!(
            "\n  ... and {} more problems",
            problems.len() - SHOWN
        ));
    }
    text
}

impl CoreError {
    pub fn io(path: impl Into<PathBuf>, cause: std::io::Error) -> Self {
        CoreError::Io {
            path: path.into(),
            cause,
        }
    }
    pub fn parse(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        CoreError::Parse {
            path: path.into(),
            message: message.into(),
        }
    }
    pub fn image(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        CoreError::Image {
            path: path.into(),
            message: message.into(),
        }
    }
}

pub type Result<T, E = CoreError> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_file_is_named_with_its_cause_once() {
        let path = std::path::Path::new("/nonexistent/model.ply");
        let error = CoreError::io(path, std::fs::read(path).unwrap_err());
        let text = error.to_string();
        assert!(text.starts_with("/nonexistent/model.ply: "), "{text}");
        // A report that walks the source chain must not repeat the cause.
        let mut chain = text.clone();
        let mut source = std::error::Error::source(&error);
        while let Some(s) = source {
            chain.push_str(&format!(": {s}"));
            source = s.source();
        }
        assert_eq!(chain.matches("no such file").count(), 1, "{chain}");
        assert!(!chain.contains("os error"), "{chain}");
    }

    #[test]
    fn a_directory_given_for_a_file_is_said_plainly() {
        let dir = std::env::temp_dir();
        let error = CoreError::io(&dir, std::fs::read(&dir).unwrap_err());
        assert!(
            error
                .to_string()
                .ends_with(": is a directory, where a file was expected"),
            "{error}"
        );
    }
}
