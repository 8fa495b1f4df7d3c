//! Densification as Markov chain Monte Carlo (Kheradmand et al., "3D
//! Gaussian Splatting as Markov Chain Monte Carlo", NeurIPS 2024), the
//! trainer's alternative to clone/split/prune (the "or MCMC").
//!
//! The splats are samples of the scene's density. Instead of cloning and
//! splitting by screen-space gradient, every 100 steps:
//! - **relocation:** splats whose opacity fell to 0.005 or below move onto
//!   live ones, drawn with probability proportional to opacity;
//! - **growth:** the count grows by 5% (up to the cap), new splats again
//!   drawn onto live ones by opacity.
//!
//! A splat that N copies share keeps its rendered contribution: each copy
//! takes opacity o' = 1 − (1 − o)^(1/N) and a scale chosen so the copies'
//! sum matches the original (the paper's equation 9). Between refinements,
//! near-transparent splats take a random walk (noise shaped by their own
//! covariance, gated by a steep sigmoid of opacity, scaled by the position
//! learning rate): the "Langevin" part that lets dead splats explore. The
//! loss adds L1 penalties on opacity and scale (0.01 each, gsplat's MCMC
//! preset), so splats that are not needed fade and get relocated.
//!
//! The constants are gsplat's `MCMCStrategy` and MCMC preset. One change:
//! the scene is not normalised here (an in-hand capture is in metres), so
//! the scale penalty and the noise are taken in units of the scene extent,
//! which makes them the same on a 5 cm object as on a unit-sphere scene.
//!
//! The noise draws its normals from a counter-based hash of (seed, step,
//! splat), so a step's noise does not depend on thread scheduling, and the
//! GPU's kernel (`gpu/optimise.wgsl`, `noise`) draws the same numbers.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::Splats;

/// Splats at or below this opacity are dead and get relocated.
pub const MIN_OPACITY: f32 = 0.005;
/// Growth per refinement: a twentieth of the count (5%, rounded down).
pub const GROWTH_DIVISOR: usize = 20;
/// Noise scale relative to the position learning rate.
pub const NOISE_LR: f32 = 5e5;
/// Weight of the mean opacity in the loss.
pub const OPACITY_REGULARISATION: f32 = 0.01;
/// Weight of the mean scale (in scene extents) in the loss.
pub const SCALE_REGULARISATION: f32 = 0.01;
/// MCMC starts every splat at this opacity, and a tenth of its size.
pub const INITIAL_OPACITY: f32 = 0.5;
pub const INITIAL_SCALE_FACTOR: f32 = 0.1;
/// Copies of one splat beyond this count share as if there were this many.
const MAX_SHARE: usize = 51;

