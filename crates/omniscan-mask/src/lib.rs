//! Masks for in-hand scans (paper, "Mask Processing"): for every image, which
//! pixels show the gripper and which show the held object.
//!
//! - [`gripper`]: the kinematic gripper mask. The robot knows where its
//!   gripper is, so the gripper model is rendered at the frame's recorded pose
//!   and finger opening, then checked pixel by pixel against the sensor depth
//!   (the object in front of a finger hides it; a finger that is not where the
//!   model says lets the background through). This replaces the paper's U-Net
//!   + SAM2 propagation, which needed hand-picked seed frames.
//! - [`object`]: the paper's object pipeline. A foreground (near depth and
//!   non-zero optical flow between neighbouring frames), candidate segments,
//!   and for each candidate the non-robot score S_NR (mean depth change
//!   against the empty-gripper pass at the same pose) and the non-gripper score
//!   S_NG (share of the candidate outside the gripper mask); candidates over
//!   both thresholds form the object mask.
//! - The model roles, each behind a trait with a weight-free default and a
//!   learned backend run from an ONNX file: [`depth`] (sensor depth; a
//!   monocular network such as Depth Anything V2, put in metres on the
//!   gripper model's pixels), [`flow`] (pyramidal Lucas-Kanade; RAFT-style
//!   networks), candidate segments ([`segment`]: Felzenszwalb-Huttenlocher
//!   graph segmentation on colour and depth; [`sam`]: Segment Anything), and
//!   the gripper ([`gripper`] kinematic; [`unet`] the paper's U-Net, trained
//!   here, run in Rust or exported to ONNX). [`onnx`] loads ONNX Runtime at
//!   run time and writes ONNX files.
//! - [`pipeline`]: a whole capture, written next to its images with the paths
//!   recorded in `capture.json`, resumable; and evaluation against the
//!   simulator's ground truth.

// Pixel loops index several planes by the same index; iterators would hide that.
#![allow(clippy::needless_range_loop)]

pub mod depth;
pub mod flow;
pub mod gripper;
pub mod object;
pub mod onnx;
pub mod pipeline;
pub mod plane;
pub mod sam;
pub mod segment;
pub mod unet;

pub use pipeline::{
    Evaluation, MaskRunSummary, MaskSettings, evaluate_capture, mask_capture, mask_frame,
};
pub use plane::Plane;

use std::path::PathBuf;

/// Errors of the masking stage.
#[derive(Debug, thiserror::Error)]
pub enum MaskError {
    #[error(transparent)]
    Core(#[from] omniscan_core::CoreError),
    #[error(transparent)]
    Scene(#[from] omniscan_scene::SceneError),
    #[error("{path}: {message}")]
    File { path: PathBuf, message: String },
    #[error(transparent)]
    Onnx(#[from] omniscan_onnx::OnnxError),
    #[error("{0}")]
    Invalid(String),
}

impl MaskError {
    pub fn file(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        MaskError::File {
            path: path.into(),
            message: message.into(),
        }
    }
}

pub type Result<T, E = MaskError> = std::result::Result<T, E>;

/// Checks that an image or depth map read from `path` has the camera's size.
pub(crate) fn check_size(
    path: &std::path::Path,
    w: usize,
    h: usize,
    expected: (u32, u32),
) -> Result<()> {
    if (w as u32, h as u32) != expected {
        return Err(MaskError::file(
            path,
            format!(
                "is {w}x{h} but the capture's camera is {}x{}",
                expected.0, expected.1
            ),
        ));
    }
    Ok(())
}
