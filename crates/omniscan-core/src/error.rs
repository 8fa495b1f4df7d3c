//! Errors of the core crate. Every error that concerns a file names it, so a
//! user can tell which of a capture's hundreds of files is at fault.

use std::path::PathBuf;

/// An error from reading or writing omniscan files.
#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    /// The cause is in the message and not chained as a `source` too, or
    /// a report that prints the chain (`{:#}`) would say it twice.
    #[error("{path}: {cause}")]
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
        let cause = std::fs::read(path).unwrap_err().to_string();
        assert_eq!(chain.matches(&cause).count(), 1, "{chain}");
    }
}
