//! ONNX models for the masking roles: the shared runtime (`omniscan_onnx`)
//! and a resampling helper for model outputs.

pub use omniscan_onnx::*;

/// A `width`x`height` plane of model output resampled to `to_width`x`to_height`.
pub fn resampled(
    data: &[f32],
    width: usize,
    height: usize,
    to_width: usize,
    to_height: usize,
) -> crate::Plane<f32> {
    let small = crate::Plane {
        width,
        height,
        data: data.to_vec(),
    };
    if (width, height) == (to_width, to_height) {
        return small;
    }
    let (sx, sy) = (
        width as f32 / to_width as f32,
        height as f32 / to_height as f32,
    );
    let mut out = Vec::with_capacity(to_width * to_height);
    for y in 0..to_height {
        for x in 0..to_width {
            out.push(small.sample((x as f32 + 0.5) * sx - 0.5, (y as f32 + 0.5) * sy - 0.5));
        }
    }
    crate::Plane {
        width: to_width,
        height: to_height,
        data: out,
    }
}
