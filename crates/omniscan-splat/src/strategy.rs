//! Densification strategies: how the trainer adds and removes splats, as
//! gsplat's `DefaultStrategy` and `MCMCStrategy` objects do. The trainer
//! ([`crate::trainer::Trainer`]) asks its strategy at each step what it needs
//! (gradient statistics, MCMC's penalties and noise) and, every
//! `densify_every` steps inside the window, to refine the model.
//!
//! - [`Adaptive`]: 3DGS's clone, split and prune by the mean screen-space
//!   gradient (or AbsGS's absolute one), with periodic opacity resets;
//! - [`Mcmc`]: 3DGS as Markov chain Monte Carlo ([`crate::mcmc`]):
//!   relocation and growth by opacity, opacity and scale penalties, noise.

use rand::Rng;
use rand_chacha::ChaCha8Rng;

use crate::Splats;
use crate::adam::Adam;
use crate::gpu::training::McmcStep;
use crate::train::{Densification, TrainConfig};

/// Values per splat of the five parameter groups (means, log-scales,
/// quaternions, opacity logits, SH with `k` coefficients per channel), in
/// the order of the trainer's Adam states.
pub(crate) fn moment_strides(k: usize) -> [usize; 5] {
    [3, 3, 4, 1, k * 3]
}

/// What a refinement works on: the model, its Adam states (reindexed as
/// splats come and go), the screen-space gradient statistics and the
/// trainer's random generator.
pub struct Refinement<'a> {
    pub splats: &'a mut Splats,
    pub(crate) adam: &'a mut [Adam; 5],
    pub grad2d_sum: &'a [f32],
    pub grad2d_count: &'a [u32],
    pub rng: &'a mut ChaCha8Rng,
}

