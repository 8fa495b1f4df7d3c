//! Dense optical flow, the weight-free backend of the paper's RAFT role: the
//! object mask's foreground keeps only pixels that move between neighbouring
//! frames (paper, "Object Mask Generation").
//!
//! Algorithm: pyramidal Lucas-Kanade (Lucas and Kanade 1981; Bouguet's
//! coarse-to-fine scheme) evaluated densely. At every pyramid level the
//! structure tensor of the first image is averaged over a square window, the
//! second image is warped by the current flow, and the flow is updated by the
//! 2x2 least-squares step wherever the tensor's smaller eigenvalue shows
//! texture in both directions. Written here because no well-kept pure-Rust
//! crate has dense flow (`../shared/notes/masking.md`: OpenCV's DIS needs 1.2 GB
//! of system packages; the pure-Rust options are sparse-only or sprawling).
//! The mask only needs to know *whether* a pixel moved, which this gives at a
//! few milliseconds per frame.

use omniscan_core::image_io::RgbImage;

use crate::plane::Plane;

/// Settings of the Lucas-Kanade flow.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FlowSettings {
    /// Pyramid levels below the working resolution.
    pub levels: usize,
    /// Half-size of the averaging window, pixels at each level.
    pub window_radius: usize,
    /// Gauss-Newton steps per level.
    pub iterations: usize,
    /// Smallest eigenvalue of the window-averaged structure tensor (grey
    /// levels 0..1 per pixel, squared) for a flow estimate to count.
    pub min_eigenvalue: f32,
    /// How many times the images are halved before estimating (speed).
    pub halvings: usize,
}

impl Default for FlowSettings {
    fn default() -> Self {
        FlowSettings {
            levels: 3,
            window_radius: 3,
            iterations: 3,
            min_eigenvalue: 2e-5,
            halvings: 1,
        }
    }
}

/// A dense flow field at the input resolution: where each pixel of the first
/// image is found in the second, in pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct Flow {
    pub dx: Plane<f32>,
    pub dy: Plane<f32>,
    /// Whether the window around the pixel had enough texture for an estimate.
    pub valid: Plane<bool>,
}

impl Flow {
    /// Pixels with a valid estimate of at least `min_pixels` of motion.
    pub fn moving(&self, min_pixels: f32) -> Plane<bool> {
        let data = (0..self.dx.len())
            .map(|i| self.valid.data[i] && self.dx.data[i].hypot(self.dy.data[i]) >= min_pixels)
            .collect();
        Plane {
            width: self.dx.width,
            height: self.dx.height,
            data,
        }
    }
}

/// The optical-flow role: a weight-free method or a learned one.
pub trait FlowEstimator: Send + Sync {
    fn name(&self) -> &str;
    fn flow(&self, from: &RgbImage, to: &RgbImage) -> crate::Result<Flow>;
}

/// Dense pyramidal Lucas-Kanade.
#[derive(Debug, Clone, Default)]
pub struct LucasKanade {
    pub settings: FlowSettings,
}

impl FlowEstimator for LucasKanade {
    fn name(&self) -> &str {
        "lucas-kanade"
    }

    fn flow(&self, from: &RgbImage, to: &RgbImage) -> crate::Result<Flow> {
        if (from.width, from.height) != (to.width, to.height) {
            return Err(crate::MaskError::Invalid(format!(
                "optical flow between images of different sizes ({}x{} and {}x{})",
                from.width, from.height, to.width, to.height
            )));
        }
        Ok(lucas_kanade(
            &Plane::luminance(from),
            &Plane::luminance(to),
            &self.settings,
        ))
    }
}

