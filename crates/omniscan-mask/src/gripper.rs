//! Kinematic gripper masks: the gripper model rendered at the frame's
//! recorded gripper pose and finger opening, checked against the sensor depth.
//!
//! The paper segments the gripper with a U-Net trained on 3,000 labelled
//! images and propagates hand-picked seed masks with SAM2 ("Gripper Mask
//! Generation"), because the learned masks were unreliable. The robot already
//! knows where its gripper is (T_i and the finger opening are recorded with
//! every frame), so we project its model instead: the same meshes the robot
//! uses, placed by `omniscan_scene::gripper::GripperModel::parts`, rasterised by
//! the simulator's renderer with the capture's intrinsics and T_c. The
//! projection is then refined against the image:
//! - where the sensor sees something nearer than the model (the held object in
//!   front of a finger), the pixel is not gripper;
//! - where the sensor sees past the model (a soft finger bent away from where
//!   the model has it), the pixel is not gripper;
//! - optionally, the mask grows by a few pixels into neighbours whose depth
//!   and colour continue the gripper's (a finger bent outward).

use nalgebra::Isometry3;
use omniscan_core::Intrinsics;
use omniscan_core::image_io::RgbImage;
use omniscan_core::lens::Distortion;
use omniscan_scene::gripper::GripperModel;
use omniscan_scene::raster::{Instance, Label, Lighting, render};

use crate::plane::Plane;

/// Settings of the kinematic gripper mask.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GripperSettings {
    /// Samples per pixel along each axis when projecting the model.
    pub supersample: u32,
    /// Sensor depth nearer than the model by more than this hides the
    /// gripper, metres (at least; see `depth_noise_m_at_1m`).
    pub occlusion_tolerance_m: f32,
    /// The depth sensor's noise (standard deviation) at 1 m, metres; it grows
    /// with the square of the distance, and the occlusion tolerance is never
    /// below four of it.
    pub depth_noise_m_at_1m: f32,
    /// Sensor depth farther than the model by more than this means the gripper
    /// is not there, metres.
    pub see_through_tolerance_m: f32,
    /// Before the per-pixel checks, shift the projection by up to this many
    /// pixels (and its depth by the median offset) to where it best agrees
    /// with the sensor's depth: absorbs small calibration errors of T_i and
    /// T_c (0 = off).
    pub align_search_px: usize,
    /// Depth agreement that counts for that search, metres.
    pub align_tolerance_m: f32,
    /// Grow the mask by up to this many pixels where depth and colour continue
    /// the gripper's (0 = off).
    pub grow_px: usize,
    /// Depth agreement for growing, metres.
    pub grow_depth_tolerance_m: f32,
    /// Colour agreement for growing (RGB distance, channels 0..1).
    pub grow_colour_tolerance: f32,
}

impl Default for GripperSettings {
    fn default() -> Self {
        GripperSettings {
            supersample: 2,
            occlusion_tolerance_m: 0.0015,
            depth_noise_m_at_1m: 0.002,
            see_through_tolerance_m: 0.015,
            align_search_px: 8,
            align_tolerance_m: 0.006,
            grow_px: 0,
            grow_depth_tolerance_m: 0.003,
            grow_colour_tolerance: 0.1,
        }
    }
}

/// The gripper model as projected into one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct GripperProjection {
    /// Pixels where the gripper (fingers, body, wrist link) is the nearest thing.
    pub mask: Plane<bool>,
    /// Model depth (z, metres) of those pixels; 0 elsewhere.
    pub depth_m: Plane<f32>,
}

/// Projects a gripper model into the fixed camera.
pub struct KinematicGripper {
    pub model: GripperModel,
    pub intrinsics: Intrinsics,
    /// T_c: camera to world.
    pub camera_to_world: Isometry3<f64>,
    pub settings: GripperSettings,
    /// The camera's lens, for a capture whose images are distorted
    /// ([`LensMap::new`]); `None` for a pinhole.
    pub lens: Option<LensMap>,
}

/// Where each pixel of a distorted image looks in a pinhole render: the
/// render covers every such place (a barrel lens sees past the pinhole
/// frame), and each image pixel takes the render's pixel its ray hits.
pub struct LensMap {
    /// The pinhole camera rendered: the image's focal lengths, a canvas
    /// grown to cover the lens's field.
    render: Intrinsics,
    /// Per image pixel, row-major: the render pixel (index) its ray hits.
    source: Vec<Option<usize>>,
}

