//! Image metrics and the image losses of training: PSNR, SSIM (Wang et al.
//! 2004, as 3DGS computes it: 11x11 Gaussian window with σ = 1.5, zero
//! padding, C1 = 0.01², C2 = 0.03², per channel), both over the whole image
//! or over a pixel mask (the paper evaluates on object ∩ accumulation,
//! gripper excluded), and the gradient of a weighted mean SSIM with respect
//! to the rendered image, for the D-SSIM term of the loss.

use rayon::prelude::*;

/// An RGB float image, row-major, values nominally in [0, 1].
pub struct ImageView<'a> {
    pub width: usize,
    pub height: usize,
    pub pixels: &'a [[f32; 3]],
}

const C1: f64 = 0.01 * 0.01;
const C2: f64 = 0.03 * 0.03;
const RADIUS: usize = 5;

fn window() -> [f64; 2 * RADIUS + 1] {
    let mut w = [0.0; 2 * RADIUS + 1];
    for (i, v) in w.iter_mut().enumerate() {
        let d = i as f64 - RADIUS as f64;
        *v = (-d * d / (2.0 * 1.5 * 1.5)).exp();
    }
    let s: f64 = w.iter().sum();
    w.map(|v| v / s)
}

/// Separable Gaussian filter with zero padding (same size), rows in
/// parallel. Each output sums its taps in window order, the vertical pass
/// a row of taps at a time.
fn blur(width: usize, height: usize, src: &[f64]) -> Vec<f64> {
    let w = window();
    let mut tmp = vec![0.0; src.len()];
    tmp.par_chunks_mut(width.max(1))
        .zip(src.par_chunks(width.max(1)))
        .for_each(|(out, row)| {
            for (x, o) in out.iter_mut().enumerate() {
                let mut s = 0.0;
                if x >= RADIUS && x + RADIUS < width {
                    // Inside: every tap, no bounds to test.
                    for (wk, v) in w.iter().zip(&row[x - RADIUS..=x + RADIUS]) {
                        s += wk * v;
                    }
                } else {
                    for (k, wk) in w.iter().enumerate() {
                        let xx = x as i64 + k as i64 - RADIUS as i64;
                        if xx >= 0 && (xx as usize) < width {
                            s += wk * row[xx as usize];
                        }
                    }
                }
                *o = s;
            }
        });
    let mut out = vec![0.0; src.len()];
    out.par_chunks_mut(width.max(1))
        .enumerate()
        .for_each(|(y, out)| {
            for (k, wk) in w.iter().enumerate() {
                let yy = y as i64 + k as i64 - RADIUS as i64;
                if yy >= 0 && (yy as usize) < height {
                    let row = &tmp[yy as usize * width..(yy as usize + 1) * width];
                    for (o, t) in out.iter_mut().zip(row) {
                        *o += wk * t;
                    }
                }
            }
        });
    out
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

struct SsimParts {
    /// Per channel: the SSIM map and its partial derivatives with respect
    /// to μx, σx² and σxy at each pixel, plus μx and μy.
    maps: Vec<[Vec<f64>; 6]>,
}

/// Channel `c`'s blurred moments of `x` and `y`: μx, μy, E[x²], E[y²], E[xy].
fn moments(x: &ImageView, y: &ImageView, c: usize) -> [Vec<f64>; 5] {
    let (w, h) = (x.width, x.height);
    let xs: Vec<f64> = x.pixels.par_iter().map(|p| p[c] as f64).collect();
    let ys: Vec<f64> = y.pixels.par_iter().map(|p| p[c] as f64).collect();
    let product =
        |a: &[f64], b: &[f64]| -> Vec<f64> { a.par_iter().zip(b).map(|(a, b)| a * b).collect() };
    [
        blur(w, h, &xs),
        blur(w, h, &ys),
        blur(w, h, &product(&xs, &xs)),
        blur(w, h, &product(&ys, &ys)),
        blur(w, h, &product(&xs, &ys)),
    ]
}

/// SSIM at pixel `i` from the moments, with the factors of its fraction:
/// (SSIM, n1, n2, d1, d2), SSIM = n1·n2 / (d1·d2).
fn ssim_at(m: &[Vec<f64>; 5], i: usize) -> (f64, f64, f64, f64, f64) {
    let [mx, my, xx, yy, xy] = m;
    let (sx, sy, sxy) = (
        xx[i] - mx[i] * mx[i],
        yy[i] - my[i] * my[i],
        xy[i] - mx[i] * my[i],
    );
    let n1 = 2.0 * mx[i] * my[i] + C1;
    let n2 = 2.0 * sxy + C2;
    let d1 = mx[i] * mx[i] + my[i] * my[i] + C1;
    let d2 = sx + sy + C2;
    (n1 * n2 / (d1 * d2), n1, n2, d1, d2)
}

/// The channels run in parallel, and so does each one's per-pixel work:
/// every value is computed as one serial pass would, so the maps are the
/// same to the bit (in training, these loops on one thread were a fifth of
/// a 3000-step DTU run's serial time, while the other threads waited).
fn ssim_parts(x: &ImageView, y: &ImageView) -> SsimParts {
    let maps = (0..3)
        .into_par_iter()
        .map(|c| {
            let m = moments(x, y, c);
            let n = m[0].len();
            let (mut s, mut d_mx, mut d_sx, mut d_sxy) =
                (vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]);
            s.par_iter_mut()
                .zip(d_mx.par_iter_mut())
                .zip(d_sx.par_iter_mut())
                .zip(d_sxy.par_iter_mut())
                .enumerate()
                .for_each(|(i, (((s, d_mx), d_sx), d_sxy))| {
                    let (mx, my) = (m[0][i], m[1][i]);
                    let (value, n1, n2, d1, d2) = ssim_at(&m, i);
                    *s = value;
                    *d_mx = 2.0 * my * n2 / (d1 * d2) - *s * 2.0 * mx / d1;
                    *d_sx = -*s / d2;
                    *d_sxy = 2.0 * n1 / (d1 * d2);
                });
            let [mx, my, ..] = m;
            [s, d_mx, d_sx, d_sxy, mx, my]
        })
        .collect();
    SsimParts { maps }
}