/// Dense pyramidal Lucas-Kanade flow from grey image `a` to grey image `b`.
pub fn lucas_kanade(a: &Plane<f32>, b: &Plane<f32>, settings: &FlowSettings) -> Flow {
    let (width, height) = (a.width, a.height);
    let mut work_a = a.clone();
    let mut work_b = b.clone();
    for _ in 0..settings.halvings {
        if work_a.width < 16 || work_a.height < 16 {
            break;
        }
        work_a = work_a.half();
        work_b = work_b.half();
    }
    let work_scale = width as f32 / work_a.width as f32;
    let mut pyramid = vec![(work_a, work_b)];
    for _ in 0..settings.levels {
        let (pa, pb) = pyramid.last().unwrap();
        if pa.width < 16 || pa.height < 16 {
            break;
        }
        let next = (pa.half(), pb.half());
        pyramid.push(next);
    }

    let mut u: Plane<f32> = Plane::filled(0, 0, 0.0);
    let mut v: Plane<f32> = Plane::filled(0, 0, 0.0);
    let mut valid = Plane::filled(0, 0, false);
    for (level_index, (la, lb)) in pyramid.iter().enumerate().rev() {
        let (w, h) = (la.width, la.height);
        // Carry the coarser level's flow up, doubled.
        if u.width == 0 {
            u = Plane::filled(w, h, 0.0);
            v = Plane::filled(w, h, 0.0);
        } else {
            u = upsample(&u, w, h, 2.0);
            v = upsample(&v, w, h, 2.0);
        }
        let (gx, gy) = gradients(la);
        let product = |p: &Plane<f32>, q: &Plane<f32>| Plane {
            width: w,
            height: h,
            data: p
                .data
                .iter()
                .zip(&q.data)
                .map(|(a, b)| a * b)
                .collect::<Vec<f32>>(),
        };
        let r = settings.window_radius;
        let sxx = product(&gx, &gx).box_mean(r);
        let sxy = product(&gx, &gy).box_mean(r);
        let syy = product(&gy, &gy).box_mean(r);
        let mut textured = vec![false; w * h];
        for i in 0..w * h {
            let (a, b, c) = (sxx.data[i], sxy.data[i], syy.data[i]);
            let half_trace = 0.5 * (a + c);
            let min_eig = half_trace - (0.25 * (a - c) * (a - c) + b * b).sqrt();
            textured[i] = min_eig > settings.min_eigenvalue;
        }
        for _ in 0..settings.iterations {
            let mut it_gx = Plane::filled(w, h, 0.0f32);
            let mut it_gy = Plane::filled(w, h, 0.0f32);
            for y in 0..h {
                for x in 0..w {
                    let i = y * w + x;
                    let warped = lb.sample(x as f32 + u.data[i], y as f32 + v.data[i]);
                    let temporal = warped - la.data[i];
                    it_gx.data[i] = temporal * gx.data[i];
                    it_gy.data[i] = temporal * gy.data[i];
                }
            }
            let bx = it_gx.box_mean(r);
            let by = it_gy.box_mean(r);
            for i in 0..w * h {
                if !textured[i] {
                    continue;
                }
                let (a, b, c) = (sxx.data[i], sxy.data[i], syy.data[i]);
                let det = a * c - b * b;
                if det.abs() < 1e-12 {
                    continue;
                }
                let du = -(c * bx.data[i] - b * by.data[i]) / det;
                let dv = -(a * by.data[i] - b * bx.data[i]) / det;
                u.data[i] += du;
                v.data[i] += dv;
            }
        }
        if level_index == 0 {
            valid = Plane {
                width: w,
                height: h,
                data: textured,
            };
        }
    }
    let dx = upsample(&u, width, height, work_scale);
    let dy = upsample(&v, width, height, work_scale);
    let valid = Plane {
        width,
        height,
        data: (0..width * height)
            .map(|i| {
                let (x, y) = (i % width, i / width);
                let sx = ((x as f32 / work_scale) as usize).min(valid.width - 1);
                let sy = ((y as f32 / work_scale) as usize).min(valid.height - 1);
                valid.at(sx, sy)
            })
            .collect(),
    };
    Flow { dx, dy, valid }
}

