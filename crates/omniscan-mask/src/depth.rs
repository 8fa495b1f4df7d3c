//! The depth role of the object pipeline (paper, "Mask Processing": the
//! foreground threshold and the non-robot score S_NR both read depth).
//!
//! - [`SensorDepth`] (default): the capture's depth images.
//! - [`MonocularDepth`]: a monocular depth network from an ONNX file (the
//!   paper uses Depth Anything V2 on plain RGB), for captures without a depth
//!   sensor. Such networks give relative inverse depth (disparity) with an
//!   unknown scale and shift per image. The paper thresholds that raw scale
//!   (its "140"); we put it in metres instead, so the same thresholds work
//!   for every backend: in every frame the gripper model, rendered at the
//!   robot's recorded pose, gives the true metric depth of the gripper's
//!   pixels, and 1/z = a·d + b is fitted there by least squares (twice, the
//!   second time without the worst fifth of the pixels: the object in front of
//!   a finger, the fingers' silhouettes). A network that outputs metres
//!   directly (`DepthOutput::Metres`) is used as it is.
//!
//! Monocular depth is far noisier than a sensor's: raise the gripper mask's
//! depth tolerance (`--depth-noise-mm-at-1m`) when using it.

use std::path::Path;

use omniscan_core::capture::{Capture, Frame};
use omniscan_core::image_io::{self, RgbImage};

use crate::onnx::{Input, OnnxModel, image_tensor, imagenet, output_plane_size, resampled};
use crate::plane::Plane;
use crate::{MaskError, Result};

/// The depth role: metres per pixel, 0 where unknown.
pub trait DepthEstimator: Send + Sync {
    fn name(&self) -> &str;
    /// Whether [`DepthEstimator::depth_m`] reads the image (else it may be
    /// given an empty one).
    fn reads_image(&self) -> bool {
        false
    }
    /// Whether [`DepthEstimator::depth_m`] needs the gripper model's depth.
    fn needs_anchor(&self) -> bool {
        false
    }
    /// Depth of frame `frame` (its image already read as `image`).
    /// `anchor`: metres where the gripper model is seen, 0 elsewhere
    /// (given when [`DepthEstimator::needs_anchor`]).
    fn depth_m(
        &self,
        capture: &Capture,
        frame: &Frame,
        image: &RgbImage,
        anchor: Option<&Plane<f32>>,
    ) -> Result<Plane<f32>>;
}

/// The capture's sensor depth (`depth_path` of each frame).
#[derive(Debug, Clone, Copy, Default)]
pub struct SensorDepth;

impl DepthEstimator for SensorDepth {
    fn name(&self) -> &str {
        "sensor"
    }

    fn depth_m(
        &self,
        capture: &Capture,
        frame: &Frame,
        _image: &RgbImage,
        _anchor: Option<&Plane<f32>>,
    ) -> Result<Plane<f32>> {
        let rel = frame.depth_path.as_ref().ok_or_else(|| {
            MaskError::file(
                capture.resolve(&frame.file_path),
                "has no depth_path: the masks need the sensor's depth (or a monocular depth model, --depth-model)",
            )
        })?;
        let path = capture.resolve(rel);
        let depth = Plane::depth_metres(&image_io::read_depth(&path)?);
        crate::check_size(
            &path,
            depth.width,
            depth.height,
            (capture.intrinsics().width, capture.intrinsics().height),
        )?;
        Ok(depth)
    }
}

/// What a monocular depth network outputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DepthOutput {
    /// Relative inverse depth, larger is nearer (Depth Anything V2's relative models).
    Disparity,
    /// Metres (metric-depth models).
    Metres,
}

