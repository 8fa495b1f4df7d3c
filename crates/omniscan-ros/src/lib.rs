//! ROS 2 recordings for omniscan: `omniscan import ros2 BAG --out CAPTURE`
//! turns a rosbag2 recording (MCAP or sqlite3) of an in-hand scan into a
//! capture (`docs/ros2.md` has the conventions: topics, frames, the phase
//! topic).
//!
//! - [`bag`] reads the storage; [`msgs`] decodes the few message types;
//! - [`tf`] looks the grippers and the camera up in the TF tree at each
//!   image's stamp;
//! - [`import`] assembles the capture and writes it atomically.
//!
//! The storage and the encoding are read with maintained crates (`mcap`,
//! `rusqlite`, `cdr-encoding`); the TF lookup is written here, as tf2 has
//! no Rust port, and it is small.

pub mod bag;
pub mod import;
pub mod msgs;
pub mod tf;

use std::path::{Path, PathBuf};

pub use import::{ImportReport, Robot, Ros2ImportSettings, import_ros2};

/// An error of the import, naming the bag and what in it is wrong.
#[derive(Debug, thiserror::Error)]
pub enum RosError {
    #[error("{path}: {message}")]
    Bag { path: PathBuf, message: String },
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Core(#[from] omniscan_core::CoreError),
}

impl RosError {
    pub fn bag(path: &Path, message: impl Into<String>) -> RosError {
        RosError::Bag {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}
