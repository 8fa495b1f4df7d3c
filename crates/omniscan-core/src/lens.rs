//! Lens distortion of calibrated photos, and their resampling onto the
//! pinhole camera that the rasterizer renders.
//!
//! Photo sets from COLMAP (nerfstudio's `ns-process-data`) keep the lens's
//! distortion in `transforms.json`: OpenCV's radial-tangential (Brown-Conrady)
//! model, which COLMAP's OPENCV, RADIAL and SIMPLE_RADIAL cameras use, or
//! OpenCV's fisheye (equidistant) model, COLMAP's OPENCV_FISHEYE. A splat
//! renders through a pinhole, so each photo (with its mask and depth map) is
//! resampled onto the pinhole camera of the same intrinsics and size before
//! training: each pinhole pixel's ray is pushed through the lens model to
//! where it met the sensor, and the photo is read there (bilinear for
//! colour and mask, nearest for depth, which must not blend across edges).
//!
//! nerfstudio's Splatfacto undistorts at the same point, with OpenCV, but
//! picks new intrinsics and crops to the rectangle every pixel of which the
//! lens saw. Here the file's intrinsics and size stay, so a render lines up
//! with the file's camera; the pixels whose rays the photo did not record (a
//! pincushion lens's corners, or rays past the point where the model's
//! radius stops rising and folds back over the image) are marked unseen, and
//! training leaves them out of every loss as it does the gripper. A barrel
//! lens's rim beyond the pinhole frame is not used, as OpenCV's crop drops it.
//!
//! Written here, not taken from a crate: OpenCV's Rust bindings need the
//! C++ library at build time, and no pure-Rust crate has both models.

use crate::error::{CoreError, Result};
use crate::image_io::{DepthMm, Mask, RgbImage};

/// A lens's distortion, in OpenCV's normalised image coordinates (x = X/Z,
/// y = Y/Z of the ray in camera axes). In `capture.json` it is the camera's
/// `distortion`: `{"model": "opencv", "k1": …, "k2": …, "k3": …, "p1": …,
/// "p2": …}` or `{"model": "opencv_fisheye", "k1": …, "k2": …, "k3": …,
/// "k4": …}` (the coefficients are unitless).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "model", deny_unknown_fields)]
pub enum Distortion {
    /// With r² = x² + y²:
    /// x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²),
    /// y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y.
    #[serde(rename = "opencv")]
    RadialTangential {
        k1: f64,
        k2: f64,
        k3: f64,
        p1: f64,
        p2: f64,
    },
    /// With θ = atan r: θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸), and
    /// (x_d, y_d) = (θ_d / r) (x, y).
    #[serde(rename = "opencv_fisheye")]
    Fisheye { k1: f64, k2: f64, k3: f64, k4: f64 },
}

