//! The learned backend of the candidate-segment role: Segment Anything
//! (paper, "Mask Processing": SAM proposes the candidate masks that the
//! non-robot and non-gripper scores then accept or reject), run by ONNX
//! Runtime from the two files of the usual export.
//!
//! - Encoder: first input `[1, 3, S, S]`, the image scaled so its longer side
//!   is S (1024 for SAM), ImageNet-normalised, padded at the right and bottom;
//!   first output: the image embedding.
//! - Decoder: the interface of segment-anything's
//!   `scripts/export_onnx_model.py`: inputs `image_embeddings`,
//!   `point_coords` `[1, N, 2]` (in the scaled image's pixels), `point_labels`
//!   `[1, N]` (1 foreground, -1 padding), `mask_input` `[1, 1, 4e, 4e]`,
//!   `has_mask_input` `[1]`, `orig_im_size` `[2]` (height, width); outputs
//!   `masks` `[1, K, H, W]` (logits at the image's size) and
//!   `iou_predictions` `[1, K]`.
//!
//! Automatic proposal, after SAM's automatic mask generator: a grid of
//! single-point prompts over the region to segment; each prompt's best mask
//! (by predicted IoU; with K = 4 the first, single-mask output is skipped as
//! SAM does for ambiguous points) is kept when its predicted IoU and its
//! stability (IoU of the mask thresholded at +1 and at -1) are high enough;
//! masks are taken best first, a mask mostly covered by earlier ones is a
//! duplicate. Our [`CandidateProposer`] contract wants non-overlapping
//! segments that never cross the gripper mask's edge, so each mask is split
//! at that edge, and region pixels no mask covers become segments of their
//! own (connected pieces), so that nothing in the foreground is lost before
//! scoring.

use std::path::Path;

use omniscan_core::image_io::RgbImage;

use crate::onnx::{Input, OnnxModel, image_tensor, imagenet, output_plane_size, pick_output};
use crate::plane::Plane;
use crate::segment::{CandidateProposer, Segmentation};
use crate::{MaskError, Result};

/// Settings of the automatic proposal.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SamSettings {
    /// Prompt grid points along the longer side of the region's bounding box.
    pub points_per_side: usize,
    /// Smallest predicted IoU of a kept mask.
    pub min_predicted_iou: f32,
    /// Smallest stability score of a kept mask.
    pub min_stability: f32,
    /// A mask whose pixels are more than this share already taken is a duplicate.
    pub max_overlap: f32,
}

impl Default for SamSettings {
    fn default() -> Self {
        // SAM's automatic generator uses 0.88 / 0.95 on a 32x32 grid over the
        // whole image; our grid covers only the foreground.
        SamSettings {
            points_per_side: 16,
            min_predicted_iou: 0.88,
            min_stability: 0.9,
            max_overlap: 0.5,
        }
    }
}

const DECODER_INPUTS: [&str; 6] = [
    "image_embeddings",
    "point_coords",
    "point_labels",
    "mask_input",
    "has_mask_input",
    "orig_im_size",
];

/// Segment Anything as a candidate proposer.
#[derive(Debug)]
pub struct SamProposer {
    pub encoder: OnnxModel,
    pub decoder: OnnxModel,
    pub settings: SamSettings,
    encoder_input: String,
    encoder_size: usize,
    mask_input_dims: Vec<i64>,
}

impl SamProposer {
    pub fn load(
        encoder: &Path,
        decoder: &Path,
        settings: SamSettings,
        runtime: Option<&Path>,
    ) -> Result<SamProposer> {
        let encoder_model = OnnxModel::load(encoder, runtime)?;
        let decoder_model = OnnxModel::load(decoder, runtime)?;
        let input = encoder_model
            .inputs
            .first()
            .cloned()
            .ok_or_else(|| MaskError::file(encoder, "the SAM encoder has no inputs"))?;
        let encoder_size = match input.dims.as_slice() {
            [_, 3, h, w] if h == w && *h > 0 => *h as usize,
            [_, 3, h, w] if *h <= 0 && *w <= 0 => 1024,
            other => {
                return Err(MaskError::file(
                    encoder,
                    format!(
                        "a SAM encoder's input must be [1, 3, S, S] (normalised RGB); `{}` is {other:?}",
                        input.name
                    ),
                ));
            }
        };
        let missing: Vec<&str> = DECODER_INPUTS
            .iter()
            .copied()
            .filter(|n| decoder_model.input(n).is_none())
            .collect();
        if !missing.is_empty() {
            return Err(MaskError::file(
                decoder,
                format!(
                    "not a SAM decoder: inputs {missing:?} are missing (expected segment-anything's ONNX export: {DECODER_INPUTS:?})"
                ),
            ));
        }
        let mask_input_dims = decoder_model
            .input("mask_input")
            .map(|i| i.dims.clone())
            .filter(|d| d.len() == 4 && d.iter().all(|&v| v > 0))
            .unwrap_or_else(|| vec![1, 1, 256, 256]);
        Ok(SamProposer {
            encoder: encoder_model,
            decoder: decoder_model,
            settings,
            encoder_input: input.name,
            encoder_size,
            mask_input_dims,
        })
    }

