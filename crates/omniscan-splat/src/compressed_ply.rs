//! PlayCanvas' compressed PLY (`.compressed.ply`, written by SuperSplat and
//! `splat-transform`), read only: a `chunk` element with the bounds of each
//! run of 256 splats, a `vertex` element of four packed `uint`s per splat
//! (position and log-scale as 11/10/11-bit fractions of the chunk's bounds,
//! the rotation as the smallest three of the quaternion in 10 bits each and
//! the largest's index in 2, colour and opacity in 8 bits each), and an
//! optional `sh` element of bytes. The layout follows the reader in
//! `playcanvas/splat-transform` (MIT), which is its only description. The
//! axes are the 3DGS PLY's, so nothing is turned.

use crate::Splats;
use crate::sh::{C0, coefficients};
use omniscan_core::ply::PlyFile;

const CHUNK: usize = 256;

/// Whether a parsed PLY has the compressed layout (a `chunk` element and
/// `packed_position` in `vertex`).
pub fn is_compressed(ply: &PlyFile) -> bool {
    ply.element("chunk").is_some()
        && ply
            .element("vertex")
            .is_some_and(|v| v.scalar("packed_position").is_some())
}

/// Decompresses a compressed PLY into the model.
pub fn splats_from_compressed_ply(ply: &PlyFile) -> Result<Splats, String> {
    let chunk = ply.element("chunk").ok_or("no `chunk` element")?;
    let vertex = ply.element("vertex").ok_or("no `vertex` element")?;
    let column = |element: &'static str, name: &str| {
        let e = if element == "chunk" { chunk } else { vertex };
        e.scalar(name)
            .ok_or_else(|| format!("not a compressed PLY: no `{name}` in `{element}`"))
    };
    let n = vertex.count;
    if n == 0 {
        return Err("the model has no splats (`element vertex 0`)".into());
    }
    if chunk.count != n.div_ceil(CHUNK) {
        return Err(format!(
            "{} chunks for {n} splats: a compressed PLY has one per {CHUNK}",
            chunk.count
        ));
    }
    let bounds = |prefix: &str| -> Result<[[&[f64]; 3]; 2], String> {
        let axis = |end: &str, a: &str| column("chunk", &format!("{end}{prefix}{a}"));
        Ok([
            [axis("min_", "x")?, axis("min_", "y")?, axis("min_", "z")?],
            [axis("max_", "x")?, axis("max_", "y")?, axis("max_", "z")?],
        ])
    };
    let position_bounds = bounds("")?;
    let scale_bounds = bounds("scale_")?;
    let colour_bounds = match chunk.scalar("min_r") {
        Some(_) => Some([
            [
                column("chunk", "min_r")?,
                column("chunk", "min_g")?,
                column("chunk", "min_b")?,
            ],
            [
                column("chunk", "max_r")?,
                column("chunk", "max_g")?,
                column("chunk", "max_b")?,
            ],
        ]),
        None => None,
    };
    let packed = [
        column("vertex", "packed_position")?,
        column("vertex", "packed_rotation")?,
        column("vertex", "packed_scale")?,
        column("vertex", "packed_color")?,
    ];
    let rest = sh_rest(ply, n)?;
    let degree = match rest.len() {
        0 => 0,
        9 => 1,
        24 => 2,
        45 => 3,
        other => return Err(format!("{other} SH properties fit no SH degree")),
    };
    let k = coefficients(degree);
    let mut s = Splats {
        sh_degree: degree,
        ..Default::default()
    };
    for i in 0..n {
        let c = i / CHUNK;
        let word = |j: usize| packed[j][i] as u32;
        let lerp = |b: &[[&[f64]; 3]; 2], a: usize, t: f32| {
            let (lo, hi) = (b[0][a][c] as f32, b[1][a][c] as f32);
            lo * (1.0 - t) + hi * t
        };
        let p = unpack_11_10_11(word(0));
        s.means
            .push([0, 1, 2].map(|a| lerp(&position_bounds, a, p[a])));
        let q = unpack_scale(word(2));
        s.log_scales
            .push([0, 1, 2].map(|a| lerp(&scale_bounds, a, q[a])));
        s.quats.push(unpack_rotation(word(1)));
        let colour = [24, 16, 8, 0].map(|shift| unorm(word(3) >> shift, 8));
        let rgb = [0, 1, 2].map(|a| match &colour_bounds {
            Some(b) => lerp(b, a, colour[a]),
            None => colour[a],
        });
        s.sh.push(rgb.map(|v| (v - 0.5) / C0 as f32));
        let alpha = colour[3].clamp(0.5 / 255.0, 254.5 / 255.0);
        s.opacity_logits.push((alpha / (1.0 - alpha)).ln());
        for kk in 1..k {
            s.sh.push([0, 1, 2].map(|ch| sh_value(rest[ch * (k - 1) + kk - 1][i])));
        }
    }
    s.validate().map_err(|e| e.to_string())?;
    Ok(s)
}

/// The `sh` element's `f_rest_*` columns, in index order.
fn sh_rest(ply: &PlyFile, n: usize) -> Result<Vec<&[f64]>, String> {
    let Some(sh) = ply.element("sh") else {
        return Ok(Vec::new());
    };
    if sh.count != n {
        return Err(format!("{} SH rows for {n} splats", sh.count));
    }
    Ok((0..)
        .map_while(|i| sh.scalar(&format!("f_rest_{i}")))
        .collect())
}

fn unorm(value: u32, bits: u32) -> f32 {
    let top = (1u32 << bits) - 1;
    (value & top) as f32 / top as f32
}

fn unpack_11_10_11(word: u32) -> [f32; 3] {
    [
        unorm(word >> 21, 11),
        unorm(word >> 11, 10),
        unorm(word, 11),
    ]
}

fn unpack_scale(word: u32) -> [f32; 3] {
    unpack_11_10_11(word)
}

/// The quaternion in the PLY's `rot_0..3` order (w, x, y, z).
fn unpack_rotation(word: u32) -> [f32; 4] {
    let scale = std::f32::consts::SQRT_2;
    let [a, b, c] = [20, 10, 0].map(|shift| (unorm(word >> shift, 10) - 0.5) * scale);
    let m = (1.0 - (a * a + b * b + c * c)).max(0.0).sqrt();
    match word >> 30 {
        0 => [m, a, b, c],
        1 => [a, m, b, c],
        2 => [a, b, m, c],
        _ => [a, b, c, m],
    }
}

fn sh_value(byte: f64) -> f32 {
    let b = byte as f32;
    let n = if b <= 0.0 {
        0.0
    } else if b >= 255.0 {
        1.0
    } else {
        (b + 0.5) / 256.0
    };
    (n - 0.5) * 8.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unpacking_matches_the_packing_by_hand() {
        // x = 2047/2047, y = 0, z = 1023/2047 of the chunk's bounds.
        let word = (2047 << 21) | 1023;
        let p = unpack_11_10_11(word);
        assert_eq!(p[0], 1.0);
        assert_eq!(p[1], 0.0);
        assert!((p[2] - 1023.0 / 2047.0).abs() < 1e-7);
        // The largest component third (index 2 = y in w,x,y,z) and the other
        // three at the middle of their range, which is 0.
        let q = unpack_rotation((2 << 30) | (511 << 20) | (511 << 10) | 511);
        assert!((q[2] - 1.0).abs() < 1e-3 && q[0].abs() < 2e-3, "{q:?}");
        assert_eq!(sh_value(0.0), -4.0);
        assert_eq!(sh_value(255.0), 4.0);
    }
}