impl LensMap {
    /// The map of a camera with `intrinsics` (pixel centres at +0.5) and lens `distortion`.
    pub fn new(distortion: &Distortion, intrinsics: &Intrinsics) -> LensMap {
        let k = intrinsics;
        let rays: Vec<Option<[f64; 2]>> = (0..k.height)
            .flat_map(|j| (0..k.width).map(move |i| (i, j)))
            .map(|(i, j)| {
                let xd = (f64::from(i) + 0.5 - k.cx) / k.fx;
                let yd = (f64::from(j) + 0.5 - k.cy) / k.fy;
                distortion
                    .undistort(xd, yd)
                    .map(|[x, y]| [k.fx * x + k.cx, k.fy * y + k.cy])
            })
            .collect();
        // The canvas: the rays' extent, at most three image sizes each way.
        let (w, h) = (f64::from(k.width), f64::from(k.height));
        let seen = rays.iter().flatten();
        let lo_u = seen
            .clone()
            .map(|p| p[0])
            .fold(0.0, f64::min)
            .max(-w)
            .floor();
        let lo_v = seen
            .clone()
            .map(|p| p[1])
            .fold(0.0, f64::min)
            .max(-h)
            .floor();
        let hi_u = seen
            .clone()
            .map(|p| p[0])
            .fold(w, f64::max)
            .min(2.0 * w)
            .ceil();
        let hi_v = seen.map(|p| p[1]).fold(h, f64::max).min(2.0 * h).ceil();
        let render = Intrinsics {
            width: (hi_u - lo_u) as u32,
            height: (hi_v - lo_v) as u32,
            fx: k.fx,
            fy: k.fy,
            cx: k.cx - lo_u,
            cy: k.cy - lo_v,
        };
        let source = rays
            .iter()
            .map(|ray| {
                let [u, v] = (*ray)?;
                let (u, v) = ((u - lo_u).floor(), (v - lo_v).floor());
                (u >= 0.0
                    && v >= 0.0
                    && u < f64::from(render.width)
                    && v < f64::from(render.height))
                .then(|| v as usize * render.width as usize + u as usize)
            })
            .collect();
        LensMap { render, source }
    }
}

impl KinematicGripper {
    /// The model at `gripper_to_world` (T_i) with the pads `opening_m` apart.
    pub fn project(&self, gripper_to_world: &Isometry3<f64>, opening_m: f64) -> GripperProjection {
        let parts = self.model.parts(opening_m);
        let instances: Vec<Instance> = parts
            .iter()
            .map(|part| Instance {
                mesh: part.mesh,
                to_world: gripper_to_world * part.tcp_to_part,
                // The forearm is drawn so that it hides what it covers, but it
                // is not part of the gripper mask (the capture format's definition).
                label: if part.is_arm {
                    Label::Arm
                } else {
                    Label::Gripper
                },
                decals: &[],
            })
            .collect();
        let lighting = Lighting {
            ambient: [1.0; 3],
            lights: vec![],
        };
        let view = render(
            &instances,
            &lighting,
            self.lens.as_ref().map_or(&self.intrinsics, |l| &l.render),
            &self.camera_to_world,
            self.settings.supersample,
        );
        let gripper_depth = |i: usize| (view.labels[i] == Label::Gripper).then_some(view.depth[i]);
        // Depth along the optical axis is the same through the lens.
        let per_pixel: Vec<Option<f32>> = match &self.lens {
            None => (0..view.labels.len()).map(gripper_depth).collect(),
            Some(lens) => lens
                .source
                .iter()
                .map(|s| s.and_then(gripper_depth))
                .collect(),
        };
        let (w, h) = (
            self.intrinsics.width as usize,
            self.intrinsics.height as usize,
        );
        let mask: Vec<bool> = per_pixel.iter().map(Option::is_some).collect();
        let depth = per_pixel.iter().map(|d| d.unwrap_or(0.0)).collect();
        GripperProjection {
            mask: Plane {
                width: w,
                height: h,
                data: mask,
            },
            depth_m: Plane {
                width: w,
                height: h,
                data: depth,
            },
        }
    }

    /// The refined gripper mask of a frame (see the module doc).
    pub fn mask(
        &self,
        gripper_to_world: &Isometry3<f64>,
        opening_m: f64,
        image: &RgbImage,
        sensor_depth_m: &Plane<f32>,
    ) -> Plane<bool> {
        let projection = self.project(gripper_to_world, opening_m);
        refine(&projection, image, sensor_depth_m, &self.settings)
    }
}