impl Distortion {
    /// Where the ray through the pinhole point (x, y) meets the photo, in the
    /// same normalised coordinates.
    pub fn distort(&self, x: f64, y: f64) -> [f64; 2] {
        let r2 = x * x + y * y;
        match *self {
            Distortion::RadialTangential { k1, k2, k3, p1, p2 } => {
                let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
                [
                    x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                    y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
                ]
            }
            Distortion::Fisheye { k1, k2, k3, k4 } => {
                let r = r2.sqrt();
                if r < 1e-12 {
                    return [x, y];
                }
                let theta = r.atan();
                let t2 = theta * theta;
                let theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))));
                let scale = theta_d / r;
                [x * scale, y * scale]
            }
        }
    }

    /// The pinhole point whose ray the lens puts at `(x_d, y_d)`: the
    /// inverse of [`distort`](Self::distort), by Newton's method from the
    /// distorted point (a finite-difference Jacobian); `None` where it does
    /// not converge to within 1e-10, as past the radius where the lens folds.
    pub fn undistort(&self, x_d: f64, y_d: f64) -> Option<[f64; 2]> {
        const H: f64 = 1e-7;
        let (mut x, mut y) = (x_d, y_d);
        for _ in 0..50 {
            let [fx, fy] = self.distort(x, y);
            let (rx, ry) = (fx - x_d, fy - y_d);
            if rx.hypot(ry) < 1e-10 {
                return Some([x, y]);
            }
            let [ax, ay] = self.distort(x + H, y);
            let [bx, by] = self.distort(x, y + H);
            let (j00, j10, j01, j11) = ((ax - fx) / H, (ay - fy) / H, (bx - fx) / H, (by - fy) / H);
            let det = j00 * j11 - j01 * j10;
            if !det.is_finite() || det.abs() < 1e-12 {
                return None;
            }
            x -= (j11 * rx - j01 * ry) / det;
            y -= (-j10 * rx + j00 * ry) / det;
        }
        None
    }

    /// The sign of the radial map's slope at pinhole radius `r`: past the
    /// first radius where it is not positive, rays further out land back
    /// inside, on pixels that already belong to nearer rays.
    fn radial_slope(&self, r: f64) -> f64 {
        match *self {
            Distortion::RadialTangential { k1, k2, k3, .. } => {
                let r2 = r * r;
                1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3))
            }
            // dθ_d/dr = dθ_d/dθ · 1/(1 + r²): the second factor is positive.
            Distortion::Fisheye { k1, k2, k3, k4 } => {
                let t2 = r.atan().powi(2);
                1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
            }
        }
    }

    /// The largest pinhole radius up to `r_max` below which the radial map
    /// rises all the way (`r_max` itself where it never stops), found on a
    /// grid of 4096 steps.
    pub fn fold_radius(&self, r_max: f64) -> f64 {
        const STEPS: u32 = 4096;
        (1..=STEPS)
            .map(|i| r_max * f64::from(i) / f64::from(STEPS))
            .find(|&r| self.radial_slope(r) <= 0.0)
            .map_or(r_max, |r| r - r_max / f64::from(STEPS))
    }
}

/// Checks a lens of a camera with `intrinsics`: finite coefficients, and a
/// pinhole image of which the lens saw at least half (a sign flipped in a
/// file folds the image over itself).
pub fn check_distortion(
    distortion: &Distortion,
    intrinsics: &crate::camera::Intrinsics,
) -> std::result::Result<(), String> {
    let coefficients = match *distortion {
        Distortion::RadialTangential { k1, k2, k3, p1, p2 } => vec![k1, k2, k3, p1, p2],
        Distortion::Fisheye { k1, k2, k3, k4 } => vec![k1, k2, k3, k4],
    };
    if coefficients.iter().any(|c| !c.is_finite()) {
        return Err(format!(
            "coefficients must be finite, found {coefficients:?}"
        ));
    }
    let k = intrinsics;
    let share = Undistortion::unseen_share(distortion, [k.fx, k.fy, k.cx, k.cy], k.width, k.height);
    if share > 0.5 {
        return Err(format!(
            "the lens leaves {:.0}% of the pinhole image unseen; check the coefficients and the intrinsics",
            share * 100.0
        ));
    }
    Ok(())
}

/// Where each pixel of the pinhole image reads a distorted photo.
#[derive(Debug, Clone)]
pub struct Undistortion {
    width: u32,
    height: u32,
    /// Per pinhole pixel, row-major: the photo position its ray met, with
    /// pixel (i, j)'s centre at (i, j); `None` where the photo did not see it.
    sources: Vec<Option<[f32; 2]>>,
}

impl Undistortion {
    /// The resampling of a `width` x `height` photo taken through
    /// `distortion` with focal lengths and principal point `[fx, fy, cx, cy]`
    /// in pixels whose first centre is (0.5, 0.5) (nerfstudio's and the
    /// rasterizer's), onto the pinhole camera with the same four and size.
    pub fn new(
        distortion: &Distortion,
        intrinsics: [f64; 4],
        width: u32,
        height: u32,
    ) -> Undistortion {
        let ray = RayTracer::new(distortion, intrinsics, width, height);
        let sources = (0..height)
            .flat_map(|j| (0..width).map(move |i| (i, j)))
            .map(|(i, j)| ray.source(f64::from(i) + 0.5, f64::from(j) + 0.5))
            .collect();
        Undistortion {
            width,
            height,
            sources,
        }
    }