/// Opacity and scale factor for each of `copies` splats that replace one of
/// opacity `opacity` (the paper's equation 9): the copies, composited on
/// top of each other, have the original's opacity, and their summed
/// profile its peak.
pub fn shared_opacity_and_scale(opacity: f32, copies: usize) -> (f32, f32) {
    let n = copies.clamp(1, MAX_SHARE);
    let o = opacity.clamp(0.0, 1.0) as f64;
    let shared = 1.0 - (1.0 - o).powf(1.0 / n as f64);
    // Σ_{i=1}^{n} Σ_{k=0}^{i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)
    let mut denominator = 0.0f64;
    for i in 1..=n {
        let mut binomial = 1.0f64;
        for k in 0..i {
            if k > 0 {
                binomial *= (i - k) as f64 / k as f64;
            }
            let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
            denominator += binomial * sign * shared.powi(k as i32 + 1) / ((k + 1) as f64).sqrt();
        }
    }
    let scale = if denominator > 0.0 {
        o / denominator
    } else {
        1.0
    };
    let shared = (shared as f32).clamp(MIN_OPACITY, 1.0 - f32::EPSILON);
    (shared, scale as f32)
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

/// Sets the starting opacity and size MCMC begins from.
pub fn prepare(s: &mut Splats) {
    let (opacity, shrink) = (logit(INITIAL_OPACITY), INITIAL_SCALE_FACTOR.ln());
    s.opacity_logits.fill(opacity);
    for l in &mut s.log_scales {
        *l = l.map(|v| v + shrink);
    }
}

/// The penalties' gradients with respect to each opacity and each scale:
/// the mean opacity over `count` splats, the mean scale over their 3·count
/// axes in units of `extent`.
pub fn penalty_weights(count: usize, extent: f32) -> (f32, f32) {
    let n = count.max(1) as f32;
    (
        OPACITY_REGULARISATION / n,
        SCALE_REGULARISATION / (3.0 * n * extent),
    )
}

/// The noise's scale for a step whose position learning rate is `rate`.
pub fn noise_scale(rate: f32, extent: f32) -> f32 {
    NOISE_LR * rate / (extent * extent)
}

/// The 32-bit seed the noise hash takes.
pub fn noise_seed(seed: u64) -> u32 {
    (seed ^ (seed >> 32)) as u32
}

/// Adds the gradients of the opacity and scale penalties (means over all
/// splats) to the gradients of opacity logits and log-scales.
pub fn add_regularisation(
    s: &Splats,
    extent: f32,
    opacity_grads: &mut [f32],
    log_scale_grads: &mut [[f32; 3]],
) {
    let (opacity_weight, scale_weight) = penalty_weights(s.len(), extent);
    opacity_grads
        .par_iter_mut()
        .zip(&s.opacity_logits)
        .for_each(|(g, &o)| {
            let p = sigmoid(o);
            *g += opacity_weight * p * (1.0 - p);
        });
    log_scale_grads
        .par_iter_mut()
        .zip(&s.log_scales)
        .for_each(|(g, l)| {
            for a in 0..3 {
                // As the GPU's Adam kernel: (∂L/∂scale + weight)·scale.
                g[a] += scale_weight * l[a].exp();
            }
        });
}

/// PCG's output hash (O'Neill), a good 32-bit mixer.
fn hash(x: u32) -> u32 {
    let state = x.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
    let word = ((state >> ((state >> 28) + 4)) ^ state).wrapping_mul(277_803_737);
    (word >> 22) ^ word
}

/// Four uniforms in (0, 1] from (seed, step, splat).
fn uniforms(seed: u32, step: u32, splat: u32) -> [f32; 4] {
    let base = hash(seed ^ hash(step ^ hash(splat)));
    [0u32, 1, 2, 3].map(|j| {
        let h = hash(base.wrapping_add(j.wrapping_mul(0x9e37_79b9)));
        ((h >> 8) as f32 + 1.0) / 16_777_216.0
    })
}

/// Moves near-transparent splats by noise shaped by their covariance:
/// Δμ = Σ·z · σ(100·(0.005 − o)) · NOISE_LR · rate / extent² (z standard
/// normal), `rate` being this step's position learning rate.
pub fn add_noise(s: &mut Splats, seed: u64, step: usize, rate: f32, extent: f32) {
    let scaler = noise_scale(rate, extent);
    let seed = noise_seed(seed);
    s.means
        .par_iter_mut()
        .zip(&s.log_scales)
        .zip(&s.quats)
        .zip(&s.opacity_logits)
        .enumerate()
        .for_each(|(i, (((mean, log_scale), quat), &logit))| {
            let gate = sigmoid(100.0 * (MIN_OPACITY - sigmoid(logit)));
            if gate * scaler == 0.0 {
                return;
            }
            let u = uniforms(seed, step as u32, i as u32);
            let radius = [(-2.0 * u[0].ln()).sqrt(), (-2.0 * u[2].ln()).sqrt()];
            let angle = [std::f32::consts::TAU * u[1], std::f32::consts::TAU * u[3]];
            let z = [
                radius[0] * angle[0].cos(),
                radius[0] * angle[0].sin(),
                radius[1] * angle[1].cos(),
            ];
            // Σz = R·S²·Rᵀ·z.
            let r = crate::raster::quat_to_rotmat(*quat);
            let variance = log_scale.map(|l| (2.0 * l).exp());
            let local =
                [0, 1, 2].map(|b| variance[b] * (0..3).map(|a| r[a][b] * z[a]).sum::<f32>());
            for a in 0..3 {
                mean[a] += gate * scaler * (0..3).map(|b| r[a][b] * local[b]).sum::<f32>();
            }
        });
}

/// Draws `count` indices from `candidates` with probability proportional
/// to opacity, with replacement.
fn draw_by_opacity(
    s: &Splats,
    candidates: &[usize],
    count: usize,
    rng: &mut ChaCha8Rng,
) -> Vec<usize> {
    let mut cumulative = Vec::with_capacity(candidates.len());
    let mut total = 0.0f64;
    for &i in candidates {
        total += sigmoid(s.opacity_logits[i]) as f64;
        cumulative.push(total);
    }
    if total <= 0.0 {
        return Vec::new();
    }
    (0..count)
        .map(|_| {
            let u = rng.random::<f64>() * total;
            let at = cumulative.partition_point(|&c| c <= u);
            candidates[at.min(candidates.len() - 1)]
        })
        .collect()
}

/// What a refinement did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Refinement {
    pub relocated: usize,
    pub added: usize,
}