/// Checks a projected gripper against the sensor depth and image.
pub fn refine(
    projection: &GripperProjection,
    image: &RgbImage,
    sensor_depth_m: &Plane<f32>,
    settings: &GripperSettings,
) -> Plane<bool> {
    let (w, h) = (projection.mask.width, projection.mask.height);
    let aligned;
    let projection = if settings.align_search_px > 0 {
        aligned = align_to_depth(projection, sensor_depth_m, settings);
        &aligned
    } else {
        projection
    };
    let mut mask = projection.mask.clone();
    for i in 0..w * h {
        if !mask.data[i] {
            continue;
        }
        let (sensor, model) = (sensor_depth_m.data[i], projection.depth_m.data[i]);
        if sensor <= 0.0 {
            continue;
        }
        let tolerance = settings
            .occlusion_tolerance_m
            .max(4.0 * settings.depth_noise_m_at_1m * model * model);
        if sensor < model - tolerance || sensor > model + settings.see_through_tolerance_m {
            mask.data[i] = false;
        }
    }
    let colour = |i: usize| -> [f32; 3] {
        let p = &image.data[3 * i..3 * i + 3];
        [
            p[0] as f32 / 255.0,
            p[1] as f32 / 255.0,
            p[2] as f32 / 255.0,
        ]
    };
    for _ in 0..settings.grow_px {
        let mut grown = mask.clone();
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let d = sensor_depth_m.data[i];
                if mask.data[i] || d <= 0.0 {
                    continue;
                }
                let c = colour(i);
                let mut accept = false;
                for (dx, dy) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                    let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                    if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                        continue;
                    }
                    let j = ny as usize * w + nx as usize;
                    if !mask.data[j] || sensor_depth_m.data[j] <= 0.0 {
                        continue;
                    }
                    let n = colour(j);
                    let colour_distance =
                        ((c[0] - n[0]).powi(2) + (c[1] - n[1]).powi(2) + (c[2] - n[2]).powi(2))
                            .sqrt();
                    if (d - sensor_depth_m.data[j]).abs() <= settings.grow_depth_tolerance_m
                        && colour_distance <= settings.grow_colour_tolerance
                    {
                        accept = true;
                        break;
                    }
                }
                grown.data[i] = accept;
            }
        }
        // A pass that adds nothing ends the growth (later ones would add
        // nothing either): --grow-px 1000000 ran a million passes.
        if grown == mask {
            break;
        }
        mask = grown;
    }
    mask
}