/// Central-difference gradients (one-sided at the borders).
fn gradients(p: &Plane<f32>) -> (Plane<f32>, Plane<f32>) {
    let (w, h) = (p.width, p.height);
    let mut gx = Plane::filled(w, h, 0.0f32);
    let mut gy = Plane::filled(w, h, 0.0f32);
    for y in 0..h {
        for x in 0..w {
            let (x0, x1) = (x.saturating_sub(1), (x + 1).min(w - 1));
            let (y0, y1) = (y.saturating_sub(1), (y + 1).min(h - 1));
            gx.data[y * w + x] = (p.at(x1, y) - p.at(x0, y)) / (x1 - x0).max(1) as f32;
            gy.data[y * w + x] = (p.at(x, y1) - p.at(x, y0)) / (y1 - y0).max(1) as f32;
        }
    }
    (gx, gy)
}

/// Resamples a flow component to `w`x`h`, multiplying its values by `factor`.
fn upsample(p: &Plane<f32>, w: usize, h: usize, factor: f32) -> Plane<f32> {
    let sx = p.width as f32 / w as f32;
    let sy = p.height as f32 / h as f32;
    let mut data = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let src_x = (x as f32 + 0.5) * sx - 0.5;
            let src_y = (y as f32 + 0.5) * sy - 0.5;
            data.push(p.sample(src_x, src_y) * factor);
        }
    }
    Plane {
        width: w,
        height: h,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth random texture, sampled at an offset.
    fn texture(w: usize, h: usize, shift_x: f32, shift_y: f32) -> Plane<f32> {
        let f = |x: f32, y: f32| {
            0.5 + 0.2 * (0.21 * x + 0.05 * y).sin()
                + 0.15 * (0.13 * y - 0.07 * x).cos()
                + 0.1 * (0.37 * x + 0.29 * y).sin()
        };
        let data = (0..w * h)
            .map(|i| f((i % w) as f32 - shift_x, (i / w) as f32 - shift_y))
            .collect();
        Plane {
            width: w,
            height: h,
            data,
        }
    }

    #[test]
    fn recovers_a_translation() {
        for (sx, sy) in [(3.0f32, -2.0f32), (7.5, 4.0), (0.0, 0.0)] {
            let a = texture(160, 120, 0.0, 0.0);
            let b = texture(160, 120, sx, sy);
            let flow = lucas_kanade(&a, &b, &FlowSettings::default());
            // Inner pixels only: the borders see the texture leave the frame.
            let (mut ex, mut ey, mut n) = (0f32, 0f32, 0);
            for y in 20..100 {
                for x in 20..140 {
                    let i = y * 160 + x;
                    if flow.valid.data[i] {
                        ex += flow.dx.data[i];
                        ey += flow.dy.data[i];
                        n += 1;
                    }
                }
            }
            assert!(n > 8000, "too few valid estimates: {n}");
            let (mx, my) = (ex / n as f32, ey / n as f32);
            assert!(
                (mx - sx).abs() < 0.1 && (my - sy).abs() < 0.1,
                "({mx}, {my}) for ({sx}, {sy})"
            );
            let moving = flow.moving(0.5).count();
            if sx == 0.0 && sy == 0.0 {
                assert_eq!(moving, 0);
            } else {
                assert!(moving > 15000);
            }
        }
    }

    #[test]
    fn a_flat_image_has_no_valid_estimate() {
        let a = Plane::filled(64, 48, 0.5f32);
        let flow = lucas_kanade(&a, &a, &FlowSettings::default());
        assert_eq!(flow.valid.count(), 0);
        assert_eq!(flow.moving(0.1).count(), 0);
    }
}

/// The value range a learned flow model expects its RGB inputs in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FlowInputRange {
    /// 0..255 (RAFT's original code normalises inside the network).
    Bytes,
    /// 0..1.
    Unit,
    /// -1..1 (torchvision's RAFT transforms).
    Signed,
}

/// A learned optical-flow network (RAFT and its kin) run by ONNX Runtime.
/// Inputs: the model's first two inputs, each `[1, 3, H, W]` RGB in
/// `range`; `H`x`W` is the model's fixed size, else the image's rounded up to
/// multiples of 8 (RAFT's feature stride). Output: the one named `flow`,
/// `flow_up` or `flow_predictions`, else the last, `[1, 2, H', W']` with
/// (dx, dy) in pixels of that output; it is resampled to the image and
/// its vectors rescaled to the image's pixels. Every pixel counts as valid.
#[derive(Debug)]
pub struct OnnxFlow {
    pub model: crate::onnx::OnnxModel,
    pub range: FlowInputRange,
    inputs: [String; 2],
    fixed_size: Option<(usize, usize)>,
}

