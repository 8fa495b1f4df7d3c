//! Adam (Kingma and Ba 2015, algorithm 1) as both training backends run it:
//! gsplat's decay rates and ε, one learning rate per value of a splat's row
//! of parameters, steps in parallel chunks that give the same bits on any
//! number of threads. The GPU's Adam kernel (`gpu::training`) reads the same
//! constants.

use rayon::prelude::*;

/// Values per parallel task of an Adam step.
const ADAM_CHUNK: usize = 1 << 14;

/// Adam's decay rates of the first and second moments, and the ε of its
/// denominator (gsplat's), on both backends.
pub const ADAM_BETAS: (f32, f32) = (0.9, 0.999);
pub const ADAM_EPSILON: f32 = 1e-15;

/// Adam on equal-length runs of parameters, first and second moments and
/// gradients (`None`: zero gradients, whose moments still decay).
#[inline]
fn adam_update(
    params: &mut [f32],
    m: &mut [f32],
    v: &mut [f32],
    grads: Option<&[f32]>,
    lr: f32,
    c1: f32,
    c2: f32,
) {
    let ((b1, b2), eps) = (ADAM_BETAS, ADAM_EPSILON);
    let update = |param: &mut f32, m: &mut f32, v: &mut f32, grad: f32| {
        *m = b1 * *m + (1.0 - b1) * grad;
        *v = b2 * *v + (1.0 - b2) * grad * grad;
        *param -= lr * (*m / c1) / ((*v / c2).sqrt() + eps);
    };
    let moments = params.iter_mut().zip(m.iter_mut()).zip(v.iter_mut());
    match grads {
        Some(grads) => {
            for (((param, m), v), &grad) in moments.zip(grads) {
                update(param, m, v, grad);
            }
        }
        None => {
            for ((param, m), v) in moments {
                update(param, m, v, 0.0);
            }
        }
    }
}

/// Adam over a flat parameter array.
pub(crate) struct Adam {
    pub(crate) m: Vec<f32>,
    pub(crate) v: Vec<f32>,
}

