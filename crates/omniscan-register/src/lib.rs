//! Point clouds and registration (paper, "Aligning the scans" and "Defect
//! Inspection"): ICP with Open3D's semantics (point-to-point, point-to-plane,
//! colored, generalized), FPFH features, TEASER++-style and RANSAC global
//! registration, and the paper's rule for merging the two arms' scans.

pub mod capture_cloud;
pub mod cloud;
pub mod fpfh;
pub mod global;
pub mod grid;
pub mod icp;
pub mod neighbors;
pub mod preprocess;
pub mod ransac;
pub mod teaser;

use std::path::{Path, PathBuf};

pub use cloud::PointCloud;

/// Errors of the registration crate.
#[derive(Debug, thiserror::Error)]
pub enum RegisterError {
    #[error("{path}: {message}")]
    File { path: PathBuf, message: String },
    #[error(transparent)]
    Core(#[from] omniscan_core::CoreError),
    #[error("{0}")]
    Invalid(String),
}

impl RegisterError {
    pub fn file(path: &Path, message: impl Into<String>) -> Self {
        RegisterError::File {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}