impl OnnxFlow {
    pub fn load(
        path: &std::path::Path,
        range: FlowInputRange,
        runtime: Option<&std::path::Path>,
    ) -> crate::Result<OnnxFlow> {
        let model = crate::onnx::OnnxModel::load(path, runtime)?;
        let bad = |m: String| crate::MaskError::file(path, m);
        if model.inputs.len() < 2 {
            return Err(bad(format!(
                "a flow model takes two images; this one has {} input(s)",
                model.inputs.len()
            )));
        }
        let mut fixed = None;
        for input in &model.inputs[..2] {
            match input.dims.as_slice() {
                [_, 3, h, w] if *h > 0 && *w > 0 => fixed = Some((*w as usize, *h as usize)),
                [_, 3, _, _] => {}
                other => {
                    return Err(bad(format!(
                        "a flow model's inputs must be [1, 3, H, W] RGB; input `{}` is {other:?}",
                        input.name
                    )));
                }
            }
        }
        let inputs = [model.inputs[0].name.clone(), model.inputs[1].name.clone()];
        Ok(OnnxFlow {
            model,
            range,
            inputs,
            fixed_size: fixed,
        })
    }
}

impl FlowEstimator for OnnxFlow {
    fn name(&self) -> &str {
        "onnx-flow"
    }

    fn flow(&self, from: &RgbImage, to: &RgbImage) -> crate::Result<Flow> {
        use crate::onnx::{Input, image_tensor, output_plane_size, pick_output, resampled};
        if (from.width, from.height) != (to.width, to.height) {
            return Err(crate::MaskError::Invalid(format!(
                "optical flow between images of different sizes ({}x{} and {}x{})",
                from.width, from.height, to.width, to.height
            )));
        }
        let (iw, ih) = (from.width as usize, from.height as usize);
        let (w, h) = self
            .fixed_size
            .unwrap_or((iw.div_ceil(8) * 8, ih.div_ceil(8) * 8));
        let range = self.range;
        let normalise = move |_: usize, v: f32| match range {
            FlowInputRange::Bytes => v,
            FlowInputRange::Unit => v / 255.0,
            FlowInputRange::Signed => v / 127.5 - 1.0,
        };
        let dims = [1, 3, h as i64, w as i64];
        let outputs = self.model.run(vec![
            (
                self.inputs[0].clone(),
                Input::float(&dims, image_tensor(from, w, h, normalise)),
            ),
            (
                self.inputs[1].clone(),
                Input::float(&dims, image_tensor(to, w, h, normalise)),
            ),
        ])?;
        let last = outputs.len().saturating_sub(1);
        let out = pick_output(&outputs, &["flow", "flow_up", "flow_predictions"], last)
            .ok_or_else(|| {
                crate::MaskError::file(&self.model.path, "the flow model returned nothing")
            })?;
        let (oh, ow) = output_plane_size(out, 2).ok_or_else(|| {
            crate::MaskError::file(
                &self.model.path,
                format!(
                    "the flow model's output `{}` is {:?}, expected [1, 2, H, W]",
                    out.name, out.dims
                ),
            )
        })?;
        let plane = ow * oh;
        let (sx, sy) = (iw as f32 / ow as f32, ih as f32 / oh as f32);
        let mut dx = resampled(&out.data[..plane], ow, oh, iw, ih);
        let mut dy = resampled(&out.data[plane..], ow, oh, iw, ih);
        dx.data.iter_mut().for_each(|v| *v *= sx);
        dy.data.iter_mut().for_each(|v| *v *= sy);
        let valid = Plane {
            width: iw,
            height: ih,
            data: (0..iw * ih)
                .map(|i| dx.data[i].is_finite() && dy.data[i].is_finite())
                .collect(),
        };
        Ok(Flow { dx, dy, valid })
    }
}