/// A monocular depth network run by ONNX Runtime. Input: the first model
/// input, `[1, 3, H, W]` RGB with ImageNet normalisation (Depth Anything
/// V2's export); `H`x`W` is the model's fixed size, or for an open size the
/// image scaled so its shorter side is 518 pixels, both sides rounded to
/// multiples of 14 (the ViT patch). Output: the first output, `[1, H', W']`
/// or `[1, 1, H', W']`, resampled to the image.
#[derive(Debug)]
pub struct MonocularDepth {
    pub model: OnnxModel,
    pub output: DepthOutput,
    input_name: String,
    fixed_size: Option<(usize, usize)>,
}

/// Fewest anchor pixels for a scale/shift fit.
const MIN_ANCHOR_PIXELS: usize = 50;

impl MonocularDepth {
    pub fn load(
        path: &Path,
        output: DepthOutput,
        runtime: Option<&Path>,
    ) -> Result<MonocularDepth> {
        let model = OnnxModel::load(path, runtime)?;
        let input = model
            .inputs
            .first()
            .cloned()
            .ok_or_else(|| MaskError::file(path, "the depth model has no inputs"))?;
        let fixed_size = match input.dims.as_slice() {
            [_, 3, h, w] if *h > 0 && *w > 0 => Some((*w as usize, *h as usize)),
            [_, 3, _, _] => None,
            other => {
                return Err(MaskError::file(
                    path,
                    format!(
                        "a depth model's input must be [1, 3, H, W] RGB; input `{}` is {other:?}",
                        input.name
                    ),
                ));
            }
        };
        if model.outputs.is_empty() {
            return Err(MaskError::file(path, "the depth model has no outputs"));
        }
        Ok(MonocularDepth {
            model,
            output,
            input_name: input.name,
            fixed_size,
        })
    }

    /// The network input size for an image of `width`x`height`.
    fn input_size(&self, width: usize, height: usize) -> (usize, usize) {
        if let Some(size) = self.fixed_size {
            return size;
        }
        let scale = 518.0 / width.min(height).max(1) as f32;
        let round = |v: usize| (((v as f32 * scale) / 14.0).round() as usize).max(1) * 14;
        (round(width), round(height))
    }

    /// The network's raw output at the image's size.
    pub fn raw(&self, image: &RgbImage) -> Result<Plane<f32>> {
        let (iw, ih) = (image.width as usize, image.height as usize);
        let (w, h) = self.input_size(iw, ih);
        let data = image_tensor(image, w, h, imagenet);
        let outputs = self.model.run(vec![(
            self.input_name.clone(),
            Input::float(&[1, 3, h as i64, w as i64], data),
        )])?;
        let out = &outputs[0];
        let (oh, ow) = output_plane_size(out, 1).ok_or_else(|| {
            MaskError::file(
                &self.model.path,
                format!(
                    "the depth model's output `{}` is {:?}, expected one plane [1, H, W] or [1, 1, H, W]",
                    out.name, out.dims
                ),
            )
        })?;
        if out.data.iter().any(|v| !v.is_finite()) {
            return Err(MaskError::file(
                &self.model.path,
                "the depth model returned NaN or infinite values",
            ));
        }
        Ok(resampled(&out.data, ow, oh, iw, ih))
    }
}

