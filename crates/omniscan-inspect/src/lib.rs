//! Defect inspection with splat digital twins (paper, "Defect Inspection"):
//! align the models of several copies of a part to the first (FPFH +
//! TEASER++-style global registration, then ICP, on filtered splat
//! centres), render the same views of every aligned model, and compare them
//! two ways, as the paper does: pixel differencing (mean per-pixel RGB L2 per
//! pair, difference images) and point differencing (distance from each
//! surface point of one model to the other, 4.5 mm threshold).
//!
//! Where the paper ranks pairs by one global number, we also locate the
//! evidence: both methods produce points on the surface (visual differences
//! are back-projected through the rendered median depth, geometric ones are
//! surface samples farther than the threshold from the other model's, and
//! pixels whose depth along the same ray differs by more than it), and a
//! difference counts against a model only where that model
//! disagrees with every other copy while the others agree with each other.
//! Colours are compared after matching each model's to the first's with a
//! slowly varying gain (lighting is baked into each scan, see
//! [`photometric`]). Such points are clustered into regions; the model with significant
//! regions is the defective one, and none is named when no model has any.
//! See [`verdict`] for the rule.

// Kernels index parallel arrays (splat attributes, RGB channels) by the same
// loop variable; iterator chains would hide the maths.
#![allow(clippy::needless_range_loop)]

pub mod align;
pub mod closeup;
pub mod differencing;
pub mod generate;
pub mod inspect;
pub mod photometric;
pub mod report;
pub mod verdict;
pub mod views;

use std::path::{Path, PathBuf};

pub use inspect::{InspectSettings, Inspection, inspect};

/// Errors of the inspection crate.
#[derive(Debug, thiserror::Error)]
pub enum InspectError {
    #[error("{path}: {message}")]
    File { path: PathBuf, message: String },
    #[error(
        "model {model} cannot be aligned to model 0: best fitness {fitness:.3} is below \
         {min_fitness} (is it a model of the same part, at the same scale?)"
    )]
    Alignment {
        /// Index of the model among those given.
        model: usize,
        fitness: f64,
        min_fitness: f64,
    },
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Core(#[from] omniscan_core::CoreError),
    #[error(transparent)]
    Splat(#[from] omniscan_splat::SplatError),
    #[error(transparent)]
    Register(#[from] omniscan_register::RegisterError),
}

impl InspectError {
    pub fn file(path: &Path, message: impl Into<String>) -> Self {
        InspectError::File {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}

/// A standard normal sample (Box-Muller), so the crate needs no extra
/// distribution crate for its few Gaussian draws.
pub(crate) fn standard_normal(rng: &mut impl rand::Rng) -> f64 {
    let u1: f64 = rng.random::<f64>().max(1e-300);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}
