//! 3D Gaussian Splat models (Kerbl et al. 2023) for omniscan: the model,
//! its standard PLY and `.splat` files, spherical-harmonics colour, and the
//! CPU reference rasterizer (paper, "3DGS Training").
//!
//! The rasterizer follows gsplat's conventions exactly (pixel centres at
//! +0.5, EWA projection with a 0.3-pixel low-pass filter and an antialiased
//! mode, 16x16 tiles, front-to-back compositing with alpha ≤ 0.999, skip below
//! 1/255, stop when transmittance falls to 1e-4), and is written generically
//! over the float type so the same code runs in f32 and, for conformance and
//! finite-difference checks, in f64.
//!
//! Training: [`train`] holds the settings, the masked loss and the
//! initialisation; [`trainer::Trainer`] steps a run (CPU or GPU alike);
//! [`strategy`] holds the densification strategies behind one trait;
//! [`adam`] the optimiser; [`evaluation`] the typed figures; [`view`],
//! [`packed`] and [`views`] a training view, its packed form and where views
//! come from.

// Kernels index parallel arrays (xyz, RGB, matrix rows) by the same loop
// variable; iterator chains would hide the maths.
#![allow(clippy::needless_range_loop)]

pub mod adam;
pub mod backend;
pub mod backward;
pub mod checkpoint;
pub mod compressed_ply;
pub mod evaluation;
pub mod glb;
pub mod gpu;
pub mod lpips;
pub mod mcmc;
pub mod metrics;
pub mod model;
pub mod offset;
pub mod orbit;
pub mod packed;
pub mod ply;
pub mod pose;
pub mod raster;
pub mod sh;
pub mod spz;
pub mod strategy;
pub mod train;
pub mod trainer;
pub mod transform;
pub mod view;
pub mod views;

/// Helpers the unit tests share.
#[cfg(test)]
pub(crate) mod test_support {
    /// `work` run on a pool of `threads` threads, for checking that a
    /// result does not depend on how many there are.
    pub fn on_threads<R: Send>(threads: usize, work: impl FnOnce() -> R + Send) -> R {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(work)
    }

    /// A pinhole camera with world-to-camera `viewmat`, focal length `focal`
    /// pixels and its principal point at the image centre (near 0.01, far 100).
    pub fn pinhole(
        viewmat: [[f32; 4]; 4],
        focal: f32,
        width: u32,
        height: u32,
    ) -> crate::raster::Camera<f32> {
        crate::raster::Camera {
            viewmat,
            fx: focal,
            fy: focal,
            cx: width as f32 / 2.0,
            cy: height as f32 / 2.0,
            width,
            height,
            near: 0.01,
            far: 100.0,
        }
    }

    /// A deterministic pseudo-random sequence in [0, 1), for test scenes.
    pub struct Lcg(pub u64);
    impl Lcg {
        pub fn next(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// `n` random splats of SH `degree` within `extent` of the origin,
    /// log-scales in [-6, -4], unit quaternions, for the format tests.
    pub fn random_model(seed: u64, degree: usize, n: usize, extent: f32) -> crate::Splats {
        let mut rng = Lcg(seed);
        let mut s = crate::Splats {
            sh_degree: degree,
            ..Default::default()
        };
        for _ in 0..n {
            s.means
                .push([0, 1, 2].map(|_| (rng.next() as f32 - 0.5) * 2.0 * extent));
            s.log_scales
                .push([0, 1, 2].map(|_| -6.0 + 2.0 * rng.next() as f32));
            let q = [0, 1, 2, 3].map(|_| rng.next() as f32 - 0.5);
            let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            s.quats.push(q.map(|v| v / norm));
            s.opacity_logits.push(4.0 * (rng.next() as f32 - 0.5));
            for _ in 0..crate::sh::coefficients(degree) {
                s.sh.push([0, 1, 2].map(|_| rng.next() as f32 - 0.5));
            }
        }
        s
    }
}

use std::path::{Path, PathBuf};

pub use model::Splats;

/// Errors of the splat crate.
#[derive(Debug, thiserror::Error)]
pub enum SplatError {
    #[error("{path}: {message}")]
    File { path: PathBuf, message: String },
    #[error(transparent)]
    Core(#[from] omniscan_core::CoreError),
    #[error("{0}")]
    Invalid(String),
}

impl SplatError {
    pub fn file(path: &Path, message: impl Into<String>) -> Self {
        SplatError::File {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}

/// The float types the reference code runs in.
pub trait Real:
    num_traits::Float
    + num_traits::FromPrimitive
    + Send
    + Sync
    + std::fmt::Debug
    + std::iter::Sum
    + 'static
{
    fn c(x: f64) -> Self {
        Self::from_f64(x).unwrap()
    }
}
impl Real for f32 {}
impl Real for f64 {}