impl Adam {
    pub(crate) fn new(n: usize) -> Adam {
        Adam {
            m: vec![0.0; n],
            v: vec![0.0; n],
        }
    }
    pub(crate) fn step(&mut self, params: &mut [f32], grads: &[f32], lr: f32, t: i32) {
        self.step_rows(params, grads, 1, &[lr], t);
    }
    /// A step over rows of `rates.len()` values (one splat's), value `j` of
    /// a row at rate `rates[j]`; `grads` holds the first `grads_per_row` of
    /// each row's gradients, the rest being zero (SH bands not yet in use).
    ///
    /// Plain loops over contiguous chunks, not a zip of per-element
    /// iterators with a rate closure: the compiler vectorises them. Before,
    /// an integer division per SH value picked its rate and the unused
    /// bands' zero gradients were copied out every step, and that was most
    /// of the optimiser's time (docs/results.md). Each value sees the same operations
    /// as before, so the result is the same to the bit.
    pub(crate) fn step_rows(
        &mut self,
        params: &mut [f32],
        grads: &[f32],
        grads_per_row: usize,
        rates: &[f32],
        t: i32,
    ) {
        let (b1, b2) = ADAM_BETAS;
        let c1 = 1.0 - b1.powi(t);
        let c2 = 1.0 - b2.powi(t);
        let stride = rates.len();
        debug_assert!(grads_per_row > 0 && grads_per_row <= stride);
        // A row's runs of one rate, with or without gradients: the same for
        // every row.
        let mut runs: Vec<(std::ops::Range<usize>, f32, bool)> = Vec::new();
        let mut j = 0;
        while j < stride {
            let with_grads = j < grads_per_row;
            let end = if with_grads { grads_per_row } else { stride };
            let mut e = j + 1;
            while e < end && rates[e] == rates[j] {
                e += 1;
            }
            runs.push((j..e, rates[j], with_grads));
            j = e;
        }
        // Rows of one run step as one flat run (means, scales, opacities).
        let uniform = runs.len() == 1 && grads_per_row == stride;
        let rows_per_chunk = ADAM_CHUNK.div_ceil(stride);
        let values = rows_per_chunk * stride;
        params
            .par_chunks_mut(values)
            .zip(self.m.par_chunks_mut(values))
            .zip(self.v.par_chunks_mut(values))
            .zip(grads.par_chunks(rows_per_chunk * grads_per_row))
            .for_each(|(((params, m), v), grads)| {
                if uniform {
                    adam_update(params, m, v, Some(grads), rates[0], c1, c2);
                    return;
                }
                let rows = params
                    .chunks_exact_mut(stride)
                    .zip(m.chunks_exact_mut(stride))
                    .zip(v.chunks_exact_mut(stride))
                    .zip(grads.chunks_exact(grads_per_row));
                for (((params, m), v), grads) in rows {
                    for (run, rate, with_grads) in &runs {
                        adam_update(
                            &mut params[run.clone()],
                            &mut m[run.clone()],
                            &mut v[run.clone()],
                            with_grads.then(|| &grads[run.clone()]),
                            *rate,
                            c1,
                            c2,
                        );
                    }
                }
            });
    }
    /// Keeps the moments of the kept entries (`stride` values per splat) and
    /// zeroes those of `added` new splats.
    pub(crate) fn reindex(&mut self, keep: &[usize], stride: usize, added: usize) {
        let pick = |a: &Vec<f32>| -> Vec<f32> {
            let mut out: Vec<f32> = keep
                .iter()
                .flat_map(|&i| a[i * stride..(i + 1) * stride].iter().copied())
                .collect();
            out.extend(std::iter::repeat_n(0.0, added * stride));
            out
        };
        self.m = pick(&self.m);
        self.v = pick(&self.v);
    }
    /// Grows to `len` elements of `stride` and zeroes the moments of `indices`.
    pub(crate) fn reset(&mut self, indices: &[usize], stride: usize, len: usize) {
        self.m.resize(len * stride, 0.0);
        self.v.resize(len * stride, 0.0);
        for &i in indices {
            self.m[i * stride..(i + 1) * stride].fill(0.0);
            self.v[i * stride..(i + 1) * stride].fill(0.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Adam as written in the paper (Kingma and Ba, algorithm 1), one value
    /// at a time, for the chunked steps to be checked against.
    fn reference_adam(p: &mut f32, m: &mut f32, v: &mut f32, grad: f32, lr: f32, t: i32) {
        let (b1, b2, eps) = (0.9f32, 0.999f32, 1e-15f32);
        *m = b1 * *m + (1.0 - b1) * grad;
        *v = b2 * *v + (1.0 - b2) * grad * grad;
        *p -= lr * (*m / (1.0 - b1.powi(t))) / ((*v / (1.0 - b2.powi(t))).sqrt() + eps);
    }

    #[test]
    fn chunked_adam_steps_each_value_as_the_one_at_a_time_update() {
        // Rows of SH (one rate for DC, another for the rest) with gradients
        // for the first bands only, over enough rows to span several chunks.
        let (stride, with_grads) = (12, 6);
        let rows = 2 * ADAM_CHUNK / stride + 7;
        let value = |i: usize, salt: f32| (i as f32 * 0.37 + salt).sin() * 0.01;
        let mut rates = vec![2e-4f32; stride];
        rates[..3].fill(3e-3);
        let mut params: Vec<f32> = (0..rows * stride).map(|i| value(i, 1.0)).collect();
        let mut expected = params.clone();
        let (mut m, mut v) = (vec![0.0f32; params.len()], vec![0.0f32; params.len()]);
        let mut adam = Adam::new(params.len());
        for t in 1..=3 {
            let grads: Vec<f32> = (0..rows * with_grads).map(|i| value(i, t as f32)).collect();
            adam.step_rows(&mut params, &grads, with_grads, &rates, t);
            for i in 0..expected.len() {
                let (row, j) = (i / stride, i % stride);
                let grad = if j < with_grads {
                    grads[row * with_grads + j]
                } else {
                    0.0
                };
                reference_adam(&mut expected[i], &mut m[i], &mut v[i], grad, rates[j], t);
            }
        }
        assert_eq!(params, expected);
        assert_eq!((adam.m, adam.v), (m, v));
        // One rate for every value: the flat path.
        let mut flat = vec![0.5f32; 3 * rows];
        let mut expected = flat.clone();
        let (mut m, mut v) = (vec![0.0f32; flat.len()], vec![0.0f32; flat.len()]);
        let mut adam = Adam::new(flat.len());
        let grads: Vec<f32> = (0..flat.len()).map(|i| value(i, 5.0)).collect();
        adam.step(&mut flat, &grads, 1e-3, 1);
        for i in 0..expected.len() {
            reference_adam(&mut expected[i], &mut m[i], &mut v[i], grads[i], 1e-3, 1);
        }
        assert_eq!(flat, expected);
    }
}
