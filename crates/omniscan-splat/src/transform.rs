//! Rigid and similarity transforms of a whole splat model (used to bring the
//! right arm's model into the left arm's frame, paper "Aligning the scans"):
//! means x' = s·R·x + t, rotations q' = q_R ⊗ q, log-scales + ln s, and the
//! view-dependent colour rotated with the model.
//!
//! SH bands are rotated with per-band matrices D^l found numerically: the
//! rotated colour function must satisfy f'(d) = f(Rᵀd), so evaluating the
//! band's basis at a fixed set of well-spread directions d_i and at Rᵀd_i
//! gives D^l = Y(d)⁺·Y(Rᵀd) (least squares over twice as many directions as
//! the band has functions). This is exact up to rounding for any band and
//! avoids hand-written Wigner-D recursions.

use nalgebra::{DMatrix, Rotation3, UnitQuaternion, Vector3};

use crate::raster::Appearance;
use crate::sh::{basis, coefficients};
use crate::{SplatError, Splats};
use omniscan_core::Pose;

/// Rotation matrices for SH bands 1..=degree.
fn band_rotations(degree: usize, rotation: &Rotation3<f64>) -> Vec<DMatrix<f64>> {
    (1..=degree)
        .map(|l| {
            let size = 2 * l + 1;
            let samples = 2 * size;
            // Well-spread directions on a Fibonacci sphere.
            let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
            let dirs: Vec<Vector3<f64>> = (0..samples)
                .map(|i| {
                    let y = 1.0 - 2.0 * (i as f64 + 0.5) / samples as f64;
                    let r = (1.0 - y * y).sqrt();
                    let t = golden * i as f64 + 0.3;
                    Vector3::new(r * t.cos(), y, r * t.sin())
                })
                .collect();
            let start = coefficients(l - 1);
            let band = |d: &Vector3<f64>| -> Vec<f64> {
                basis(l, [d.x, d.y, d.z])[start..start + size].to_vec()
            };
            let y = DMatrix::from_fn(samples, size, |i, k| band(&dirs[i])[k]);
            let y_rot = DMatrix::from_fn(samples, size, |i, k| {
                band(&(rotation.inverse() * dirs[i]))[k]
            });
            let pinv = y
                .clone()
                .pseudo_inverse(1e-12)
                .expect("SH sample matrix has full rank");
            pinv * y_rot
        })
        .collect()
}

