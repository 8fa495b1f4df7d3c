//! Image metrics and the image losses of training: PSNR, SSIM (Wang et al.
//! 2004, as 3DGS computes it: 11x11 Gaussian window with σ = 1.5, zero
//! padding, C1 = 0.01², C2 = 0.03², per channel), both over the whole image
//! or over a pixel mask (the paper evaluates on object ∩ accumulation,
//! gripper excluded), and the gradient of a weighted mean SSIM with respect
//! to the rendered image, for the D-SSIM term of the loss.
//!
//! Training computes that SSIM and its gradient at every step: 24 separable
//! 11-tap blurs of the image. They were a third of a CPU training step at
//! 320x240 and more at full size, so they run in bands of rows: a
//! band blurs horizontally only the rows its vertical taps reach (a ring of
//! 11 rows a plane), so the blurred moments never exist as whole planes and
//! a band's rows stay in cache. The row loops are also compiled for AVX2,
//! picked at run time (the `multiversion` crate), as a build for baseline
//! x86-64 cannot assume it. Every sum keeps the order of a plain
//! pixel-by-pixel loop, and Rust never fuses a multiply and an add, so each
//! path gives the plain loops' bits (`banded_ssim_sums_as_plain_pixel_loops_do_at_every_size`),
//! and a trained model is the same to the byte. Bands and AVX2 more than
//! halve the SSIM's time (docs/results.md).
//!
//! The passes are generic over their float type ([`SsimFloat`]). Reported
//! metrics use f64. The training loss uses f32, as gsplat's does: an AVX2
//! vector holds eight lanes instead of four (docs/results.md). The f32 figures
//! stay within 1e-6 of the f64 value and 5e-5 of the largest gradient
//! (`f32_ssim_and_gradient_agree_with_f64`).

use rayon::prelude::*;

use crate::Real;

/// The float type SSIM is computed in: f64 for the reported metric, f32 for
/// the training loss, whose blurs then fill twice the lanes of a vector
/// (gsplat's loss is f32 as well). The weighted total is summed in f64
/// either way.
pub trait SsimFloat: Real {
    /// A pixel value (images are f32) in this type.
    fn of_f32(v: f32) -> Self;
    /// This value in f64, for totals and the f32 gradient's rounding.
    fn wide(self) -> f64;
}

impl SsimFloat for f32 {
    #[inline]
    fn of_f32(v: f32) -> f32 {
        v
    }
    #[inline]
    fn wide(self) -> f64 {
        self as f64
    }
}

impl SsimFloat for f64 {
    #[inline]
    fn of_f32(v: f32) -> f64 {
        v as f64
    }
    #[inline]
    fn wide(self) -> f64 {
        self
    }
}

/// An RGB float image, row-major, values nominally in [0, 1].
pub struct ImageView<'a> {
    pub width: usize,
    pub height: usize,
    pub pixels: &'a [[f32; 3]],
}

const C1: f64 = 0.01 * 0.01;
const C2: f64 = 0.03 * 0.03;
const RADIUS: usize = 5;

/// The SSIM window's taps (normalised in f64, then rounded to `S`); the GPU
/// loss blurs with the same f32 values.
pub(crate) fn window<S: SsimFloat>() -> [S; 2 * RADIUS + 1] {
    let mut w = [0.0f64; 2 * RADIUS + 1];
    for (i, v) in w.iter_mut().enumerate() {
        let d = i as f64 - RADIUS as f64;
        *v = (-d * d / (2.0 * 1.5 * 1.5)).exp();
    }
    let s: f64 = w.iter().sum();
    w.map(|v| S::c(v / s))
}

const TAPS: usize = 2 * RADIUS + 1;

/// One row blurred horizontally with zero padding: each output adds its
/// in-bounds taps in window order, a tap at a time across the row.
#[multiversion::multiversion(targets("x86_64+avx2"))]
fn blur_row<S: SsimFloat>(window: &[S; TAPS], row: &[S], out: &mut [S]) {
    let width = row.len();
    out.fill(S::zero());
    for (k, &wk) in window.iter().enumerate() {
        let first = RADIUS.saturating_sub(k);
        let end = (width + RADIUS).saturating_sub(k).min(width);
        if first >= end {
            continue;
        }
        let source = first + k - RADIUS;
        for (o, v) in out[first..end]
            .iter_mut()
            .zip(&row[source..source + end - first])
        {
            *o = *o + wk * *v;
        }
    }
}

