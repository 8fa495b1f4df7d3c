//! The omniscan scan simulator: renders the captures of a bimanual in-hand
//! scan (paper, "Scanning Procedure") with ground truth for every later stage.

pub mod builtin;
pub mod defect;
pub mod grasp;
pub mod scene;
pub mod simulate;

// Meshes, the gripper model and the rasterizer live in `omniscan-scene`,
// which masking shares; the simulator's modules name them as its own.
pub use omniscan_scene::{canvas, gripper, loaders, mesh, raster};

pub use simulate::{SimConfig, SimSummary, Simulation};

use std::path::{Path, PathBuf};

/// Errors of the simulator.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("{path}: {message}")]
    Mesh { path: PathBuf, message: String },
    #[error(transparent)]
    Core(#[from] omniscan_core::CoreError),
    /// A mesh, its file or the gripper model (`omniscan-scene`).
    #[error(transparent)]
    Scene(#[from] omniscan_scene::SceneError),
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