/// Copies a splat's parameters (all but opacity and scale, set by the
/// caller) from `from` to `to` in the flat arrays.
fn copy_splat(s: &mut Splats, from: usize, to: usize) {
    let k = s.sh_coefficients();
    s.means[to] = s.means[from];
    s.quats[to] = s.quats[from];
    s.opacity_logits[to] = s.opacity_logits[from];
    s.log_scales[to] = s.log_scales[from];
    s.sh.copy_within(from * k..(from + 1) * k, to * k);
}

/// One refinement: relocates dead splats, then grows the count by 5% up to
/// `cap`. `reset_moments(indices)` is called with every splat whose
/// parameters changed (their optimiser state no longer fits), after the
/// arrays have grown to the new count.
pub fn refine(
    s: &mut Splats,
    cap: usize,
    rng: &mut ChaCha8Rng,
    reset_moments: &mut dyn FnMut(&[usize], usize),
) -> Refinement {
    let n = s.len();
    let (dead, alive): (Vec<usize>, Vec<usize>) =
        (0..n).partition(|&i| sigmoid(s.opacity_logits[i]) <= MIN_OPACITY);
    let mut changed = Vec::new();
    let mut relocated = 0;
    if !dead.is_empty() && !alive.is_empty() {
        let sources = draw_by_opacity(s, &alive, dead.len(), rng);
        relocated = sources.len();
        share(s, &sources, &dead[..sources.len()], &mut changed);
    }
    let target = (n + n / GROWTH_DIVISOR).min(cap);
    let mut added = 0;
    if target > n {
        let everyone: Vec<usize> = (0..n).collect();
        let sources = draw_by_opacity(s, &everyone, target - n, rng);
        added = sources.len();
        let k = s.sh_coefficients();
        let slots: Vec<usize> = (n..n + added).collect();
        s.means.resize(n + added, [0.0; 3]);
        s.log_scales.resize(n + added, [0.0; 3]);
        s.quats.resize(n + added, [1.0, 0.0, 0.0, 0.0]);
        s.opacity_logits.resize(n + added, 0.0);
        s.sh.resize((n + added) * k, [0.0; 3]);
        share(s, &sources, &slots, &mut changed);
    }
    changed.sort_unstable();
    changed.dedup();
    reset_moments(&changed, s.len());
    Refinement { relocated, added }
}