/// Rows `first..end` of `P` planes blurred by the separable SSIM window:
/// `fill(y, planes)` writes input row `y` of every plane, `each(y, blurred)`
/// takes output row `y`. The horizontal pass keeps only the rows the
/// vertical taps reach, so a band's working set stays in cache; a band
/// blurs the RADIUS rows beyond each of its ends again.
fn blur_band<S: SsimFloat, const P: usize>(
    width: usize,
    height: usize,
    (first, end): (usize, usize),
    mut fill: impl FnMut(usize, &mut [Vec<S>; P]),
    mut each: impl FnMut(usize, &[Vec<S>; P]),
) {
    let window = window::<S>();
    let mut input: [Vec<S>; P] = std::array::from_fn(|_| vec![S::zero(); width]);
    let mut output: [Vec<S>; P] = std::array::from_fn(|_| vec![S::zero(); width]);
    // Plane p's horizontally blurred row y sits in slot y mod TAPS.
    let mut rows = vec![S::zero(); P * TAPS * width];
    let slot = |p: usize, y: usize| (p * TAPS + y % TAPS) * width;
    let mut next = first.saturating_sub(RADIUS);
    for y in first..end {
        while next < (y + RADIUS + 1).min(height) {
            fill(next, &mut input);
            for (p, row) in input.iter().enumerate() {
                let at = slot(p, next);
                blur_row(&window, row, &mut rows[at..at + width]);
            }
            next += 1;
        }
        // The rows this output row's taps reach, in window order.
        let taps: Vec<(S, usize)> = window
            .iter()
            .enumerate()
            .filter_map(|(k, &wk)| {
                let source = (y + k).checked_sub(RADIUS).filter(|&s| s < height)?;
                Some((wk, source))
            })
            .collect();
        for (p, out) in output.iter_mut().enumerate() {
            sum_rows(&taps, &rows[slot(p, 0)..slot(p, 0) + TAPS * width], out);
        }
        each(y, &output);
    }
}

/// `out` = Σ weight · row over `taps` (weight, row index mod TAPS into
/// `rows`), in the taps' order.
#[multiversion::multiversion(targets("x86_64+avx2"))]
fn sum_rows<S: SsimFloat>(taps: &[(S, usize)], rows: &[S], out: &mut [S]) {
    let width = out.len();
    out.fill(S::zero());
    for &(wk, source) in taps {
        let at = source % TAPS * width;
        for (o, t) in out.iter_mut().zip(&rows[at..at + width]) {
            *o = *o + wk * *t;
        }
    }
}

/// Rows per band of the SSIM passes: enough bands for every thread, each
/// tall enough that blurring its ends' neighbours again stays a small share.
fn band_rows(height: usize) -> usize {
    height
        .div_ceil(4 * rayon::current_num_threads().max(1))
        .max(32)
}

/// Rows `first..end` of channel `c`'s blurred moments μx, μy, E[x²],
/// E[y²], E[xy], handed to `each` a row at a time.
fn moments_band<S: SsimFloat>(
    x: &ImageView,
    y: &ImageView,
    c: usize,
    rows: (usize, usize),
    each: impl FnMut(usize, &[Vec<S>; 5]),
) {
    let width = x.width;
    let fill = |row: usize, planes: &mut [Vec<S>; 5]| {
        let pixels = row * width..(row + 1) * width;
        moment_inputs(&x.pixels[pixels.clone()], &y.pixels[pixels], c, planes);
    };
    blur_band(width, x.height, rows, fill, each);
}

/// One row of channel `c`'s inputs to the moments: x, y, x², y², xy.
#[multiversion::multiversion(targets("x86_64+avx2"))]
fn moment_inputs<S: SsimFloat>(x: &[[f32; 3]], y: &[[f32; 3]], c: usize, planes: &mut [Vec<S>; 5]) {
    let [xs, ys, xx, yy, xy] = planes;
    for (i, (p, q)) in x.iter().zip(y).enumerate() {
        let (a, b) = (S::of_f32(p[c]), S::of_f32(q[c]));
        xs[i] = a;
        ys[i] = b;
        xx[i] = a * a;
        yy[i] = b * b;
        xy[i] = a * b;
    }
}

