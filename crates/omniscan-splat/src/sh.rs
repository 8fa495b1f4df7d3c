//! Real spherical harmonics up to degree 3 in the basis order and signs of
//! the original 3DGS code (Sloan's "efficient evaluation"), as gsplat uses:
//! colour = max(Σ_k c_k·Y_k(d) + 0.5, 0) for the unit view direction d.

use crate::Real;

pub const C0: f64 = 0.282_094_791_773_878_14;
const C1: f64 = 0.488_602_511_902_919_9;
const C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
const C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// Number of coefficients per colour channel for a degree.
pub fn coefficients(degree: usize) -> usize {
    (degree + 1) * (degree + 1)
}

/// The basis values Y_0..Y_{(d+1)²−1} at the unit direction `dir`.
pub fn basis<F: Real>(degree: usize, dir: [F; 3]) -> Vec<F> {
    let c = F::c;
    let [x, y, z] = dir;
    // Sized once: growing it band by band reallocated three times per
    // Gaussian per view, a tenth of a training step.
    let mut b = Vec::with_capacity(coefficients(degree));
    b.push(c(C0));
    if degree >= 1 {
        b.extend([-c(C1) * y, c(C1) * z, -c(C1) * x]);
    }
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        b.extend([
            c(C2[0]) * x * y,
            c(C2[1]) * y * z,
            c(C2[2]) * (c(2.0) * zz - xx - yy),
            c(C2[3]) * x * z,
            c(C2[4]) * (xx - yy),
        ]);
    }
    if degree >= 3 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        b.extend([
            c(C3[0]) * y * (c(3.0) * xx - yy),
            c(C3[1]) * x * y * z,
            c(C3[2]) * y * (c(4.0) * zz - xx - yy),
            c(C3[3]) * z * (c(2.0) * zz - c(3.0) * xx - c(3.0) * yy),
            c(C3[4]) * x * (c(4.0) * zz - xx - yy),
            c(C3[5]) * z * (xx - yy),
            c(C3[6]) * x * (xx - c(3.0) * yy),
        ]);
    }
    b
}

/// Σ_k coeffs\[k\]·Y_k(dir) per channel (no offset, no clamp); `coeffs` holds
/// `(degree+1)²` RGB triples, basis index major.
pub fn evaluate<F: Real>(degree: usize, dir: [F; 3], coeffs: &[[F; 3]]) -> [F; 3] {
    let b = basis(degree, dir);
    let mut out = [F::zero(); 3];
    for (bk, ck) in b.iter().zip(coeffs) {
        for ch in 0..3 {
            out[ch] = out[ch] + *bk * ck[ch];
        }
    }
    out
}

/// Derivatives of the SH basis with respect to the (unit) direction.
pub fn basis_gradient<F: Real>(degree: usize, d: [F; 3]) -> Vec<[F; 3]> {
    let c = F::c;
    let [x, y, z] = d;
    let (c1, z0) = (c(C1), F::zero());
    let mut out = Vec::with_capacity(coefficients(degree));
    out.push([z0; 3]);
    if degree >= 1 {
        out.extend([[z0, -c1, z0], [z0, z0, c1], [-c1, z0, z0]]);
    }
    if degree >= 2 {
        let k = C2.map(c);
        out.extend([
            [k[0] * y, k[0] * x, z0],
            [z0, k[1] * z, k[1] * y],
            [c(-2.0) * k[2] * x, c(-2.0) * k[2] * y, c(4.0) * k[2] * z],
            [k[3] * z, z0, k[3] * x],
            [c(2.0) * k[4] * x, c(-2.0) * k[4] * y, z0],
        ]);
    }
    if degree >= 3 {
        let k = C3.map(c);
        let (xx, yy, zz) = (x * x, y * y, z * z);
        out.extend([
            [
                c(6.0) * k[0] * x * y,
                k[0] * (c(3.0) * xx - c(3.0) * yy),
                z0,
            ],
            [k[1] * y * z, k[1] * x * z, k[1] * x * y],
            [
                c(-2.0) * k[2] * x * y,
                k[2] * (c(4.0) * zz - xx - c(3.0) * yy),
                c(8.0) * k[2] * y * z,
            ],
            [
                c(-6.0) * k[3] * x * z,
                c(-6.0) * k[3] * y * z,
                k[3] * (c(6.0) * zz - c(3.0) * xx - c(3.0) * yy),
            ],
            [
                k[4] * (c(4.0) * zz - c(3.0) * xx - yy),
                c(-2.0) * k[4] * x * y,
                c(8.0) * k[4] * x * z,
            ],
            [
                c(2.0) * k[5] * x * z,
                c(-2.0) * k[5] * y * z,
                k[5] * (xx - yy),
            ],
            [
                k[6] * (c(3.0) * xx - c(3.0) * yy),
                c(-6.0) * k[6] * x * y,
                z0,
            ],
        ]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_is_orthonormal_on_the_sphere() {
        // Monte Carlo over a Fibonacci sphere: ∫ Y_i Y_j dΩ = δ_ij.
        let n = 20000;
        let mut gram = vec![vec![0.0f64; 16]; 16];
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for i in 0..n {
            let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - y * y).sqrt();
            let t = golden * i as f64;
            let b = basis(3, [r * t.cos(), y, r * t.sin()]);
            for a in 0..16 {
                for c in 0..16 {
                    gram[a][c] += b[a] * b[c] * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for a in 0..16 {
            for c in 0..16 {
                let want = if a == c { 1.0 } else { 0.0 };
                assert!(
                    (gram[a][c] - want).abs() < 2e-3,
                    "<Y{a},Y{c}> = {}",
                    gram[a][c]
                );
            }
        }
    }
}