    /// The image embedding and the image's scale in the encoder's frame.
    fn embed(&self, image: &RgbImage) -> Result<(Vec<i64>, Vec<f32>, f32)> {
        let (iw, ih) = (image.width as usize, image.height as usize);
        let s = self.encoder_size;
        let scale = s as f32 / iw.max(ih) as f32;
        let (sw, sh) = (
            ((iw as f32 * scale).round() as usize).clamp(1, s),
            ((ih as f32 * scale).round() as usize).clamp(1, s),
        );
        let scaled = image_tensor(image, sw, sh, imagenet);
        // Padding is zero after normalisation (SAM pads the normalised image).
        let mut padded = vec![0f32; 3 * s * s];
        for c in 0..3 {
            for y in 0..sh {
                let from = (c * sh + y) * sw;
                let to = (c * s + y) * s;
                padded[to..to + sw].copy_from_slice(&scaled[from..from + sw]);
            }
        }
        let outputs = self.encoder.run(vec![(
            self.encoder_input.clone(),
            Input::float(&[1, 3, s as i64, s as i64], padded),
        )])?;
        let embedding = outputs.into_iter().next().ok_or_else(|| {
            MaskError::file(&self.encoder.path, "the SAM encoder returned nothing")
        })?;
        Ok((embedding.dims, embedding.data, scale))
    }

    /// The best mask for one point prompt, with its predicted IoU and
    /// stability, or None when the decoder returns no usable mask.
    fn decode(
        &self,
        embedding: &(Vec<i64>, Vec<f32>),
        point: (f32, f32),
        width: usize,
        height: usize,
    ) -> Result<Option<(Vec<f32>, f32, f32)>> {
        let mask_len: i64 = self.mask_input_dims.iter().product();
        let outputs = self.decoder.run(vec![
            (
                "image_embeddings".into(),
                Input::float(&embedding.0, embedding.1.clone()),
            ),
            (
                "point_coords".into(),
                Input::float(&[1, 2, 2], vec![point.0, point.1, 0.0, 0.0]),
            ),
            (
                "point_labels".into(),
                Input::float(&[1, 2], vec![1.0, -1.0]),
            ),
            (
                "mask_input".into(),
                Input::float(&self.mask_input_dims, vec![0.0; mask_len as usize]),
            ),
            ("has_mask_input".into(), Input::float(&[1], vec![0.0])),
            (
                "orig_im_size".into(),
                Input::float(&[2], vec![height as f32, width as f32]),
            ),
        ])?;
        let masks = pick_output(&outputs, &["masks"], 0).ok_or_else(|| {
            MaskError::file(&self.decoder.path, "the SAM decoder returned nothing")
        })?;
        let plane = width * height;
        let count = masks.data.len() / plane.max(1);
        if count == 0 || output_plane_size(masks, count) != Some((height, width)) {
            return Err(MaskError::file(
                &self.decoder.path,
                format!(
                    "the SAM decoder's `masks` is {:?}, expected [1, K, {height}, {width}]",
                    masks.dims
                ),
            ));
        }
        let scores = pick_output(&outputs, &["iou_predictions"], 1)
            .filter(|s| s.data.len() == count)
            .map(|s| s.data.clone())
            .unwrap_or_else(|| vec![1.0; count]);
        // With the multi-mask output, the first mask is the single-mask answer.
        let first = usize::from(count == 4);
        let Some(best) = (first..count).max_by(|&a, &b| scores[a].total_cmp(&scores[b])) else {
            return Ok(None);
        };
        let logits = masks.data[best * plane..(best + 1) * plane].to_vec();
        let high = logits.iter().filter(|&&v| v > 1.0).count();
        let low = logits.iter().filter(|&&v| v > -1.0).count();
        let stability = if low == 0 {
            0.0
        } else {
            high as f32 / low as f32
        };
        Ok(Some((logits, scores[best], stability)))
    }
}