    /// The share of [`new`](Self::new)'s pinhole pixels that the photo did
    /// not see, estimated on a grid of at most 64 x 64 of them (cheap enough
    /// to check every frame of a set before reading any image).
    pub fn unseen_share(
        distortion: &Distortion,
        intrinsics: [f64; 4],
        width: u32,
        height: u32,
    ) -> f64 {
        let ray = RayTracer::new(distortion, intrinsics, width, height);
        let (nx, ny) = (width.min(64), height.min(64));
        let grid =
            |n: u32, size: u32, k: u32| (f64::from(k) + 0.5) * f64::from(size) / f64::from(n);
        let unseen = (0..ny)
            .flat_map(|j| (0..nx).map(move |i| (i, j)))
            .filter(|&(i, j)| {
                ray.source(grid(nx, width, i), grid(ny, height, j))
                    .is_none()
            })
            .count();
        unseen as f64 / f64::from(nx * ny)
    }

    /// The pinhole pixels the photo did not see.
    pub fn unseen(&self) -> usize {
        self.sources.iter().filter(|s| s.is_none()).count()
    }

    /// 255 on the pinhole pixels the photo did not see, 0 elsewhere.
    pub fn unseen_mask(&self) -> Mask {
        Mask {
            width: self.width,
            height: self.height,
            data: self
                .sources
                .iter()
                .map(|s| if s.is_none() { 255 } else { 0 })
                .collect(),
        }
    }

    fn check_size(&self, what: &str, width: u32, height: u32) -> Result<()> {
        if (width, height) == (self.width, self.height) {
            return Ok(());
        }
        Err(CoreError::Invalid(format!(
            "the {what} is {width}x{height}, but its lens was calibrated for {}x{}",
            self.width, self.height
        )))
    }

    /// The photo as the pinhole camera sees it (bilinear; black where unseen).
    pub fn rgb(&self, photo: &RgbImage) -> Result<RgbImage> {
        self.check_size("photo", photo.width, photo.height)?;
        let mut data = Vec::with_capacity(photo.data.len());
        for source in &self.sources {
            match source {
                Some(s) => data.extend((0..3).map(|c| {
                    bilinear(photo.width, photo.height, *s, |p| {
                        f32::from(photo.data[p * 3 + c])
                    })
                    .round() as u8
                })),
                None => data.extend([0; 3]),
            }
        }
        Ok(RgbImage {
            width: self.width,
            height: self.height,
            data,
        })
    }

    /// The mask as the pinhole camera sees it: 255 where at least half of
    /// the bilinear footprint is in the mask (values from 128 count as in),
    /// 0 elsewhere and where unseen.
    pub fn mask(&self, mask: &Mask) -> Result<Mask> {
        self.check_size("mask", mask.width, mask.height)?;
        let data = self
            .sources
            .iter()
            .map(|source| match source {
                Some(s) => {
                    let inside = bilinear(mask.width, mask.height, *s, |p| {
                        f32::from(u8::from(mask.data[p] >= 128))
                    });
                    if inside >= 0.5 { 255 } else { 0 }
                }
                None => 0,
            })
            .collect();
        Ok(Mask {
            width: self.width,
            height: self.height,
            data,
        })
    }

    /// The depth map as the pinhole camera sees it: the nearest sample
    /// (depth along the optical axis is the same for both cameras), 0 where
    /// unseen.
    pub fn depth(&self, depth: &DepthMm) -> Result<DepthMm> {
        self.check_size("depth map", depth.width, depth.height)?;
        let data = self
            .sources
            .iter()
            .map(|source| match source {
                Some([u, v]) => {
                    let i = (u.round().max(0.0) as u32).min(depth.width - 1);
                    let j = (v.round().max(0.0) as u32).min(depth.height - 1);
                    depth.data[(j * depth.width + i) as usize]
                }
                None => 0,
            })
            .collect();
        Ok(DepthMm {
            width: self.width,
            height: self.height,
            data,
        })
    }
}

/// Traces a pinhole pixel's ray through the lens onto the photo.
struct RayTracer<'a> {
    distortion: &'a Distortion,
    intrinsics: [f64; 4],
    /// Rays further out than this pinhole radius fold back (see
    /// [`Distortion::fold_radius`]).
    fold: f64,
    size: (f64, f64),
}