/// PSNR in dB over the pixels where `mask` is set (all pixels without a
/// mask), for images in [0, 1]; `None` when no pixel counts.
pub fn psnr(a: &ImageView, b: &ImageView, mask: Option<&[bool]>) -> Option<f64> {
    let mut sum = 0.0;
    let mut n = 0usize;
    for i in 0..a.pixels.len() {
        if mask.is_some_and(|m| !m[i]) {
            continue;
        }
        for c in 0..3 {
            let d = a.pixels[i][c] as f64 - b.pixels[i][c] as f64;
            sum += d * d;
        }
        n += 3;
    }
    (n > 0).then(|| {
        let mse = sum / n as f64;
        if mse == 0.0 {
            f64::INFINITY
        } else {
            -10.0 * mse.log10()
        }
    })
}

/// SSIM at a pixel from its blurred moments (μx, μy, E[x²], E[y²], E[xy]),
/// with the factors of its fraction: (SSIM, n1, n2, d1, d2), SSIM = n1·n2 / (d1·d2).
#[inline]
fn ssim_at<S: SsimFloat>([mx, my, xx, yy, xy]: [S; 5]) -> (S, S, S, S, S) {
    let two = S::c(2.0);
    let (c1, c2) = (S::c(C1), S::c(C2));
    let (sx, sy, sxy) = (xx - mx * mx, yy - my * my, xy - mx * my);
    let n1 = two * mx * my + c1;
    let n2 = two * sxy + c2;
    let d1 = mx * mx + my * my + c1;
    let d2 = sx + sy + c2;
    (n1 * n2 / (d1 * d2), n1, n2, d1, d2)
}

/// One row's terms of the SSIM gradient from its blurred moments `m` and
/// its weights: w·(A − 2B·μx − C·μy), w·B, w·C and w·SSIM, where
/// A = ∂SSIM/∂μx, B = ∂SSIM/∂σx², C = ∂SSIM/∂σxy.
#[multiversion::multiversion(targets("x86_64+avx2"))]
fn gradient_terms<S: SsimFloat>(m: &[Vec<S>; 5], weights: &[S], [a, b, c, sw]: [&mut [S]; 4]) {
    let two = S::c(2.0);
    for (i, &w) in weights.iter().enumerate() {
        let (mx, my) = (m[0][i], m[1][i]);
        let (s, n1, n2, d1, d2) = ssim_at(std::array::from_fn(|p| m[p][i]));
        let d_mx = two * my * n2 / (d1 * d2) - s * two * mx / d1;
        let d_sx = -s / d2;
        let d_sxy = two * n1 / (d1 * d2);
        a[i] = w * (d_mx - two * d_sx * mx - d_sxy * my);
        b[i] = w * d_sx;
        c[i] = w * d_sxy;
        sw[i] = s * w;
    }
}

/// Row bands of `planes` (each `width` pixels wide, `rows` rows a band),
/// each with its plane index and first row, for the threads to share.
fn plane_bands<T>(
    planes: &mut [Vec<T>],
    width: usize,
    rows: usize,
) -> Vec<(usize, usize, &mut [T])> {
    planes
        .iter_mut()
        .enumerate()
        .flat_map(|(c, plane)| {
            plane
                .chunks_mut(rows * width)
                .enumerate()
                .map(move |(b, chunk)| (c, b * rows, chunk))
        })
        .collect()
}

/// Each channel's SSIM map, bands of rows and channels on all threads (the
/// blurred moments never exist beyond the rows a band's taps reach).
fn ssim_maps(x: &ImageView, y: &ImageView) -> Vec<Vec<f64>> {
    let (width, height) = (x.width, x.height);
    let mut maps = vec![vec![0.0; width * height]; 3];
    if width * height == 0 {
        return maps;
    }
    let rows = band_rows(height);
    plane_bands(&mut maps, width, rows)
        .into_par_iter()
        .for_each(|(c, first, map)| {
            moments_band::<f64>(x, y, c, (first, first + map.len() / width), |row, m| {
                let out = &mut map[(row - first) * width..][..width];
                for (i, o) in out.iter_mut().enumerate() {
                    *o = ssim_at(std::array::from_fn(|p| m[p][i])).0;
                }
            });
        });
    maps
}