impl Splats {
    /// The model moved by `pose` after scaling by `scale` about the origin
    /// (x' = R·(s·x) + t).
    pub fn transformed(&self, pose: &Pose, scale: f64) -> Result<Splats, SplatError> {
        if !(scale.is_finite() && scale > 0.0) {
            return Err(SplatError::Invalid(format!(
                "scale must be a positive number, got {scale}"
            )));
        }
        let rotation = pose.rotation.to_rotation_matrix();
        let q_r: UnitQuaternion<f64> = pose.rotation;
        let ln_s = scale.ln() as f32;
        let k = self.sh_coefficients();
        // Fixed-rig SH are a function of the normal in the camera's frame,
        // which moving the model and its cameras together leaves as it was.
        let bands = match self.appearance {
            Appearance::ViewDirection => band_rotations(self.sh_degree, &rotation),
            Appearance::FixedRig => Vec::new(),
        };
        let mut out = self.clone();
        for i in 0..self.len() {
            let m = Vector3::from(self.means[i].map(|v| v as f64));
            let moved = pose.rotation * (m * scale) + pose.translation.vector;
            out.means[i] = [moved.x as f32, moved.y as f32, moved.z as f32];
            out.log_scales[i] = self.log_scales[i].map(|v| v + ln_s);
            let [w, x, y, z] = self.quats[i].map(|v| v as f64);
            let q = nalgebra::Quaternion::new(w, x, y, z);
            let r = q_r.quaternion() * q;
            out.quats[i] = [r.w as f32, r.i as f32, r.j as f32, r.k as f32];
            for (l, d) in bands.iter().enumerate() {
                let band = l + 1;
                let start = coefficients(band - 1);
                let size = 2 * band + 1;
                for ch in 0..3 {
                    let c =
                        DMatrix::from_fn(size, 1, |kk, _| self.sh[i * k + start + kk][ch] as f64);
                    let rotated = d * c;
                    for kk in 0..size {
                        out.sh[i * k + start + kk][ch] = rotated[kk] as f32;
                    }
                }
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use crate::Splats;
    use crate::raster::{Appearance, Camera, Settings, render};
    use nalgebra::{Point3, Vector3};
    use omniscan_core::Pose;
    use omniscan_core::geometry::look_at;

    fn model() -> Splats {
        let n = 40;
        let k = 16;
        let f = |i: usize, s: f32| (i as f32 * 1.7 + s).sin();
        Splats {
            means: (0..n)
                .map(|i| [0.3 * f(i, 0.0), 0.3 * f(i, 1.0), 0.3 * f(i, 2.0)])
                .collect(),
            log_scales: (0..n)
                .map(|i| [-3.0 + 0.3 * f(i, 3.0), -2.8, -3.2 + 0.2 * f(i, 4.0)])
                .collect(),
            quats: (0..n)
                .map(|i| [1.0, 0.3 * f(i, 5.0), 0.2 * f(i, 6.0), -0.4 * f(i, 7.0)])
                .collect(),
            opacity_logits: (0..n).map(|i| 1.0 + f(i, 8.0)).collect(),
            sh_degree: 3,
            sh: (0..n * k)
                .map(|j| [0.3 * f(j, 9.0), 0.3 * f(j, 10.0), 0.3 * f(j, 11.0)])
                .collect(),
            antialiased: false,
            appearance: Default::default(),
        }
    }

    fn camera(camera_to_world: &Pose) -> Camera<f64> {
        let v = camera_to_world.inverse().to_homogeneous();
        let mut viewmat = [[0.0; 4]; 4];
        for r in 0..4 {
            for c in 0..4 {
                viewmat[r][c] = v[(r, c)];
            }
        }
        Camera {
            viewmat,
            fx: 60.0,
            fy: 60.0,
            cx: 32.0,
            cy: 24.0,
            width: 64,
            height: 48,
            near: 0.01,
            far: 100.0,
        }
    }

    #[test]
    fn moving_model_and_camera_together_leaves_the_image_unchanged() {
        for appearance in [Appearance::ViewDirection, Appearance::FixedRig] {
            moved_with_the_camera(appearance);
        }
    }

    fn moved_with_the_camera(appearance: Appearance) {
        let m = Splats {
            appearance,
            ..model()
        };
        let eye = look_at(
            &Point3::new(0.4, -1.5, 0.6),
            &Point3::origin(),
            &Vector3::z(),
        );
        let settings = Settings {
            appearance,
            ..Settings::default()
        };
        let (_, before) = render(&m.gaussians::<f64>(), &camera(&eye), &settings);
        let pose = Pose::new(Vector3::new(0.2, -0.1, 0.5), Vector3::new(0.7, -1.1, 2.3));
        for scale in [1.0, 2.5] {
            let moved = m.transformed(&pose, scale).unwrap();
            // The camera moves with the model (and sits `scale` times farther).
            let eye_moved = Pose::from_parts(
                nalgebra::Translation3::from(
                    pose.rotation * (eye.translation.vector * scale) + pose.translation.vector,
                ),
                pose.rotation * eye.rotation,
            );
            let (_, after) = render(&moved.gaussians::<f64>(), &camera(&eye_moved), &settings);
            let worst = before
                .rgb
                .iter()
                .zip(&after.rgb)
                .flat_map(|(a, b)| (0..3).map(move |c| (a[c] - b[c]).abs()))
                .fold(0.0, f64::max);
            assert!(
                worst < 2e-4,
                "{appearance:?}, scale {scale}: colours differ by {worst}"
            );
            let alpha = before
                .alpha
                .iter()
                .zip(&after.alpha)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(alpha < 2e-4, "scale {scale}: alpha differs by {alpha}");
        }
        assert!(m.transformed(&pose, 0.0).is_err());
    }
}
