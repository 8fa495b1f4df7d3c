//! omniscan's pipeline as a library: the stages of the Omni-Scan paper
//! (Qiu et al. 2025), one function each, over typed values.
//!
//! | stage | function | paper |
//! |---|---|---|
//! | simulate a bimanual in-hand scan | [`simulate::simulate`] | "Bimanual scanning" |
//! | gripper and object masks | [`mask::mask`] | "Object masks" |
//! | train a model (one arm, or both merged) | [`train::train`] | "3DGS Training" |
//! | align the right arm onto the left | [`align::align`] | "3DGS Training", merge |
//! | the whole twin, resumable | [`twin::twin`] | "3DGS Training" |
//! | score a model against views | [`evaluate::evaluate`] | "Results" |
//! | render a model | [`render::render`] | |
//! | find the defective copy | [`inspect::inspect`] | "Defect inspection" |
//! | make a (defective) copy | [`inspect::make_copy`] | |
//! | a watertight, coloured mesh of a twin | [`geometry::mesh`] | |
//! | a simulation asset (URDF, MJCF) of a twin | [`geometry::asset`] | |
//! | a ROS 2 recording to a capture | [`import::import_ros2`] | |
//!
//! Each stage takes one settings struct: its fields carry their unit in
//! their name or doc, and its `Default` is the documented default. The same
//! structs derive the command line's flags (`clap::Args`), so a default is
//! written once, here. Each stage returns a report that serialises with
//! serde (the CLI's `--json` prints it) and tells its progress through a
//! [`Progress`] the caller hands in ([`progress::Silent`] for none).
//!
//! Errors are `anyhow` errors whose message names the file and the problem;
//! the CLI prints them with their context (`{:#}`).
//!
//! ```no_run
//! use omniscan_pipeline::Silent;
//! use omniscan_pipeline::twin::{TwinSettings, twin};
//!
//! # fn main() -> anyhow::Result<()> {
//! let settings = TwinSettings { steps: 1000, ..TwinSettings::default() };
//! let report = twin("scans/tee".as_ref(), "twins/tee".as_ref(), &settings, &Silent)?;
//! println!("{} splats", report.stages.twin.report.splats);
//! # Ok(())
//! # }
//! ```

pub mod align;
pub mod demo;
pub mod deviation;
pub mod evaluate;
pub mod failure;
pub mod geometry;
pub mod import;
pub mod inspect;
pub mod mask;
pub mod memory;
pub mod pose_refinement;
pub mod progress;
pub mod render;
pub mod reports;
pub mod settings;
pub mod share;
pub mod simulate;
pub mod train;
pub mod twin;
pub mod views;

pub use progress::{Bars, Progress, Silent};