impl CandidateProposer for SamProposer {
    fn name(&self) -> &str {
        "sam"
    }

    fn propose(
        &self,
        image: &RgbImage,
        depth_m: &Plane<f32>,
        region: &Plane<bool>,
        barrier: &Plane<bool>,
    ) -> Result<Segmentation> {
        crate::segment::check_sizes(image, depth_m, region, barrier)?;
        let (w, h) = (image.width as usize, image.height as usize);
        let n = w * h;
        let mut labels = Plane::filled(w, h, u32::MAX);
        let mut sizes: Vec<usize> = Vec::new();
        let mut add = |labels: &mut Plane<u32>, pixels: &[usize]| {
            if pixels.is_empty() {
                return;
            }
            for &i in pixels {
                labels.data[i] = sizes.len() as u32;
            }
            sizes.push(pixels.len());
        };
        if let Some((x0, y0, x1, y1)) = bounding_box(region) {
            let embedding = self.embed(image)?;
            let scale = embedding.2;
            let embedding = (embedding.0, embedding.1);
            let step = ((x1 - x0).max(y1 - y0) as f32
                / self.settings.points_per_side.max(1) as f32)
                .max(1.0);
            let mut masks: Vec<(Vec<usize>, f32)> = Vec::new();
            let mut y = y0 as f32 + step / 2.0;
            while y <= y1 as f32 {
                let mut x = x0 as f32 + step / 2.0;
                while x <= x1 as f32 {
                    let (px, py) = (x as usize, y as usize);
                    if region.at(px, py) {
                        let point = ((x + 0.5) * scale, (y + 0.5) * scale);
                        if let Some((logits, score, stability)) =
                            self.decode(&embedding, point, w, h)?
                            && score >= self.settings.min_predicted_iou
                            && stability >= self.settings.min_stability
                        {
                            let pixels: Vec<usize> = (0..n)
                                .filter(|&i| logits[i] > 0.0 && region.data[i])
                                .collect();
                            if !pixels.is_empty() {
                                masks.push((pixels, score));
                            }
                        }
                    }
                    x += step;
                }
                y += step;
            }
            masks.sort_by(|a, b| b.1.total_cmp(&a.1));
            for (pixels, _) in masks {
                let free: Vec<usize> = pixels
                    .iter()
                    .copied()
                    .filter(|&i| labels.data[i] == u32::MAX)
                    .collect();
                if (free.len() as f32) < (1.0 - self.settings.max_overlap) * pixels.len() as f32 {
                    continue;
                }
                let (inside, outside): (Vec<usize>, Vec<usize>) =
                    free.into_iter().partition(|&i| barrier.data[i]);
                add(&mut labels, &inside);
                add(&mut labels, &outside);
            }
        }
        // What no mask covers: its connected pieces, split at the barrier's edge.
        let uncovered = Plane {
            width: w,
            height: h,
            data: (0..n)
                .map(|i| region.data[i] && labels.data[i] == u32::MAX)
                .collect(),
        };
        let (pieces, piece_sizes) =
            uncovered.components_joined_by(|i, j| barrier.data[i] == barrier.data[j]);
        let mut members: Vec<Vec<usize>> = vec![Vec::new(); piece_sizes.len()];
        for (i, &p) in pieces.data.iter().enumerate() {
            if p != u32::MAX {
                members[p as usize].push(i);
            }
        }
        for pixels in &members {
            add(&mut labels, pixels);
        }
        Ok(Segmentation { labels, sizes })
    }
}

/// The smallest box holding every set pixel: (x0, y0, x1, y1), inclusive.
fn bounding_box(region: &Plane<bool>) -> Option<(usize, usize, usize, usize)> {
    let mut bounds: Option<(usize, usize, usize, usize)> = None;
    for (i, &set) in region.data.iter().enumerate() {
        if set {
            let (x, y) = (i % region.width, i / region.width);
            bounds = Some(match bounds {
                None => (x, y, x, y),
                Some((a, b, c, d)) => (a.min(x), b.min(y), c.max(x), d.max(y)),
            });
        }
    }
    bounds
}
