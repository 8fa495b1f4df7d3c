//! Errors of the core crate. Every error that concerns a file names it, so a
//! user can tell which of a capture's hundreds of files is at fault.

use std::path::PathBuf;

/// An error from reading or writing omniscan files.
#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
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
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        CoreError::Io {
            path: path.into(),
            source,
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
