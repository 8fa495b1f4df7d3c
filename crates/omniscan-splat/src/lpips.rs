//! LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep
//! Features as a Perceptual Metric"), the paper's third image metric, run
//! from an ONNX export of the network that the user provides (no weights
//! ship with omniscan or can be downloaded here).
//!
//! Contract of the file: two float inputs `[1, 3, H, W]`, RGB scaled to
//! [-1, 1] (the `lpips` package's convention), in that order; the first
//! output holds the distance (any shape with one element). Such a file comes
//! from `torch.onnx.export(lpips.LPIPS(net="alex"), (x, y), "lpips.onnx",
//! input_names=["in0", "in1"], dynamic_axes={"in0": {2: "h", 3: "w"}, "in1":
//! {2: "h", 3: "w"}})`. A model with a fixed input size gets images resized
//! bilinearly to it.
//!
//! The masked variant (the paper's "object pixels") sets every pixel outside
//! the mask to black in both images before comparing.

use std::path::Path;

use omniscan_onnx::{Input, OnnxModel};

use crate::SplatError;

/// A loaded LPIPS network.
#[derive(Debug)]
pub struct Lpips {
    model: OnnxModel,
    inputs: [String; 2],
    fixed_size: Option<(usize, usize)>,
}

fn onnx_error(e: omniscan_onnx::OnnxError) -> SplatError {
    SplatError::Invalid(e.to_string())
}

impl Lpips {
    /// Loads the network (ONNX Runtime found as `omniscan_onnx::find_runtime` says).
    pub fn load(path: &Path, runtime: Option<&Path>) -> Result<Lpips, SplatError> {
        let model = OnnxModel::load(path, runtime).map_err(onnx_error)?;
        if model.inputs.len() != 2 || model.outputs.is_empty() {
            return Err(SplatError::file(
                path,
                format!(
                    "an LPIPS network takes two images and returns a distance; this model has {} input(s) and {} output(s)",
                    model.inputs.len(),
                    model.outputs.len()
                ),
            ));
        }
        let mut fixed_size = None;
        for input in &model.inputs {
            match input.dims.as_slice() {
                [_, 3, h, w] if *h > 0 && *w > 0 => fixed_size = Some((*w as usize, *h as usize)),
                [_, 3, _, _] => {}
                other => {
                    return Err(SplatError::file(
                        path,
                        format!(
                            "LPIPS inputs must be [1, 3, H, W]; `{}` is {other:?}",
                            input.name
                        ),
                    ));
                }
            }
        }
        let inputs = [model.inputs[0].name.clone(), model.inputs[1].name.clone()];
        Ok(Lpips {
            model,
            inputs,
            fixed_size,
        })
    }

    /// LPIPS distance between two `width`x`height` images (RGB 0..1), with
    /// pixels outside `mask` blacked out in both when a mask is given.
    pub fn distance(
        &self,
        a: &[[f32; 3]],
        b: &[[f32; 3]],
        width: usize,
        height: usize,
        mask: Option<&[bool]>,
    ) -> Result<f64, SplatError> {
        let n = width * height;
        if a.len() != n || b.len() != n || mask.is_some_and(|m| m.len() != n) {
            return Err(SplatError::Invalid(format!(
                "LPIPS: images of {} and {} pixels for {width}x{height}",
                a.len(),
                b.len()
            )));
        }
        let (w, h) = self.fixed_size.unwrap_or((width, height));
        let keep = |i: usize| mask.is_none_or(|m| m[i]);
        let tensor = |image: &[[f32; 3]]| -> Vec<f32> {
            if (w, h) == (width, height) {
                // Channels first, no resampling: the floats as they are.
                let mut out = vec![-1.0f32; 3 * n];
                for (i, p) in image.iter().enumerate() {
                    if keep(i) {
                        for c in 0..3 {
                            out[c * n + i] = p[c].clamp(0.0, 1.0) * 2.0 - 1.0;
                        }
                    }
                }
                return out;
            }
            let image = omniscan_core::image_io::RgbImage {
                width: width as u32,
                height: height as u32,
                data: image
                    .iter()
                    .enumerate()
                    .flat_map(|(i, p)| {
                        let kept = keep(i);
                        p.map(|v| {
                            if kept {
                                (v.clamp(0.0, 1.0) * 255.0).round() as u8
                            } else {
                                0
                            }
                        })
                    })
                    .collect(),
            };
            omniscan_onnx::image_tensor(&image, w, h, |_, v| v / 127.5 - 1.0)
        };
        let dims = [1, 3, h as i64, w as i64];
        let outputs = self
            .model
            .run(vec![
                (self.inputs[0].clone(), Input::float(&dims, tensor(a))),
                (self.inputs[1].clone(), Input::float(&dims, tensor(b))),
            ])
            .map_err(onnx_error)?;
        match outputs.first().map(|o| o.data.as_slice()) {
            Some([d]) if d.is_finite() => Ok(*d as f64),
            _ => Err(SplatError::file(
                &self.model.path,
                format!(
                    "the LPIPS network's output is not one number: {:?}",
                    outputs.first().map(|o| &o.dims)
                ),
            )),
        }
    }
}
