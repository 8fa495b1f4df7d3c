//! Core of omniscan: geometry, cameras, the capture format, pose processing
//! (Omni-Scan paper, "Pose Processing"), the scan plan and image I/O. Every
//! other omniscan crate builds on these types.

pub mod camera;
pub mod capture;
pub mod digest;
pub mod error;
pub mod geometry;
pub mod image_io;
pub mod io;
pub mod lens;
pub mod lock;
pub mod nerfstudio;
pub mod paths;
pub mod plan;
pub mod ply;
pub mod poses;
pub mod tiles;

pub use camera::Intrinsics;
pub use capture::{Arm, Capture, CaptureFile, Frame};
pub use error::{CoreError, Result};
pub use geometry::{Pose, RigidTransform};
