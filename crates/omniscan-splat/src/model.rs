//! A 3D Gaussian Splat model as stored: means, log-scales, rotation
//! quaternions (w, x, y, z, not necessarily unit), opacity logits and
//! spherical-harmonics coefficients up to degree 3, all pre-activation, as in
//! the standard 3DGS PLY.

use crate::raster::{Colors, Gaussians};
use crate::sh::coefficients;
use crate::{Real, SplatError};
use rayon::prelude::*;

/// A splat model. `sh` holds `(sh_degree+1)²` RGB triples per splat, basis
/// index major (gsplat's `[N, K, 3]`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Splats {
    pub means: Vec<[f32; 3]>,
    pub log_scales: Vec<[f32; 3]>,
    pub quats: Vec<[f32; 4]>,
    pub opacity_logits: Vec<f32>,
    pub sh_degree: usize,
    pub sh: Vec<[f32; 3]>,
    /// Trained with the antialiased (Mip-Splatting) opacity compensation.
    pub antialiased: bool,
    /// What the SH are a function of (see [`crate::raster::Appearance`]).
    pub appearance: crate::raster::Appearance,
}

/// The largest log-scale a model may hold: e²⁰ ≈ 4.9·10⁸ units. A larger
/// splat's covariance, squared and projected, overflows `f32` and renders
/// NaN; no trained model comes near it.
pub const MAX_LOG_SCALE: f32 = 20.0;

/// The furthest a splat may lie from the origin along an axis, in model
/// units, for the same reason.
pub const MAX_COORDINATE: f32 = 1e9;

impl Splats {
    pub fn len(&self) -> usize {
        self.means.len()
    }
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }
    /// Coefficients per channel.
    pub fn sh_coefficients(&self) -> usize {
        coefficients(self.sh_degree)
    }

    /// Checks array sizes, that every value is finite, and that no splat is
    /// beyond [`MAX_LOG_SCALE`] or [`MAX_COORDINATE`].
    pub fn validate(&self) -> Result<(), SplatError> {
        let n = self.len();
        let k = self.sh_coefficients();
        if self.sh_degree > 3 {
            return Err(SplatError::Invalid(format!(
                "SH degree {} is above 3",
                self.sh_degree
            )));
        }
        if self.log_scales.len() != n
            || self.quats.len() != n
            || self.opacity_logits.len() != n
            || self.sh.len() != n * k
        {
            return Err(SplatError::Invalid(
                "splat arrays have different lengths".into(),
            ));
        }
        let bad =
            |i: usize| SplatError::Invalid(format!("splat {i} has a NaN or infinite parameter"));
        for i in 0..n {
            let finite = self.means[i]
                .iter()
                .chain(&self.log_scales[i])
                .chain(&self.quats[i])
                .all(|v| v.is_finite())
                && self.opacity_logits[i].is_finite()
                && self.sh[i * k..(i + 1) * k]
                    .iter()
                    .flatten()
                    .all(|v| v.is_finite());
            if !finite {
                return Err(bad(i));
            }
            if let Some(&s) = self.log_scales[i].iter().find(|&&s| s > MAX_LOG_SCALE) {
                return Err(SplatError::Invalid(format!(
                    "splat {i} has a log-scale of {s}, above {MAX_LOG_SCALE} (a splat larger than 10⁸ units)"
                )));
            }
            if self.means[i].iter().any(|v| v.abs() > MAX_COORDINATE) {
                return Err(SplatError::Invalid(format!(
                    "splat {i} lies at {:?}, further than {MAX_COORDINATE:e} units from the origin on an axis",
                    self.means[i]
                )));
            }
            if self.quats[i].iter().all(|&v| v == 0.0) {
                return Err(SplatError::Invalid(format!(
                    "splat {i} has a zero rotation quaternion"
                )));
            }
        }
        Ok(())
    }

    /// The settings the model renders with: the footprint filter and the
    /// appearance it was trained with, over `background`.
    pub fn render_settings<F: Real>(&self, background: [F; 3]) -> crate::raster::Settings<F> {
        crate::raster::Settings {
            mode: if self.antialiased {
                crate::raster::Mode::Antialiased
            } else {
                crate::raster::Mode::Classic
            },
            appearance: self.appearance,
            background,
            ..crate::raster::Settings::default()
        }
    }

    /// Activated parameters in float type `F` for the rasterizer.
    pub fn gaussians<F: Real>(&self) -> Gaussians<F> {
        self.gaussians_up_to(self.sh_degree)
    }

    /// [`Splats::gaussians`] with the SH bands up to `degree` only (at most
    /// the model's): training raises the degree on a schedule. Copies each
    /// coefficient once into storage sized up front; per step, a copy of all
    /// bands cut down afterwards through a growing vector cost two 25 MB
    /// copies and their reallocations at 130k splats.
    pub fn gaussians_up_to<F: Real>(&self, degree: usize) -> Gaussians<F> {
        // In parallel: the trainer converts every step, and on one thread
        // this was a fifth of a 3000-step DTU run's serial time.
        let c = |v: f32| F::c(v as f64);
        let degree = degree.min(self.sh_degree);
        let (k, kept) = (self.sh_coefficients(), coefficients(degree));
        let coeffs = (0..self.len() * kept)
            .into_par_iter()
            .map(|j| self.sh[j / kept * k + j % kept].map(c))
            .collect();
        Gaussians {
            means: self.means.par_iter().map(|m| m.map(c)).collect(),
            scales: self
                .log_scales
                .par_iter()
                .map(|s| s.map(|v| c(v).exp()))
                .collect(),
            quats: self.quats.par_iter().map(|q| q.map(c)).collect(),
            opacities: self
                .opacity_logits
                .par_iter()
                .map(|&o| F::one() / (F::one() + (-c(o)).exp()))
                .collect(),
            colors: Colors::Sh { degree, coeffs },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(mean: [f32; 3], log_scale: f32) -> Splats {
        Splats {
            means: vec![mean],
            log_scales: vec![[log_scale; 3]],
            quats: vec![[1.0, 0.0, 0.0, 0.0]],
            opacity_logits: vec![0.0],
            sh: vec![[0.5; 3]],
            ..Default::default()
        }
    }

    /// Finite but absurd splats rendered NaN and scored "PSNR NaN dB".
    #[test]
    fn splats_too_large_or_too_far_are_refused() {
        assert!(one([0.0; 3], MAX_LOG_SCALE).validate().is_ok());
        assert!(one([MAX_COORDINATE, 0.0, 0.0], -40.0).validate().is_ok());
        let error = one([0.0; 3], 80.0).validate().unwrap_err().to_string();
        assert!(error.contains("log-scale of 80"), "{error}");
        let error = one([0.0, -1e12, 0.0], 0.0)
            .validate()
            .unwrap_err()
            .to_string();
        assert!(error.contains("further than"), "{error}");
    }
}