impl<'a> RayTracer<'a> {
    fn new(distortion: &'a Distortion, intrinsics: [f64; 4], width: u32, height: u32) -> Self {
        let [fx, fy, cx, cy] = intrinsics;
        let (w, h) = (f64::from(width), f64::from(height));
        let r_max = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)]
            .iter()
            .map(|&(u, v)| ((u - cx) / fx).hypot((v - cy) / fy))
            .fold(0.0, f64::max);
        RayTracer {
            distortion,
            intrinsics,
            fold: distortion.fold_radius(r_max),
            size: (w, h),
        }
    }

    /// Where the ray through pinhole position (u, v) (pixel (i, j)'s centre
    /// at (i + 0.5, j + 0.5)) met the photo, with pixel (i, j)'s centre at
    /// (i, j); `None` where the photo did not record it.
    fn source(&self, u: f64, v: f64) -> Option<[f32; 2]> {
        let [fx, fy, cx, cy] = self.intrinsics;
        let (x, y) = ((u - cx) / fx, (v - cy) / fy);
        if x.hypot(y) > self.fold {
            return None;
        }
        let [xd, yd] = self.distortion.distort(x, y);
        let (ud, vd) = (fx * xd + cx, fy * yd + cy);
        // Inside the photo's own footprint, edges included.
        ((0.0..=self.size.0).contains(&ud) && (0.0..=self.size.1).contains(&vd))
            .then_some([(ud - 0.5) as f32, (vd - 0.5) as f32])
    }
}

