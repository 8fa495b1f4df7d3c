//! Painting of procedural textures: fills, stripes, noise, discs and
//! text-like print made of seeded glyphs, for the built-in objects and the
//! scene.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::mesh::Texture;

/// An RGB float image to paint on; v = 0 is the bottom row, as in UVs.
pub struct Canvas {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[f32; 3]>,
}

impl Canvas {
    pub fn new(width: u32, height: u32, color: [f32; 3]) -> Canvas {
        Canvas {
            width,
            height,
            pixels: vec![color; (width * height) as usize],
        }
    }

    fn put(&mut self, x: i64, y: i64, color: [f32; 3], alpha: f32) {
        if x < 0 || y < 0 || x >= self.width as i64 || y >= self.height as i64 {
            return;
        }
        // Row 0 of the texture is the top (v = 1).
        let i = ((self.height as i64 - 1 - y) * self.width as i64 + x) as usize;
        let p = &mut self.pixels[i];
        for c in 0..3 {
            p[c] = p[c] * (1.0 - alpha) + color[c] * alpha;
        }
    }

    fn to_px(&self, u: f32, v: f32) -> (i64, i64) {
        (
            (u * self.width as f32) as i64,
            (v * self.height as f32) as i64,
        )
    }

    /// Fills the UV rectangle [u0, u1] x [v0, v1].
    pub fn rect(&mut self, u0: f32, v0: f32, u1: f32, v1: f32, color: [f32; 3]) {
        let (x0, y0) = self.to_px(u0.min(u1), v0.min(v1));
        let (x1, y1) = self.to_px(u0.max(u1), v0.max(v1));
        for y in y0..y1.max(y0 + 1) {
            for x in x0..x1.max(x0 + 1) {
                self.put(x, y, color, 1.0);
            }
        }
    }

    /// A filled disc centred at (u, v) with radius `r` in units of the width.
    pub fn disc(&mut self, u: f32, v: f32, r: f32, color: [f32; 3]) {
        let (cx, cy) = self.to_px(u, v);
        let rp = (r * self.width as f32).max(1.0) as i64;
        for y in -rp..=rp {
            for x in -rp..=rp {
                if x * x + y * y <= rp * rp {
                    self.put(cx + x, cy + y, color, 1.0);
                }
            }
        }
    }

    /// Multiplies the image with seeded value noise of the given strength and feature size (pixels).
    pub fn noise(&mut self, seed: u64, strength: f32, feature: u32) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let gw = self.width / feature.max(1) + 2;
        let gh = self.height / feature.max(1) + 2;
        let grid: Vec<f32> = (0..gw * gh)
            .map(|_| rng.random::<f32>() * 2.0 - 1.0)
            .collect();
        let fine: Vec<f32> = (0..self.width * self.height)
            .map(|_| rng.random::<f32>() * 2.0 - 1.0)
            .collect();
        for y in 0..self.height {
            for x in 0..self.width {
                let gx = x as f32 / feature as f32;
                let gy = y as f32 / feature as f32;
                let (ix, iy) = (gx as u32, gy as u32);
                let (fx, fy) = (gx - ix as f32, gy - iy as f32);
                let at = |i: u32, j: u32| grid[(j.min(gh - 1) * gw + i.min(gw - 1)) as usize];
                let top = at(ix, iy) * (1.0 - fx) + at(ix + 1, iy) * fx;
                let bottom = at(ix, iy + 1) * (1.0 - fx) + at(ix + 1, iy + 1) * fx;
                let n = top * (1.0 - fy) + bottom * fy;
                let f = 1.0 + strength * (0.8 * n + 0.2 * fine[(y * self.width + x) as usize]);
                let p = &mut self.pixels[(y * self.width + x) as usize];
                for c in p.iter_mut() {
                    *c = (*c * f).clamp(0.0, 1.0);
                }
            }
        }
    }

    /// Stripes along u with the given period and duty (UV units).
    pub fn stripes(&mut self, period: f32, duty: f32, color: [f32; 3], [u0, v0, u1, v1]: [f32; 4]) {
        let mut u = u0;
        while u < u1 {
            self.rect(u, v0, (u + period * duty).min(u1), v1, color);
            u += period;
        }
    }

    /// Text-like print: each character is a seeded 5x7 glyph, so the same
    /// word always looks the same. `height` is the glyph height in UV units
    /// of the canvas height, starting at (u, v) = lower-left corner.
    pub fn text(&mut self, text: &str, u: f32, v: f32, height: f32, color: [f32; 3]) {
        let cell_h = height / 7.0 * self.height as f32;
        let cell_w = cell_h;
        let (x0, y0) = self.to_px(u, v);
        for (i, ch) in text.chars().enumerate() {
            if ch == ' ' {
                continue;
            }
            let glyph = glyph(ch);
            let gx = x0 as f32 + i as f32 * 6.0 * cell_w;
            for (row, bits) in glyph.iter().enumerate() {
                for col in 0..5 {
                    if bits & (1 << (4 - col)) != 0 {
                        let px0 = (gx + col as f32 * cell_w) as i64;
                        let py0 = (y0 as f32 + (6 - row) as f32 * cell_h) as i64;
                        let n = cell_w.ceil().max(1.0) as i64;
                        for dy in 0..n {
                            for dx in 0..n {
                                self.put(px0 + dx, py0 + dy, color, 1.0);
                            }
                        }
                    }
                }
            }
        }
    }

    pub fn into_texture(self) -> Texture {
        Texture {
            width: self.width,
            height: self.height,
            texels: self.pixels,
        }
    }
}

/// A seeded glyph: vertical and horizontal strokes on a 5x7 grid.
fn glyph(ch: char) -> [u8; 7] {
    let mut rng = ChaCha8Rng::seed_from_u64(ch as u64 * 7919 + 17);
    let mut rows = [0u8; 7];
    let strokes = 2 + rng.random_range(0..3);
    for _ in 0..strokes {
        if rng.random_bool(0.5) {
            let col = rng.random_range(0..5);
            let (a, b) = (rng.random_range(0..4), rng.random_range(3..7));
            for r in rows.iter_mut().take(b + 1).skip(a) {
                *r |= 1 << (4 - col);
            }
        } else {
            let row = [0, 3, 6, rng.random_range(0..7)][rng.random_range(0..4)];
            let (a, b) = (rng.random_range(0..3), rng.random_range(2..5));
            for col in a..=b {
                rows[row] |= 1 << (4 - col);
            }
        }
    }
    if ch.is_ascii_digit() {
        rows[0] |= 0b01110;
        rows[6] |= 0b01110;
    }
    rows
}
