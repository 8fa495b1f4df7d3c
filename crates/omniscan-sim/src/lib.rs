//! The omniscan scan simulator: renders the captures of a bimanual in-hand
//! scan (paper, "Scanning Procedure") with ground truth for every later stage.

pub mod builtin;
pub mod canvas;
pub mod defect;
pub mod grasp;
pub mod gripper;
pub mod loaders;
pub mod mesh;
pub mod raster;
pub mod scene;
pub mod simulate;

pub use simulate::{SimConfig, SimSummary, Simulation};

use std::path::{Path, PathBuf};

/// Errors of the simulator.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("{path}: {message}")]
    Mesh { path: PathBuf, message: String },
    #[error(transparent)]
    Core(#[from] omniscan_core::CoreError),
    #[error("{0}")]
    Invalid(String),
}

impl SimError {
    pub fn mesh(path: &Path, message: impl Into<String>) -> Self {
        SimError::Mesh {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}