/// Each channel's SSIM map alone, one channel at a time: what the means
/// need, in a fifth of the memory [`ssim_parts`] holds for training's
/// gradient (a 4K view's parts took about 2.8 GB).
fn ssim_maps(x: &ImageView, y: &ImageView) -> Vec<Vec<f64>> {
    (0..3)
        .map(|c| {
            let m = moments(x, y, c);
            (0..m[0].len())
                .into_par_iter()
                .map(|i| ssim_at(&m, i).0)
                .collect()
        })
        .collect()
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
pub fn weighted_ssim_and_gradient(
    x: &ImageView,
    y: &ImageView,
    weights: &[f64],
) -> (f64, Vec<[f32; 3]>) {
    let (w, h) = (x.width, x.height);
    let parts = ssim_parts(x, y);
    // Per channel: its weighted SSIM sum, and the three blurred terms of
    // its gradient.
    let channels: Vec<(f64, [Vec<f64>; 3])> = parts
        .maps
        .par_iter()
        .map(|m| {
            let [s, d_mx, d_sx, d_sxy, mx, my] = m;
            let value = s.iter().zip(weights).map(|(a, b)| a * b).sum::<f64>();
            // dL/dx_q = G⋆(w·(A − 2B·μx − C·μy)) + 2x_q·G⋆(w·B) + y_q·G⋆(w·C)
            let term_a: Vec<f64> = (0..s.len())
                .into_par_iter()
                .map(|i| weights[i] * (d_mx[i] - 2.0 * d_sx[i] * mx[i] - d_sxy[i] * my[i]))
                .collect();
            let term_b: Vec<f64> = (0..s.len())
                .into_par_iter()
                .map(|i| weights[i] * d_sx[i])
                .collect();
            let term_c: Vec<f64> = (0..s.len())
                .into_par_iter()
                .map(|i| weights[i] * d_sxy[i])
                .collect();
            (
                value,
                [
                    blur(w, h, &term_a),
                    blur(w, h, &term_b),
                    blur(w, h, &term_c),
                ],
            )
        })
        .collect();
    let value = channels.iter().fold(0.0, |sum, (v, _)| sum + v);
    let grad: Vec<[f32; 3]> = (0..x.pixels.len())
        .into_par_iter()
        .map(|q| {
            std::array::from_fn(|c| {
                let [ga, gb, gc] = &channels[c].1;
                let xq = x.pixels[q][c] as f64;
                let yq = y.pixels[q][c] as f64;
                (ga[q] + 2.0 * xq * gb[q] + yq * gc[q]) as f32
            })
        })
        .collect();
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
}
