//! Turntable cameras around a splat model: evenly spaced azimuths at a
//! slight elevation, looking at the model's robust centre (the median of
//! its opaque splats, so floaters do not pull the view away), far enough
//! that the central 90% of the model fills about two thirds of the view.

use nalgebra::{Point3, Vector3};

use crate::Splats;
use crate::raster::Camera;
use omniscan_core::geometry::look_at;

/// The model's robust centre (median of its opaque splats) and radius (half
/// the diagonal of the box holding the central 90% of them per axis).
pub fn robust_bounds(model: &Splats) -> (Point3<f64>, f64) {
    let sigmoid = |x: f32| 1.0 / (1.0 + (-x).exp());
    let mut pts: Vec<[f32; 3]> = model
        .means
        .iter()
        .zip(&model.opacity_logits)
        .filter(|(_, o)| sigmoid(**o) > 0.1)
        .map(|(m, _)| *m)
        .collect();
    if pts.is_empty() {
        pts = model.means.clone();
    }
    if pts.is_empty() {
        return (Point3::origin(), 1.0);
    }
    let mut axes: Vec<Vec<f32>> = (0..3).map(|k| pts.iter().map(|p| p[k]).collect()).collect();
    let mut centre = [0.0f64; 3];
    let mut radius = 0.0f64;
    for (k, a) in axes.iter_mut().enumerate() {
        a.sort_by(f32::total_cmp);
        let (lo, mid, hi) = (
            a[a.len() / 20],
            a[a.len() / 2],
            a[a.len() - 1 - a.len() / 20],
        );
        centre[k] = mid as f64;
        radius += ((hi - lo) as f64 * 0.5).powi(2);
    }
    (Point3::from(centre), radius.sqrt().max(1e-6))
}

/// Half the horizontal field of view of the orbit's cameras.
pub const HALF_FOV_DEG: f64 = 25.0;

/// Where the orbit's camera at `azimuth` (radians, from +x towards +y)
/// stands and looks: 20° above the model's robust centre, at 1.5 times the
/// distance that fits its radius in the field of view; z is up.
pub fn orbit_eye(model: &Splats, azimuth: f64) -> (Point3<f64>, Point3<f64>) {
    let (target, radius) = robust_bounds(model);
    let distance = radius / HALF_FOV_DEG.to_radians().tan() * 1.5;
    let elevation = 20f64.to_radians();
    let eye = target
        + distance
            * Vector3::new(
                elevation.cos() * azimuth.cos(),
                elevation.cos() * azimuth.sin(),
                elevation.sin(),
            );
    (eye, target)
}

/// `count` cameras of `width` x `height` pixels orbiting the model.
pub fn orbit_cameras(model: &Splats, count: usize, width: u32, height: u32) -> Vec<Camera<f32>> {
    let focal = 0.5 * width as f64 / HALF_FOV_DEG.to_radians().tan();
    (0..count.max(1))
        .map(|i| {
            let azimuth = std::f64::consts::TAU * i as f64 / count.max(1) as f64;
            let (eye, target) = orbit_eye(model, azimuth);
            let distance = (eye - target).norm();
            let camera_to_world = look_at(&eye, &target, &Vector3::z());
            let intrinsics = omniscan_core::Intrinsics {
                width,
                height,
                fx: focal,
                fy: focal,
                cx: width as f64 * 0.5,
                cy: height as f64 * 0.5,
            };
            Camera {
                near: (0.01 * distance) as f32,
                far: (100.0 * distance) as f32,
                ..Camera::from_pose(&camera_to_world, &intrinsics)
            }
        })
        .collect()
}