/// The bilinear blend of `value(pixel index)` around `[u, v]` (pixel (i, j)'s
/// centre at (i, j)), the taps clamped to the image.
fn bilinear(width: u32, height: u32, [u, v]: [f32; 2], value: impl Fn(usize) -> f32) -> f32 {
    let clamp = |x: f32, n: u32| x.clamp(0.0, (n - 1) as f32);
    let (u, v) = (clamp(u, width), clamp(v, height));
    let (i0, j0) = (u.floor() as u32, v.floor() as u32);
    let (i1, j1) = ((i0 + 1).min(width - 1), (j0 + 1).min(height - 1));
    let (a, b) = (u - i0 as f32, v - j0 as f32);
    let at = |i: u32, j: u32| value((j * width + i) as usize);
    (1.0 - b) * ((1.0 - a) * at(i0, j0) + a * at(i1, j0))
        + b * ((1.0 - a) * at(i0, j1) + a * at(i1, j1))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The pinhole point whose ray meets the photo at (x_d, y_d): OpenCV's
    /// fixed-point iteration for the radial-tangential model, and Newton's
    /// method on θ for the fisheye, written apart from [`Distortion::distort`].
    fn undistort_point(d: &Distortion, xd: f64, yd: f64) -> [f64; 2] {
        match *d {
            Distortion::RadialTangential { k1, k2, k3, p1, p2 } => {
                let (mut x, mut y) = (xd, yd);
                for _ in 0..200 {
                    let r2 = x * x + y * y;
                    let radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2;
                    let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
                    let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
                    x = (xd - dx) / radial;
                    y = (yd - dy) / radial;
                }
                [x, y]
            }
            Distortion::Fisheye { k1, k2, k3, k4 } => {
                let theta_d = xd.hypot(yd);
                if theta_d == 0.0 {
                    return [0.0, 0.0];
                }
                let mut t = theta_d;
                for _ in 0..50 {
                    let f = t + k1 * t.powi(3) + k2 * t.powi(5) + k3 * t.powi(7) + k4 * t.powi(9)
                        - theta_d;
                    let df = 1.0
                        + 3.0 * k1 * t.powi(2)
                        + 5.0 * k2 * t.powi(4)
                        + 7.0 * k3 * t.powi(6)
                        + 9.0 * k4 * t.powi(8);
                    t -= f / df;
                }
                let s = t.tan() / theta_d;
                [xd * s, yd * s]
            }
        }
    }

    /// A smooth pattern on the pinhole plane, 0..255.
    fn pattern(x: f64, y: f64) -> f64 {
        127.5 + 100.0 * (5.0 * x).sin() * (4.0 * y + 0.3).cos()
    }

    /// A `width` x `height` photo of [`pattern`] through `d`: each photo
    /// pixel's centre traced back through the lens by [`undistort_point`].
    fn photo_through(d: &Distortion, k: [f64; 4], width: u32, height: u32) -> RgbImage {
        let [fx, fy, cx, cy] = k;
        let mut data = Vec::new();
        for j in 0..height {
            for i in 0..width {
                let xd = (f64::from(i) + 0.5 - cx) / fx;
                let yd = (f64::from(j) + 0.5 - cy) / fy;
                let [x, y] = undistort_point(d, xd, yd);
                let g = pattern(x, y).round() as u8;
                data.extend([g, g, 255 - g]);
            }
        }
        RgbImage {
            width,
            height,
            data,
        }
    }

    /// The mean absolute difference, in 8-bit levels, between `image` and
    /// the pattern on its pixels that `seen` allows.
    fn error_against_pattern(image: &RgbImage, k: [f64; 4], seen: &[bool]) -> f64 {
        let [fx, fy, cx, cy] = k;
        let (mut sum, mut n) = (0.0, 0);
        for j in 0..image.height {
            for i in 0..image.width {
                let p = (j * image.width + i) as usize;
                if !seen[p] {
                    continue;
                }
                let x = (f64::from(i) + 0.5 - cx) / fx;
                let y = (f64::from(j) + 0.5 - cy) / fy;
                sum += (f64::from(image.data[p * 3]) - pattern(x, y).round()).abs();
                n += 1;
            }
        }
        sum / n as f64
    }

    #[test]
    fn undistorted_photos_show_the_pinhole_view() {
        let (width, height) = (96, 72);
        let k = [80.0, 82.0, 49.0, 35.0];
        let lenses = [
            // Barrel, as a wide-angle lens under COLMAP's OPENCV model.
            Distortion::RadialTangential {
                k1: -0.28,
                k2: 0.07,
                k3: 0.0,
                p1: 0.002,
                p2: -0.001,
            },
            // Pincushion: its corners are unseen.
            Distortion::RadialTangential {
                k1: 0.15,
                k2: 0.0,
                k3: 0.01,
                p1: 0.0,
                p2: 0.0,
            },
            Distortion::Fisheye {
                k1: 0.05,
                k2: -0.01,
                k3: 0.002,
                k4: 0.0,
            },
        ];
        for lens in lenses {
            let photo = photo_through(&lens, k, width, height);
            let undistortion = Undistortion::new(&lens, k, width, height);
            let seen: Vec<bool> = undistortion.sources.iter().map(|s| s.is_some()).collect();
            let undistorted = undistortion.rgb(&photo).unwrap();
            let error = error_against_pattern(&undistorted, k, &seen);
            // The photo as it came: the pinhole assumption misplaces pixels off the centre.
            let as_taken = error_against_pattern(&photo, k, &seen);
            assert!(
                error < 0.5 && as_taken > 10.0 * error,
                "{lens:?}: {error} levels undistorted, {as_taken} as taken"
            );
            let unseen = undistortion.unseen();
            match lens {
                Distortion::RadialTangential { k1, .. } if k1 > 0.0 => {
                    assert!(unseen > 0 && unseen < 1000, "{unseen}");
                    // The corners are unseen, the centre is not.
                    assert!(undistortion.sources[0].is_none());
                    assert!(undistortion.sources[(35 * width + 48) as usize].is_some());
                }
                _ => assert_eq!(unseen, 0, "{lens:?}"),
            }
        }
    }

    #[test]
    fn masks_and_depth_follow_the_photo() {
        let lens = Distortion::RadialTangential {
            k1: 0.2,
            k2: 0.0,
            k3: 0.0,
            p1: 0.0,
            p2: 0.0,
        };
        let (width, height, k) = (40, 30, [30.0, 30.0, 20.0, 15.0]);
        let undistortion = Undistortion::new(&lens, k, width, height);
        // A mask and depth map of the photo's left half.
        let mask = Mask {
            width,
            height,
            data: (0..width * height)
                .map(|p| if p % width < 20 { 255 } else { 0 })
                .collect(),
        };
        let depth = DepthMm {
            width,
            height,
            data: (0..width * height)
                .map(|p| if p % width < 20 { 500 } else { 900 })
                .collect(),
        };
        let (m, d) = (
            undistortion.mask(&mask).unwrap(),
            undistortion.depth(&depth).unwrap(),
        );
        for p in 0..(width * height) as usize {
            match undistortion.sources[p] {
                // Each pixel keeps its side of the mask's edge, the vertical
                // line through the principal point, which the lens leaves straight.
                Some([u, _]) => {
                    assert_eq!(m.data[p] == 255, u < 19.5, "pixel {p}");
                    assert_eq!(d.data[p], if u < 19.5 { 500 } else { 900 });
                }
                None => assert_eq!((m.data[p], d.data[p]), (0, 0)),
            }
        }
        let wrong = Mask::new(width + 1, height);
        let error = undistortion.mask(&wrong).unwrap_err().to_string();
        assert!(
            error.contains("41x30") && error.contains("40x30"),
            "{error}"
        );
    }

    #[test]
    fn undistort_inverts_distort_for_both_models() {
        let lenses = [
            Distortion::RadialTangential {
                k1: -0.28,
                k2: 0.07,
                k3: 0.0,
                p1: 0.001,
                p2: -0.0008,
            },
            Distortion::Fisheye {
                k1: 0.05,
                k2: -0.01,
                k3: 0.002,
                k4: 0.0,
            },
        ];
        for lens in lenses {
            for (x, y) in [(0.0, 0.0), (0.31, -0.2), (-0.45, 0.33), (0.5, 0.38)] {
                let [xd, yd] = lens.distort(x, y);
                let [ux, uy] = lens.undistort(xd, yd).unwrap();
                assert!(
                    (ux - x).abs() < 1e-9 && (uy - y).abs() < 1e-9,
                    "{lens:?} {x} {y}: {ux} {uy}"
                );
            }
        }
    }

    #[test]
    fn a_lens_in_a_capture_file_reads_back_and_is_checked() {
        let lens = Distortion::Fisheye {
            k1: 0.05,
            k2: -0.01,
            k3: 0.002,
            k4: 0.0,
        };
        let json = serde_json::to_value(lens).unwrap();
        assert_eq!(json["model"], "opencv_fisheye");
        assert_eq!(serde_json::from_value::<Distortion>(json).unwrap(), lens);
        let bad =
            serde_json::json!({"model": "opencv", "k1": 0.1, "k2": 0.0, "k3": 0.0, "p1": 0.0});
        assert!(
            serde_json::from_value::<Distortion>(bad)
                .unwrap_err()
                .to_string()
                .contains("p2")
        );
        let k = crate::camera::Intrinsics::from_horizontal_fov(640, 480, 1.2);
        assert!(check_distortion(&lens, &k).is_ok());
        let folded = Distortion::RadialTangential {
            k1: -3.0,
            k2: 0.0,
            k3: 0.0,
            p1: 0.0,
            p2: 0.0,
        };
        assert!(
            check_distortion(&folded, &k)
                .unwrap_err()
                .contains("unseen")
        );
    }

    #[test]
    fn rays_past_the_fold_are_unseen() {
        // r_d = r (1 − 0.5 r²) peaks at r = 1/√1.5 ≈ 0.816 and falls after.
        let lens = Distortion::RadialTangential {
            k1: -0.5,
            k2: 0.0,
            k3: 0.0,
            p1: 0.0,
            p2: 0.0,
        };
        let fold = lens.fold_radius(2.0);
        assert!((fold - 1.5f64.sqrt().recip()).abs() < 1e-3, "{fold}");
        let (width, height) = (64, 64);
        // A wide view: its corners are 1.41 out, past the fold.
        let k = [32.0, 32.0, 32.0, 32.0];
        let undistortion = Undistortion::new(&lens, k, width, height);
        for (p, s) in undistortion.sources.iter().enumerate() {
            let (x, y) = (
                ((p % 64) as f64 + 0.5 - 32.0) / 32.0,
                ((p / 64) as f64 + 0.5 - 32.0) / 32.0,
            );
            assert_eq!(s.is_some(), x.hypot(y) <= fold, "pixel {p}");
        }
        // The grid's estimate of the unseen share, without the image.
        let exact = undistortion.unseen() as f64 / (64.0 * 64.0);
        let estimate = Undistortion::unseen_share(&lens, k, 64, 64);
        assert!(
            exact > 0.2 && (estimate - exact).abs() < 1e-9,
            "{estimate} {exact}"
        );
        let large = Undistortion::unseen_share(&lens, k.map(|v| 4.0 * v), 256, 256);
        assert!((large - exact).abs() < 0.02, "{large} against {exact}");
        // A model that rises everywhere has no fold.
        let gentle = Distortion::Fisheye {
            k1: 0.01,
            k2: 0.0,
            k3: 0.0,
            k4: 0.0,
        };
        assert_eq!(gentle.fold_radius(3.0), 3.0);
    }
}
