//! Pinhole camera intrinsics in pixels, OpenCV conventions: x right, y down,
//! z forward, the centre of pixel (col, row) at (col + 0.5, row + 0.5).

use nalgebra::{Matrix4, Point2, Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::geometry::Pose;

/// Intrinsics of a pinhole camera without distortion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
}

impl Intrinsics {
    /// A camera with the given horizontal field of view (radians) and the
    /// principal point at the image centre.
    pub fn from_horizontal_fov(width: u32, height: u32, fov_x: f64) -> Self {
        let fx = 0.5 * width as f64 / (0.5 * fov_x).tan();
        Intrinsics {
            width,
            height,
            fx,
            fy: fx,
            cx: 0.5 * width as f64,
            cy: 0.5 * height as f64,
        }
    }

    /// Projects a camera-space point to pixel coordinates; `None` behind the camera.
    pub fn project(&self, p: &Point3<f64>) -> Option<Point2<f64>> {
        if p.z <= 0.0 {
            return None;
        }
        Some(Point2::new(
            self.fx * p.x / p.z + self.cx,
            self.fy * p.y / p.z + self.cy,
        ))
    }

    /// Camera-space point at pixel coordinates `(u, v)` and depth `z` (metres along the optical axis).
    pub fn unproject(&self, u: f64, v: f64, z: f64) -> Point3<f64> {
        Point3::new((u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z)
    }

    /// Unit ray direction through pixel coordinates `(u, v)`, camera space.
    pub fn ray(&self, u: f64, v: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0).normalize()
    }

    /// Checks the values a renderer or trainer relies on.
    pub fn validate(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "camera size {}x{} is empty",
                self.width, self.height
            ));
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !v.is_finite() || v <= 0.0 {
                return Err(format!(
                    "camera {name} must be a positive number of pixels, found {v}"
                ));
            }
        }
        check_principal_point(self.cx, self.cy, self.width, self.height)
            .map_err(|e| format!("camera {e}"))
    }
}

/// A principal point (`cx`, `cy`, pixels) a `width`x`height` image can
/// have: finite, and no further outside the image than its own size. A
/// cropped image's centre may lie outside it; one 4·10⁹ pixels away is a
/// damaged file, and its projections overflowed into NaN figures.
pub fn check_principal_point(cx: f64, cy: f64, width: u32, height: u32) -> Result<(), String> {
    for (name, v, size) in [("cx", cx, width), ("cy", cy, height)] {
        let size = f64::from(size);
        if !(v.is_finite() && (-size..=2.0 * size).contains(&v)) {
            return Err(format!(
                "{name} = {v} pixels is not within the {size}-pixel image or its own size beyond it"
            ));
        }
    }
    Ok(())
}

/// Converts an OpenCV camera-to-world pose (x right, y down, z forward) to the
/// OpenGL / nerfstudio convention (x right, y up, z backward), as a 4x4 matrix.
pub fn opencv_to_opengl(camera_to_world: &Pose) -> Matrix4<f64> {
    camera_to_world.to_homogeneous()
        * Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, -1.0, -1.0, 1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn project_unproject_round_trip() {
        let k = Intrinsics {
            width: 640,
            height: 480,
            fx: 500.0,
            fy: 510.0,
            cx: 320.5,
            cy: 239.0,
        };
        let p = Point3::new(0.05, -0.02, 0.4);
        let uv = k.project(&p).unwrap();
        let back = k.unproject(uv.x, uv.y, p.z);
        assert!((back - p).norm() < 1e-12);
        assert!(k.project(&Point3::new(0.0, 0.0, -1.0)).is_none());
    }

    /// A principal point 2³² pixels out turned every figure into NaN.
    #[test]
    fn principal_points_far_outside_the_image_are_refused() {
        assert!(check_principal_point(320.0, 240.0, 640, 480).is_ok());
        assert!(check_principal_point(-600.0, 900.0, 640, 480).is_ok());
        for (cx, cy) in [(4294967296.0, 240.0), (320.0, -481.0), (f64::NAN, 0.0)] {
            let error = check_principal_point(cx, cy, 640, 480).unwrap_err();
            assert!(error.contains("is not within"), "{error}");
        }
    }

    #[test]
    fn opengl_flip_keeps_position_and_turns_axes() {
        let pose = Pose::translation(1.0, 2.0, 3.0);
        let gl = opencv_to_opengl(&pose);
        assert_eq!(gl[(0, 3)], 1.0);
        assert_eq!(gl[(1, 1)], -1.0);
        assert_eq!(gl[(2, 2)], -1.0);
    }
}
