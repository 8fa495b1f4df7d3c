//! Object point clouds from a capture's depth: every masked pixel of the
//! chosen frames is back-projected and carried into the holding gripper's
//! frame (T_ic = T_i⁻¹·T_c), so the left and right scans give one coloured
//! cloud each, in the frames the paper's merge step aligns.

use rayon::prelude::*;

use crate::{PointCloud, RegisterError};
use omniscan_core::capture::{Arm, Capture};
use omniscan_core::image_io::{read_depth, read_mask, read_rgb};
use omniscan_core::poses::camera_to_object;

/// Back-projects the object pixels of every `frame_step`-th frame of `arm`
/// (every `pixel_step`-th pixel in each direction). Uses the frame's object
/// mask, or the ground-truth one of a simulated capture.
pub fn object_cloud(
    capture: &Capture,
    arm: Arm,
    frame_step: usize,
    pixel_step: u32,
) -> Result<PointCloud, RegisterError> {
    let k = *capture.intrinsics();
    let camera = capture.camera_to_world();
    let frames: Vec<_> = capture
        .arm_frames(arm)
        .step_by(frame_step.max(1))
        .map(|(_, f)| f.clone())
        .collect();
    if frames.is_empty() {
        return Err(RegisterError::Invalid(format!(
            "the capture has no {arm} frames"
        )));
    }
    let parts: Vec<PointCloud> = frames
        .par_iter()
        .map(|frame| -> Result<PointCloud, RegisterError> {
            let mask_path = frame
                .object_mask_path
                .clone()
                .or_else(|| frame.gt.as_ref().and_then(|g| g.object_mask_path.clone()))
                .ok_or_else(|| {
                    RegisterError::Invalid(format!(
                        "{}: no object mask; run the masking stage first",
                        frame.file_path
                    ))
                })?;
            let depth_path = frame
                .depth_path
                .clone()
                .ok_or_else(|| RegisterError::Invalid(format!("{}: no depth", frame.file_path)))?;
            let mask = read_mask(&capture.resolve(&mask_path))?;
            let depth = read_depth(&capture.resolve(&depth_path))?;
            let rgb = read_rgb(&capture.resolve(&frame.file_path))?;
            let to_object = camera_to_object(&frame.gripper_to_world.0, &camera);
            let mut cloud = PointCloud::default();
            let step = pixel_step.max(1);
            for y in (0..k.height).step_by(step as usize) {
                for x in (0..k.width).step_by(step as usize) {
                    if !mask.get(x, y) {
                        continue;
                    }
                    let Some(z) = depth.metres(x, y) else {
                        continue;
                    };
                    let (u, v) = (x as f64 + 0.5, y as f64 + 0.5);
                    let p = match capture.distortion() {
                        None => k.unproject(u, v, z),
                        // The pixel's ray, through the lens (the depth is
                        // registered to the colour image, lens and all).
                        Some(lens) => {
                            let Some([xn, yn]) =
                                lens.undistort((u - k.cx) / k.fx, (v - k.cy) / k.fy)
                            else {
                                continue;
                            };
                            nalgebra::Point3::new(xn * z, yn * z, z)
                        }
                    };
                    cloud.points.push(to_object * p);
                    let i = ((y * k.width + x) * 3) as usize;
                    cloud.colors.push(
                        [rgb.data[i], rgb.data[i + 1], rgb.data[i + 2]].map(|c| c as f32 / 255.0),
                    );
                }
            }
            Ok(cloud)
        })
        .collect::<Result<_, _>>()?;
    let mut out = PointCloud::default();
    for p in &parts {
        out.extend(p);
    }
    if out.is_empty() {
        return Err(RegisterError::Invalid(format!(
            "no object pixel with depth in the {arm} frames"
        )));
    }
    Ok(out)
}