/// Puts a copy of `sources[j]` in `slots[j]`, each source and its copies
/// sharing its opacity and size.
fn share(s: &mut Splats, sources: &[usize], slots: &[usize], changed: &mut Vec<usize>) {
    let mut copies = std::collections::BTreeMap::<usize, usize>::new();
    for &i in sources {
        *copies.entry(i).or_insert(0) += 1;
    }
    for (&source, &extra) in &copies {
        let (opacity, factor) =
            shared_opacity_and_scale(sigmoid(s.opacity_logits[source]), extra + 1);
        s.opacity_logits[source] = logit(opacity);
        let grow = factor.max(1e-12).ln();
        s.log_scales[source] = s.log_scales[source].map(|l| l + grow);
        changed.push(source);
    }
    for (&source, &slot) in sources.iter().zip(slots) {
        copy_splat(s, source, slot);
        changed.push(slot);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_copy_is_the_original() {
        let (o, f) = shared_opacity_and_scale(0.7, 1);
        assert!((o - 0.7).abs() < 1e-6 && (f - 1.0).abs() < 1e-6);
    }

    /// The copies composited on one another have the original's opacity,
    /// and the paper's scale rule keeps the peak of their summed alpha:
    /// for N copies of opacity o' the centre's alpha is 1 − (1 − o')^N.
    #[test]
    fn shared_copies_keep_the_opacity() {
        for &(o, n) in &[(0.9f32, 2usize), (0.5, 3), (0.2, 5), (0.99, 10)] {
            let (shared, _) = shared_opacity_and_scale(o, n);
            let composite = 1.0 - (1.0 - shared as f64).powi(n as i32);
            assert!((composite - o as f64).abs() < 1e-5, "{o} x{n}: {composite}");
        }
    }

    /// Equation 9 against a direct computation: the 1D profile
    /// 1 − Π(1 − o'·g(x/s')) of N stacked copies, integrated, equals the
    /// original o·g(x/s)'s integral when Σ over the expanded product is
    /// weighted as the paper does (each product term of k+1 Gaussians is a
    /// Gaussian of width s'/sqrt(k+1)); so o·s = s'·Σ_terms.
    #[test]
    fn scale_rule_matches_the_expanded_product() {
        let (o, n) = (0.6f64, 4usize);
        let (shared, factor) = shared_opacity_and_scale(o as f32, n);
        let shared = shared as f64;
        // Integrate over x the sum, over copies i = 1..n, of the i-th copy's
        // contribution o'·g·Π_{j<i}(1 − o'·g), with g = exp(−x²/2s'²), s' = factor.
        let s = factor as f64;
        let mut integral = 0.0;
        let dx = 1e-3;
        let mut x = -10.0;
        while x < 10.0 {
            let g = (-x * x / (2.0 * s * s)).exp();
            let mut transmitted = 1.0;
            for _ in 0..n {
                integral += shared * g * transmitted * dx;
                transmitted *= 1.0 - shared * g;
            }
            x += dx;
        }
        // The original: o·g(x/1) integrated = o·sqrt(2π).
        let original = o * (2.0 * std::f64::consts::PI).sqrt();
        assert!(
            (integral - original).abs() < 1e-3 * original,
            "{integral} against {original}"
        );
    }

    #[test]
    fn the_noise_is_the_same_for_a_seed_and_spares_opaque_splats() {
        let mut s = Splats {
            sh_degree: 0,
            means: vec![[0.0; 3]; 3],
            log_scales: vec![[-2.0; 3]; 3],
            quats: vec![[1.0, 0.0, 0.0, 0.0]; 3],
            opacity_logits: vec![logit(0.001), logit(0.9), logit(0.001)],
            sh: vec![[0.0; 3]; 3],
            ..Default::default()
        };
        let mut t = s.clone();
        add_noise(&mut s, 7, 12, 1.6e-4, 1.0);
        add_noise(&mut t, 7, 12, 1.6e-4, 1.0);
        assert_eq!(s.means, t.means);
        assert_ne!(s.means[0], [0.0; 3]);
        assert_ne!(s.means[0], s.means[2], "each splat draws its own noise");
        assert!(s.means[1].iter().all(|v| v.abs() < 1e-9));
    }

    #[test]
    fn refinement_relocates_the_dead_and_grows_by_five_percent() {
        use rand::SeedableRng;
        let n = 100;
        let mut s = Splats {
            sh_degree: 0,
            means: (0..n).map(|i| [i as f32, 0.0, 0.0]).collect(),
            log_scales: vec![[-1.0; 3]; n],
            quats: vec![[1.0, 0.0, 0.0, 0.0]; n],
            opacity_logits: (0..n)
                .map(|i| logit(if i < 10 { 0.001 } else { 0.8 }))
                .collect(),
            sh: vec![[0.0; 3]; n],
            ..Default::default()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut reset = Vec::new();
        let done = refine(&mut s, 1000, &mut rng, &mut |changed, len| {
            reset = changed.to_vec();
            assert_eq!(len, 105);
        });
        assert_eq!(
            done,
            Refinement {
                relocated: 10,
                added: 5
            }
        );
        assert_eq!(s.len(), 105);
        s.validate().unwrap();
        // Every dead splat now sits on a live one, and no splat is dead.
        for i in 0..10 {
            assert!(s.means[i][0] >= 10.0, "splat {i} at {:?}", s.means[i]);
        }
        assert!(s.opacity_logits.iter().all(|&o| sigmoid(o) > MIN_OPACITY));
        assert!(reset.len() >= 15 && reset.contains(&0) && reset.contains(&104));
        // The cap holds.
        let done = refine(&mut s, 105, &mut rng, &mut |_, _| {});
        assert_eq!(done.added, 0);
    }
}