/// A densification strategy.
pub trait Strategy: Send + Sync {
    /// Readies a fresh model (not a resumed one).
    fn prepare(&self, _splats: &mut Splats) {}
    /// Whether the trainer sums each splat's screen-space gradient for it.
    fn uses_gradient_statistics(&self) -> bool;
    /// Whether opacities are reset every `reset_every` steps.
    fn resets_opacities(&self) -> bool;
    /// The step's MCMC terms for both backends, if the strategy has them.
    fn mcmc_step(
        &self,
        _splats: &Splats,
        _config: &TrainConfig,
        _extent: f32,
        _means_lr: f32,
        _step: usize,
    ) -> Option<McmcStep> {
        None
    }
    /// Adds the strategy's regularisation to a CPU step's gradients.
    fn regularise(
        &self,
        _splats: &Splats,
        _extent: f32,
        _opacity_grads: &mut [f32],
        _log_scale_grads: &mut [[f32; 3]],
    ) {
    }
    /// Changes the model after a CPU step's Adam update.
    fn after_step(
        &self,
        _splats: &mut Splats,
        _config: &TrainConfig,
        _step: usize,
        _means_lr: f32,
        _extent: f32,
    ) {
    }
    /// Adds, removes or moves splats.
    fn refine(&self, refinement: Refinement<'_>, config: &TrainConfig, extent: f32);
}

/// The strategy `config` names.
pub fn for_config(config: &TrainConfig) -> Box<dyn Strategy> {
    match config.densification {
        Densification::Adaptive => Box::new(Adaptive),
        Densification::Mcmc => Box::new(Mcmc),
    }
}

/// gsplat's default strategy: clone small and split large splats whose
/// mean screen-space gradient exceeds `grad_threshold`, prune transparent
/// ones, reset opacities periodically, never past `max_splats`.
#[derive(Debug, Clone, Copy, Default)]
pub struct Adaptive;

impl Strategy for Adaptive {
    fn uses_gradient_statistics(&self) -> bool {
        true
    }
    fn resets_opacities(&self) -> bool {
        true
    }
    fn refine(&self, r: Refinement<'_>, config: &TrainConfig, extent: f32) {
        densify(
            r.splats,
            r.adam,
            r.grad2d_sum,
            r.grad2d_count,
            config,
            extent,
            r.rng,
        );
    }
}

/// 3DGS as Markov chain Monte Carlo (see [`crate::mcmc`]).
#[derive(Debug, Clone, Copy, Default)]
pub struct Mcmc;

impl Strategy for Mcmc {
    fn prepare(&self, splats: &mut Splats) {
        crate::mcmc::prepare(splats);
    }
    fn uses_gradient_statistics(&self) -> bool {
        false
    }
    fn resets_opacities(&self) -> bool {
        false
    }
    fn mcmc_step(
        &self,
        splats: &Splats,
        config: &TrainConfig,
        extent: f32,
        means_lr: f32,
        step: usize,
    ) -> Option<McmcStep> {
        let (opacity_penalty, scale_penalty) = crate::mcmc::penalty_weights(splats.len(), extent);
        Some(McmcStep {
            opacity_penalty,
            scale_penalty,
            noise_scale: crate::mcmc::noise_scale(means_lr, extent),
            seed: crate::mcmc::noise_seed(config.seed),
            step: step as u32,
        })
    }
    fn regularise(
        &self,
        splats: &Splats,
        extent: f32,
        opacity_grads: &mut [f32],
        log_scale_grads: &mut [[f32; 3]],
    ) {
        crate::mcmc::add_regularisation(splats, extent, opacity_grads, log_scale_grads);
    }
    fn after_step(
        &self,
        splats: &mut Splats,
        config: &TrainConfig,
        step: usize,
        means_lr: f32,
        extent: f32,
    ) {
        crate::mcmc::add_noise(splats, config.seed, step, means_lr, extent);
    }
    fn refine(&self, r: Refinement<'_>, config: &TrainConfig, _extent: f32) {
        let k = r.splats.sh_coefficients();
        let adam = r.adam;
        crate::mcmc::refine(r.splats, config.max_splats, r.rng, &mut |changed, len| {
            for (a, stride) in adam.iter_mut().zip(moment_strides(k)) {
                a.reset(changed, stride, len);
            }
        });
    }
}

/// Clone, split and prune (gsplat's default strategy's refinement).
fn densify(
    s: &mut Splats,
    adam: &mut [Adam; 5],
    sum: &[f32],
    count: &[u32],
    config: &TrainConfig,
    extent: f32,
    rng: &mut ChaCha8Rng,
) {
    let n = s.len();
    let k = s.sh_coefficients();
    let sigmoid = |x: f32| 1.0 / (1.0 + (-x).exp());
    let mut keep: Vec<usize> = Vec::with_capacity(n);
    let mut clones: Vec<usize> = Vec::new();
    let mut splits: Vec<usize> = Vec::new();
    for i in 0..n {
        if sigmoid(s.opacity_logits[i]) < 0.005 {
            continue;
        }
        keep.push(i);
        let avg = if count[i] > 0 {
            sum[i] / count[i] as f32
        } else {
            0.0
        };
        if avg > config.grad_threshold {
            let largest = s.log_scales[i]
                .iter()
                .cloned()
                .fold(f32::NEG_INFINITY, f32::max)
                .exp();
            if largest <= 0.01 * extent {
                clones.push(i)
            } else {
                splits.push(i)
            }
        }
    }
    let room = config.max_splats.saturating_sub(keep.len());
    clones.truncate(room);
    splits.truncate(room.saturating_sub(clones.len()));
    let mut added: Vec<(usize, [f32; 3], Option<[f32; 3]>)> =
        clones.iter().map(|&i| (i, s.means[i], None)).collect();
    for &i in &splits {
        // Two samples from the Gaussian, both 1.6x smaller: the original becomes one of them.
        let scales = s.log_scales[i].map(|v| v.exp());
        let rot = crate::raster::quat_to_rotmat(s.quats[i]);
        let mut samples = [[0.0f32; 3]; 2];
        for sample in &mut samples {
            let z = [0; 3].map(|_| {
                let (u1, u2): (f32, f32) = (rng.random::<f32>().max(1e-7), rng.random());
                (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
            });
            for a in 0..3 {
                sample[a] =
                    s.means[i][a] + (0..3).map(|b| rot[a][b] * scales[b] * z[b]).sum::<f32>();
            }
        }
        let smaller = s.log_scales[i].map(|v| v - 1.6f32.ln());
        s.means[i] = samples[0];
        s.log_scales[i] = smaller;
        added.push((i, samples[1], Some(smaller)));
    }
    let mut out = Splats {
        sh_degree: s.sh_degree,
        antialiased: s.antialiased,
        appearance: s.appearance,
        ..Default::default()
    };
    for &i in &keep {
        out.means.push(s.means[i]);
        out.log_scales.push(s.log_scales[i]);
        out.quats.push(s.quats[i]);
        out.opacity_logits.push(s.opacity_logits[i]);
        out.sh.extend_from_slice(&s.sh[i * k..(i + 1) * k]);
    }
    for &(i, mean, scale) in &added {
        out.means.push(mean);
        out.log_scales.push(scale.unwrap_or(s.log_scales[i]));
        out.quats.push(s.quats[i]);
        out.opacity_logits.push(s.opacity_logits[i]);
        out.sh.extend_from_slice(&s.sh[i * k..(i + 1) * k]);
    }
    for (a, stride) in adam.iter_mut().zip(moment_strides(k)) {
        a.reindex(&keep, stride, added.len());
    }
    *s = out;
}