/// Fits 1/z = a·d + b over the pixels where `anchor` (metres) is set, and
/// returns the metric depth of every pixel (0 where a·d + b ≤ 0).
pub fn disparity_to_metres(disparity: &Plane<f32>, anchor: &Plane<f32>) -> Result<Plane<f32>> {
    let mut pairs: Vec<(f64, f64)> = (0..anchor.len())
        .filter(|&i| anchor.data[i] > 0.0)
        .map(|i| (disparity.data[i] as f64, 1.0 / anchor.data[i] as f64))
        .collect();
    let fit = |pairs: &[(f64, f64)]| -> Option<(f64, f64)> {
        let n = pairs.len() as f64;
        let (sx, sy) = pairs
            .iter()
            .fold((0.0, 0.0), |(a, b), &(x, y)| (a + x, b + y));
        let (mx, my) = (sx / n, sy / n);
        let (sxx, sxy) = pairs.iter().fold((0.0, 0.0), |(a, b), &(x, y)| {
            (a + (x - mx) * (x - mx), b + (x - mx) * (y - my))
        });
        (sxx > 1e-12 * n).then(|| {
            let a = sxy / sxx;
            (a, my - a * mx)
        })
    };
    let not_enough = |n: usize| {
        MaskError::Invalid(format!(
            "cannot put the depth model's output in metres: the gripper model covers {n} pixels with varying output (at least {MIN_ANCHOR_PIXELS} needed)"
        ))
    };
    if pairs.len() < MIN_ANCHOR_PIXELS {
        return Err(not_enough(pairs.len()));
    }
    let (a, b) = fit(&pairs).ok_or_else(|| not_enough(0))?;
    pairs.sort_by(|p, q| {
        let r = |&(x, y): &(f64, f64)| (a * x + b - y).abs();
        r(p).total_cmp(&r(q))
    });
    pairs.truncate(pairs.len() * 4 / 5);
    let (a, b) = fit(&pairs).unwrap_or((a, b));
    if a <= 0.0 {
        return Err(MaskError::Invalid(
            "cannot put the depth model's output in metres: on the gripper it grows with distance; \
             is it metric depth rather than disparity (--depth-model-output metres)?"
                .into(),
        ));
    }
    Ok(Plane {
        width: disparity.width,
        height: disparity.height,
        data: disparity
            .data
            .iter()
            .map(|&d| {
                let inverse = a * d as f64 + b;
                if inverse > 1e-3 {
                    (1.0 / inverse) as f32
                } else {
                    0.0
                }
            })
            .collect(),
    })
}

impl DepthEstimator for MonocularDepth {
    fn name(&self) -> &str {
        "onnx-monocular"
    }

    fn reads_image(&self) -> bool {
        true
    }

    fn needs_anchor(&self) -> bool {
        self.output == DepthOutput::Disparity
    }

    fn depth_m(
        &self,
        _capture: &Capture,
        _frame: &Frame,
        image: &RgbImage,
        anchor: Option<&Plane<f32>>,
    ) -> Result<Plane<f32>> {
        let raw = self.raw(image)?;
        match self.output {
            DepthOutput::Metres => Ok(Plane {
                width: raw.width,
                height: raw.height,
                data: raw.data.iter().map(|&z| z.max(0.0)).collect(),
            }),
            DepthOutput::Disparity => {
                let anchor = anchor.ok_or_else(|| {
                    MaskError::Invalid("relative depth needs the gripper model's depth".into())
                })?;
                disparity_to_metres(&raw, anchor)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn disparity_fit_recovers_metric_depth_despite_outliers() {
        // True depth 0.3..0.6 m; the "network" gives 5/z + 2 (affine in 1/z).
        let (w, h) = (40, 30);
        let depth: Vec<f32> = (0..w * h)
            .map(|i| 0.3 + 0.3 * (i % w) as f32 / w as f32 + 0.001 * (i / w) as f32)
            .collect();
        let disparity = Plane {
            width: w,
            height: h,
            data: depth.iter().map(|z| 5.0 / z + 2.0).collect(),
        };
        // Anchors: the left third, with a tenth of them wrong by 5 cm.
        let anchor = Plane {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| match (i % w < w / 3, i % 10 == 0) {
                    (true, true) => depth[i] + 0.05,
                    (true, false) => depth[i],
                    _ => 0.0,
                })
                .collect(),
        };
        let metres = disparity_to_metres(&disparity, &anchor).unwrap();
        let worst = (0..w * h)
            .map(|i| (metres.data[i] - depth[i]).abs())
            .fold(0f32, f32::max);
        assert!(worst < 2e-3, "worst error {worst} m");
        // Too few anchors: an error, not a guess.
        let sparse = Plane {
            width: w,
            height: h,
            data: (0..w * h).map(|i| if i < 10 { 0.4 } else { 0.0 }).collect(),
        };
        assert!(disparity_to_metres(&disparity, &sparse).is_err());
    }
}