/// Mean SSIM over the pixels where `mask` is set (all without a mask).
pub fn ssim(x: &ImageView, y: &ImageView, mask: Option<&[bool]>) -> Option<f64> {
    mean_ssim(&ssim_maps(x, y), mask)
}

/// Mean SSIM over the whole image and over the pixels where `mask` is set,
/// the same as two [`ssim`] calls, from one computation of the SSIM maps
/// (most of the time an evaluation spends on a view besides rendering it).
pub fn ssim_whole_and_masked(
    x: &ImageView,
    y: &ImageView,
    mask: &[bool],
) -> (Option<f64>, Option<f64>) {
    let maps = ssim_maps(x, y);
    (mean_ssim(&maps, None), mean_ssim(&maps, Some(mask)))
}

fn mean_ssim(maps: &[Vec<f64>], mask: Option<&[bool]>) -> Option<f64> {
    let mut sum = 0.0;
    let mut n = 0usize;
    for m in maps {
        for (i, v) in m.iter().enumerate() {
            if mask.is_some_and(|mk| !mk[i]) {
                continue;
            }
            sum += v;
            n += 1;
        }
    }
    (n > 0).then(|| sum / n as f64)
}

/// Σ_p weight_p · SSIM_p(x, y) summed over channels, and its gradient with
/// respect to `x` (the rendered image). Training minimises 1 − SSIM with
/// weights that are zero on gripper pixels and sum to one over the rest.
///
/// Two sweeps over bands of rows: the first blurs the moments and leaves
/// each pixel's weighted SSIM and the three terms of its gradient,
/// dL/dx_q = G⋆(w·(A − 2B·μx − C·μy)) + 2x_q·G⋆(w·B) + y_q·G⋆(w·C); the
/// second blurs the terms into the gradient. Every value is summed in the
/// order a pixel-by-pixel loop sums it, and the SSIM total in pixel order
/// (in f64), so the result does not depend on the threads. `S` is the
/// precision of the blurs and terms ([`SsimFloat`]).
pub fn weighted_ssim_and_gradient<S: SsimFloat>(
    x: &ImageView,
    y: &ImageView,
    weights: &[S],
) -> (f64, Vec<[f32; 3]>) {
    let (width, height) = (x.width, x.height);
    let n = width * height;
    if n == 0 {
        return (0.0, Vec::new());
    }
    let rows = band_rows(height);
    // Per channel: the terms w·(A − 2B·μx − C·μy), w·B, w·C, and w·SSIM.
    let mut terms: Vec<[Vec<S>; 4]> = (0..3)
        .map(|_| std::array::from_fn(|_| vec![S::zero(); n]))
        .collect();
    let chunk = rows * width;
    let tasks: Vec<_> = terms
        .iter_mut()
        .enumerate()
        .flat_map(|(c, [a, b, cc, sw])| {
            a.chunks_mut(chunk)
                .zip(b.chunks_mut(chunk))
                .zip(cc.chunks_mut(chunk))
                .zip(sw.chunks_mut(chunk))
                .enumerate()
                .map(move |(band, (((a, b), cc), sw))| (c, band * rows, a, b, cc, sw))
        })
        .collect();
    tasks.into_par_iter().for_each(|(c, first, a, b, cc, sw)| {
        moments_band(x, y, c, (first, first + a.len() / width), |row, m| {
            let at = (row - first) * width;
            gradient_terms(
                m,
                &weights[row * width..(row + 1) * width],
                [
                    &mut a[at..at + width],
                    &mut b[at..at + width],
                    &mut cc[at..at + width],
                    &mut sw[at..at + width],
                ],
            );
        });
    });
    let value = terms.iter().fold(0.0, |sum, t| {
        sum + t[3].iter().map(|v| v.wide()).sum::<f64>()
    });
    let two = S::c(2.0);
    let mut grad = vec![[0.0f32; 3]; n];
    grad.par_chunks_mut(chunk)
        .enumerate()
        .for_each(|(band, out)| {
            let first = band * rows;
            let end = first + out.len() / width;
            for (c, t) in terms.iter().enumerate() {
                let planes = &t[..3];
                let fill = |row: usize, input: &mut [Vec<S>; 3]| {
                    for (to, plane) in input.iter_mut().zip(planes) {
                        to.copy_from_slice(&plane[row * width..(row + 1) * width]);
                    }
                };
                blur_band(width, height, (first, end), fill, |row, g| {
                    let at = row * width;
                    for i in 0..width {
                        let xq = S::of_f32(x.pixels[at + i][c]);
                        let yq = S::of_f32(y.pixels[at + i][c]);
                        let d = g[0][i] + two * xq * g[1][i] + yq * g[2][i];
                        out[at - first * width + i][c] = d.wide() as f32;
                    }
                });
            }
        });
    (value, grad)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pattern(w: usize, h: usize, phase: f32) -> Vec<[f32; 3]> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                [
                    0.5 + 0.4 * (x * 0.7 + phase).sin(),
                    0.5 + 0.3 * (y * 0.5 + x * 0.2).cos(),
                    0.3 + 0.2 * ((x + y) * 0.3 + phase).sin(),
                ]
            })
            .collect()
    }

    #[test]
    fn identical_images_score_perfectly_and_noise_lowers_both() {
        let (w, h) = (24, 20);
        let a = pattern(w, h, 0.0);
        let b = pattern(w, h, 0.4);
        let va = ImageView {
            width: w,
            height: h,
            pixels: &a,
        };
        let vb = ImageView {
            width: w,
            height: h,
            pixels: &b,
        };
        assert_eq!(psnr(&va, &va, None), Some(f64::INFINITY));
        assert!((ssim(&va, &va, None).unwrap() - 1.0).abs() < 1e-9);
        let p = psnr(&va, &vb, None).unwrap();
        assert!(p > 5.0 && p < 40.0);
        assert!(ssim(&va, &vb, None).unwrap() < 0.99);
        // Both means from one set of maps are the two calls' to the bit.
        let mask: Vec<bool> = (0..w * h).map(|i| i % 3 != 0).collect();
        let both = ssim_whole_and_masked(&va, &vb, &mask);
        assert_eq!(both, (ssim(&va, &vb, None), ssim(&va, &vb, Some(&mask))));
        assert_ne!(both.0, both.1);
        // A uniform error of 0.1 is 20 dB.
        let c: Vec<[f32; 3]> = a.iter().map(|p| p.map(|v| v + 0.1)).collect();
        let vc = ImageView {
            width: w,
            height: h,
            pixels: &c,
        };
        assert!((psnr(&va, &vc, None).unwrap() - 20.0).abs() < 1e-4);
        let mask: Vec<bool> = (0..w * h).map(|i| i % 3 == 0).collect();
        assert!(psnr(&va, &vb, Some(&mask)).is_some());
        assert!(psnr(&va, &vb, Some(&vec![false; w * h])).is_none());
    }

    /// The SSIM and its gradient as plain loops over pixels, one thread:
    /// each sum in the order the banded passes must keep.
    mod reference {
        use super::super::{C1, C2, RADIUS, SsimFloat, window};

        /// One pass of the window along rows (`across`) or columns.
        fn pass<S: SsimFloat>(width: usize, height: usize, src: &[S], across: bool) -> Vec<S> {
            let w = window::<S>();
            let mut out = vec![S::zero(); src.len()];
            for y in 0..height {
                for x in 0..width {
                    let (n, at) = if across { (width, x) } else { (height, y) };
                    let mut s = S::zero();
                    for (k, &wk) in w.iter().enumerate() {
                        let Some(i) = (at + k).checked_sub(RADIUS).filter(|&i| i < n) else {
                            continue;
                        };
                        s = s + wk * src[if across { y * width + i } else { i * width + x }];
                    }
                    out[y * width + x] = s;
                }
            }
            out
        }

        fn blur<S: SsimFloat>(width: usize, height: usize, src: &[S]) -> Vec<S> {
            pass(width, height, &pass(width, height, src, true), false)
        }

        /// Per channel: the SSIM map and the three gradient terms before
        /// their blur, given the weights.
        fn parts<S: SsimFloat>(
            w: usize,
            h: usize,
            x: &[[f32; 3]],
            y: &[[f32; 3]],
            weights: &[S],
            c: usize,
        ) -> [Vec<S>; 4] {
            let xs: Vec<S> = x.iter().map(|p| S::of_f32(p[c])).collect();
            let ys: Vec<S> = y.iter().map(|p| S::of_f32(p[c])).collect();
            let times =
                |a: &[S], b: &[S]| -> Vec<S> { a.iter().zip(b).map(|(&a, &b)| a * b).collect() };
            let (two, c1, c2) = (S::c(2.0), S::c(C1), S::c(C2));
            let mx = blur(w, h, &xs);
            let my = blur(w, h, &ys);
            let xx = blur(w, h, &times(&xs, &xs));
            let yy = blur(w, h, &times(&ys, &ys));
            let xy = blur(w, h, &times(&xs, &ys));
            let mut out: [Vec<S>; 4] = std::array::from_fn(|_| vec![S::zero(); w * h]);
            for i in 0..w * h {
                let (sx, sy, sxy) = (
                    xx[i] - mx[i] * mx[i],
                    yy[i] - my[i] * my[i],
                    xy[i] - mx[i] * my[i],
                );
                let n1 = two * mx[i] * my[i] + c1;
                let n2 = two * sxy + c2;
                let d1 = mx[i] * mx[i] + my[i] * my[i] + c1;
                let d2 = sx + sy + c2;
                let s = n1 * n2 / (d1 * d2);
                let d_mx = two * my[i] * n2 / (d1 * d2) - s * two * mx[i] / d1;
                let d_sx = -s / d2;
                let d_sxy = two * n1 / (d1 * d2);
                out[0][i] = s;
                out[1][i] = weights[i] * (d_mx - two * d_sx * mx[i] - d_sxy * my[i]);
                out[2][i] = weights[i] * d_sx;
                out[3][i] = weights[i] * d_sxy;
            }
            out
        }

        pub fn maps(w: usize, h: usize, x: &[[f32; 3]], y: &[[f32; 3]]) -> Vec<Vec<f64>> {
            let ones = vec![1.0; w * h];
            (0..3)
                .map(|c| {
                    let [s, ..] = parts(w, h, x, y, &ones, c);
                    s
                })
                .collect()
        }

        pub fn weighted_and_gradient<S: SsimFloat>(
            w: usize,
            h: usize,
            x: &[[f32; 3]],
            y: &[[f32; 3]],
            weights: &[S],
        ) -> (f64, Vec<[f32; 3]>) {
            let mut value = 0.0;
            let mut grad = vec![[0.0f32; 3]; w * h];
            for c in 0..3 {
                let [s, a, b, cc] = parts(w, h, x, y, weights, c);
                value += s
                    .iter()
                    .zip(weights)
                    .map(|(&s, &w)| (s * w).wide())
                    .sum::<f64>();
                let (ga, gb, gc) = (blur(w, h, &a), blur(w, h, &b), blur(w, h, &cc));
                for q in 0..w * h {
                    let (xq, yq) = (S::of_f32(x[q][c]), S::of_f32(y[q][c]));
                    grad[q][c] = (ga[q] + S::c(2.0) * xq * gb[q] + yq * gc[q]).wide() as f32;
                }
            }
            (value, grad)
        }
    }

    #[test]
    fn banded_ssim_sums_as_plain_pixel_loops_do_at_every_size() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        // Narrower and shorter than the window, one band, and several
        // bands with a short last one.
        for (w, h) in [
            (1, 1),
            (3, 17),
            (11, 11),
            (12, 5),
            (37, 29),
            (23, 100),
            (64, 70),
        ] {
            let mut image = || -> Vec<[f32; 3]> {
                (0..w * h)
                    .map(|_| std::array::from_fn(|_| rng.random::<f32>()))
                    .collect()
            };
            let (x, y) = (image(), image());
            let weights: Vec<f64> = (0..w * h)
                .map(|i| {
                    if i % 5 == 2 {
                        0.0
                    } else {
                        rng.random::<f64>() / (w * h) as f64
                    }
                })
                .collect();
            let view = |pixels| ImageView {
                width: w,
                height: h,
                pixels,
            };
            let bits = |g: &[[f32; 3]]| -> Vec<[u32; 3]> {
                g.iter().map(|p| p.map(f32::to_bits)).collect()
            };
            // In both precisions: f64 for the metric, f32 for training.
            let weights32: Vec<f32> = weights.iter().map(|&v| v as f32).collect();
            let (value, grad) = weighted_ssim_and_gradient(&view(&x), &view(&y), &weights);
            let (want_value, want_grad) = reference::weighted_and_gradient(w, h, &x, &y, &weights);
            assert_eq!(value.to_bits(), want_value.to_bits(), "{w}x{h}: value");
            assert_eq!(bits(&grad), bits(&want_grad), "{w}x{h}: gradient");
            let (value32, grad32) = weighted_ssim_and_gradient(&view(&x), &view(&y), &weights32);
            let (want_value32, want_grad32) =
                reference::weighted_and_gradient(w, h, &x, &y, &weights32);
            assert_eq!(
                value32.to_bits(),
                want_value32.to_bits(),
                "{w}x{h}: f32 value"
            );
            assert_eq!(bits(&grad32), bits(&want_grad32), "{w}x{h}: f32 gradient");
            let maps = ssim_maps(&view(&x), &view(&y));
            let want_maps = reference::maps(w, h, &x, &y);
            for (m, r) in maps.iter().zip(&want_maps) {
                let same = m.iter().zip(r).all(|(a, b)| a.to_bits() == b.to_bits());
                assert!(same && m.len() == r.len(), "{w}x{h}: SSIM maps");
            }
        }
    }

    #[test]
    fn ssim_gradient_matches_central_differences() {
        let (w, h) = (14, 12);
        let x = pattern(w, h, 0.0);
        let y = pattern(w, h, 0.9);
        let weights: Vec<f64> = (0..w * h)
            .map(|i| {
                if i % 7 == 3 {
                    0.0
                } else {
                    1.0 / (w * h) as f64
                }
            })
            .collect();
        let (_, grad) = weighted_ssim_and_gradient(
            &ImageView {
                width: w,
                height: h,
                pixels: &x,
            },
            &ImageView {
                width: w,
                height: h,
                pixels: &y,
            },
            &weights,
        );
        let value = |img: &[[f32; 3]]| {
            weighted_ssim_and_gradient(
                &ImageView {
                    width: w,
                    height: h,
                    pixels: img,
                },
                &ImageView {
                    width: w,
                    height: h,
                    pixels: &y,
                },
                &weights,
            )
            .0
        };
        for q in [0usize, 17, 50, w * h - 1] {
            for c in 0..3 {
                let e = 1e-3f32;
                let mut plus = x.clone();
                plus[q][c] += e;
                let mut minus = x.clone();
                minus[q][c] -= e;
                let fd = (value(&plus) - value(&minus)) / (2.0 * e as f64);
                assert!(
                    (fd - grad[q][c] as f64).abs() < 1e-4 * (1.0 + fd.abs()) + 1e-6,
                    "pixel {q} channel {c}: {fd} vs {}",
                    grad[q][c]
                );
            }
        }
    }

    /// Training's f32 SSIM agrees with the f64 one (checked above against
    /// central differences) to f32's rounding, on a photo-sized image with
    /// zero-weight (gripper) pixels.
    #[test]
    fn f32_ssim_and_gradient_agree_with_f64() {
        let (w, h) = (96, 80);
        let x = pattern(w, h, 0.0);
        let y = pattern(w, h, 0.7);
        let n = (w * h) as f64;
        let weights: Vec<f64> = (0..w * h)
            .map(|i| if i % 11 < 3 { 0.0 } else { 1.0 / n })
            .collect();
        let weights32: Vec<f32> = weights.iter().map(|&v| v as f32).collect();
        let view = |pixels| ImageView {
            width: w,
            height: h,
            pixels,
        };
        let (v64, g64) = weighted_ssim_and_gradient(&view(&x), &view(&y), &weights);
        let (v32, g32) = weighted_ssim_and_gradient(&view(&x), &view(&y), &weights32);
        assert!((v64 - v32).abs() < 1e-6 * v64.abs(), "{v64} vs {v32}");
        let largest = g64.iter().flatten().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(largest > 0.0);
        for (a, b) in g64.iter().flatten().zip(g32.iter().flatten()) {
            assert!(
                (a - b).abs() <= 5e-5 * largest,
                "{a} vs {b} (largest {largest})"
            );
        }
    }
}
