//! What the scan simulator and the kinematic gripper masks both need: meshes
//! and their files (OBJ with textures, STL, PLY), the robot's gripper model
//! placed at a pose and finger opening, and the tiled mesh rasterizer that
//! renders them with labels and depth. The simulator renders whole scenes
//! with it; masking renders the gripper alone at a frame's recorded pose
//! (paper, "Object masks"). A crate of its own so that masking does not
//! depend on the simulator.

pub mod canvas;
pub mod collision;
pub mod gripper;
pub mod loaders;
pub mod mesh;
mod mjcf;
pub mod raster;
pub mod robot;

use std::path::{Path, PathBuf};

/// Errors of meshes, their files and the gripper model.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("{path}: {message}")]
    Mesh { path: PathBuf, message: String },
    #[error(transparent)]
    Core(#[from] omniscan_core::CoreError),
    #[error("{0}")]
    Invalid(String),
}

impl SceneError {
    pub fn mesh(path: &Path, message: impl Into<String>) -> Self {
        SceneError::Mesh {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}