/// The projection moved by the image shift (searched coarse to fine within
/// `align_search_px`) at which most of its pixels agree with the sensor's
/// depth, with its depth moved by the median remaining offset. The unshifted
/// projection wins ties, so an exact calibration is left alone.
fn align_to_depth(
    projection: &GripperProjection,
    sensor_depth_m: &Plane<f32>,
    settings: &GripperSettings,
) -> GripperProjection {
    let (w, h) = (projection.mask.width, projection.mask.height);
    let pixels: Vec<(usize, usize, f32)> = (0..w * h)
        .filter(|&i| projection.mask.data[i])
        .map(|i| (i % w, i / w, projection.depth_m.data[i]))
        .collect();
    if pixels.is_empty() {
        return projection.clone();
    }
    // Index of pixel (x, y) moved by (dx, dy), if still inside the image.
    let shifted = |x: usize, y: usize, dx: i64, dy: i64| -> Option<usize> {
        let (sx, sy) = (x as i64 + dx, y as i64 + dy);
        (sx >= 0 && sy >= 0 && sx < w as i64 && sy < h as i64)
            .then(|| sy as usize * w + sx as usize)
    };
    // Sensor-minus-model depth of every shifted pixel that agrees with the sensor.
    let agreeing = |dx: i64, dy: i64| {
        pixels.iter().filter_map(move |&(x, y, model)| {
            let sensor = sensor_depth_m.data[shifted(x, y, dx, dy)?];
            (sensor > 0.0 && (sensor - model).abs() <= settings.align_tolerance_m)
                .then_some(sensor - model)
        })
    };
    let score = |dx: i64, dy: i64| agreeing(dx, dy).count();
    let reach = settings.align_search_px as i64;
    let unshifted = score(0, 0);
    let mut best = ((0i64, 0i64), unshifted);
    let consider = |dx: i64, dy: i64, best: &mut ((i64, i64), usize)| {
        let s = score(dx, dy);
        if s > best.1 {
            *best = ((dx, dy), s);
        }
    };
    let coarse = 2;
    for dy in (-reach..=reach).step_by(coarse) {
        for dx in (-reach..=reach).step_by(coarse) {
            consider(dx, dy, &mut best);
        }
    }
    let ((cx, cy), _) = best;
    for dy in cy - 1..=cy + 1 {
        for dx in cx - 1..=cx + 1 {
            consider(dx, dy, &mut best);
        }
    }
    // A shift must explain clearly more pixels than the recorded pose does:
    // with an exact calibration, occlusions and noise make small gains
    // elsewhere that are not worth a move.
    let (dx, dy) = if best.1 as f64 > unshifted as f64 * 1.005 + 10.0 {
        best.0
    } else {
        (0, 0)
    };
    let mut offsets: Vec<f32> = agreeing(dx, dy).collect();
    let offset = if offsets.is_empty() {
        0.0
    } else {
        let mid = offsets.len() / 2;
        *offsets.select_nth_unstable_by(mid, f32::total_cmp).1
    };
    let mut out = GripperProjection {
        mask: Plane::filled(w, h, false),
        depth_m: Plane::filled(w, h, 0.0),
    };
    for &(x, y, model) in &pixels {
        if let Some(j) = shifted(x, y, dx, dy) {
            out.mask.data[j] = true;
            out.depth_m.data[j] = model + offset;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn projection() -> GripperProjection {
        // A 10x10 gripper square at 0.40 m in a 20x20 image.
        let mask = Plane {
            width: 20,
            height: 20,
            data: (0..400)
                .map(|i| (5..15).contains(&(i % 20)) && (5..15).contains(&(i / 20)))
                .collect(),
        };
        let depth_m = Plane {
            width: 20,
            height: 20,
            data: mask
                .data
                .iter()
                .map(|&m| if m { 0.40 } else { 0.0 })
                .collect(),
        };
        GripperProjection { mask, depth_m }
    }

    fn grey(w: usize, h: usize) -> RgbImage {
        RgbImage {
            width: w as u32,
            height: h as u32,
            data: vec![100; w * h * 3],
        }
    }

    #[test]
    fn the_object_in_front_hides_the_gripper_and_the_background_shows_through() {
        let p = projection();
        let mut depth = Plane::filled(20, 20, 1.0f32);
        for y in 5..15 {
            for x in 5..15 {
                depth.data[y * 20 + x] = 0.40;
            }
        }
        // Object in front of the left column, background through the right column.
        for y in 5..15 {
            depth.data[y * 20 + 5] = 0.37;
            depth.data[y * 20 + 14] = 1.0;
        }
        let settings = GripperSettings::default();
        let m = refine(&p, &grey(20, 20), &depth, &settings);
        assert_eq!(m.count(), 80);
        assert!(!m.at(5, 8) && !m.at(14, 8) && m.at(6, 8) && m.at(13, 8));
    }

    #[test]
    fn a_miscalibrated_projection_is_moved_onto_the_depth() {
        // The real gripper sits 3 px right, 2 px down and 2 mm further than the model says.
        let p = projection();
        let mut depth = Plane::filled(20, 20, 1.0f32);
        for y in 7..17 {
            for x in 8..18 {
                depth.data[y * 20 + x] = 0.402;
            }
        }
        let m = refine(&p, &grey(20, 20), &depth, &GripperSettings::default());
        assert_eq!(m.count(), 100);
        assert!(m.at(8, 7) && m.at(17, 16) && !m.at(7, 7) && !m.at(5, 5));
        let off = GripperSettings {
            align_search_px: 0,
            ..GripperSettings::default()
        };
        // Without the search, the background shows through the uncovered part.
        assert_eq!(refine(&p, &grey(20, 20), &depth, &off).count(), 56);
    }

    #[test]
    fn growing_follows_depth_and_colour() {
        let p = projection();
        let mut depth = Plane::filled(20, 20, 1.0f32);
        for y in 5..15 {
            for x in 5..17 {
                depth.data[y * 20 + x] = 0.40; // the real finger reaches 2 px further
            }
        }
        let settings = GripperSettings {
            grow_px: 3,
            ..GripperSettings::default()
        };
        let m = refine(&p, &grey(20, 20), &depth, &settings);
        assert_eq!(m.count(), 120);
        assert!(m.at(16, 9) && !m.at(17, 9));
        // Growth stops where it adds nothing: a million passes give the
        // same mask at once.
        let settings = GripperSettings {
            grow_px: 1_000_000,
            ..settings
        };
        assert_eq!(refine(&p, &grey(20, 20), &depth, &settings), m);
    }
}
