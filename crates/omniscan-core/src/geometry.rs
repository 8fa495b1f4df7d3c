//! Rigid transforms as the capture format stores them: 4x4 row-major matrices
//! in metres. Internally a transform is an `Isometry3<f64>`; the file form is
//! validated on the way in (finite, bottom row `0 0 0 1`, orthonormal rotation
//! with determinant +1) so that a bad calibration is caught where it is read,
//! not as a blurred model hours later.

use nalgebra::{
    Isometry3, Matrix3, Matrix4, Point3, Rotation3, Translation3, UnitQuaternion, Vector3,
};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// A rigid transform (rotation + translation in metres).
pub type Pose = Isometry3<f64>;

/// Tolerance on `RᵀR − I` (max abs entry) and on `det R − 1` for a matrix to
/// count as rigid. Loose enough for matrices printed with 6 decimals.
pub const RIGIDITY_TOLERANCE: f64 = 1e-4;

/// Why a 4x4 matrix is not a rigid transform.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MatrixError {
    #[error("matrix has a non-finite entry (NaN or infinity) at row {row}, column {col}")]
    NonFinite { row: usize, col: usize },
    #[error("matrix bottom row must be [0, 0, 0, 1], found {0:?}")]
    BottomRow([f64; 4]),
    #[error(
        "matrix is not rigid: rotation part deviates from orthonormal by {deviation:.3e} (tolerance {RIGIDITY_TOLERANCE:e})"
    )]
    NotOrthonormal { deviation: f64 },
    #[error("matrix is a reflection, not a rotation (determinant {det:.4})")]
    Reflection { det: f64 },
}

/// Converts a row-major 4x4 matrix into a pose, checking that it is rigid.
pub fn pose_from_rows(m: &[[f64; 4]; 4]) -> Result<Pose, MatrixError> {
    for (row, values) in m.iter().enumerate() {
        for (col, v) in values.iter().enumerate() {
            if !v.is_finite() {
                return Err(MatrixError::NonFinite { row, col });
            }
        }
    }
    let bottom = m[3];
    if bottom[0].abs() > 1e-9
        || bottom[1].abs() > 1e-9
        || bottom[2].abs() > 1e-9
        || (bottom[3] - 1.0).abs() > 1e-9
    {
        return Err(MatrixError::BottomRow(bottom));
    }
    let r = Matrix3::new(
        m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
    );
    let deviation = (r.transpose() * r - Matrix3::identity()).abs().max();
    if deviation > RIGIDITY_TOLERANCE {
        return Err(MatrixError::NotOrthonormal { deviation });
    }
    let det = r.determinant();
    if det < 0.0 {
        return Err(MatrixError::Reflection { det });
    }
    // A matrix a little off orthonormal (JSON digits) gives a quaternion a
    // little off unit length, which nalgebra trusts: rotating by it then
    // scales points, and by a different amount than its matrix does (a
    // capture's handover pose was 1.3e-7 off, 3e-8 m apart on a scan).
    let rotation = UnitQuaternion::new_normalize(
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r)).into_inner(),
    );
    Ok(Isometry3::from_parts(
        Translation3::new(m[0][3], m[1][3], m[2][3]),
        rotation,
    ))
}

/// The row-major 4x4 form of a pose.
pub fn pose_to_rows(pose: &Pose) -> [[f64; 4]; 4] {
    let h: Matrix4<f64> = pose.to_homogeneous();
    let mut rows = [[0.0; 4]; 4];
    for (r, row) in rows.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            // Keep files readable: no "1e-17" noise where a value is zero.
            let x = h[(r, c)];
            *v = if x.abs() < 1e-15 { 0.0 } else { x };
        }
    }
    rows
}

/// Serde wrapper storing a [`Pose`] as a validated row-major 4x4 matrix.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RigidTransform(pub Pose);

impl RigidTransform {
    pub fn identity() -> Self {
        RigidTransform(Pose::identity())
    }
}

impl From<Pose> for RigidTransform {
    fn from(p: Pose) -> Self {
        RigidTransform(p)
    }
}

impl Serialize for RigidTransform {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        pose_to_rows(&self.0).serialize(s)
    }
}

impl<'de> Deserialize<'de> for RigidTransform {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let rows = <[[f64; 4]; 4]>::deserialize(d)?;
        pose_from_rows(&rows)
            .map(RigidTransform)
            .map_err(serde::de::Error::custom)
    }
}

/// Camera-to-world pose of a camera at `eye` looking at `target`, in OpenCV
/// axes (x right, y down, z forward). `up` is the world direction that should
/// appear upwards in the image.
pub fn look_at(eye: &Point3<f64>, target: &Point3<f64>, up: &Vector3<f64>) -> Pose {
    let forward = (target - eye).normalize();
    let mut right = forward.cross(up);
    if right.norm() < 1e-9 {
        // Looking straight along `up`: any perpendicular will do.
        right = forward.cross(&Vector3::x());
        if right.norm() < 1e-9 {
            right = forward.cross(&Vector3::y());
        }
    }
    let right = right.normalize();
    let down = forward.cross(&right);
    let r = Matrix3::from_columns(&[right, down, forward]);
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    Isometry3::from_parts(Translation3::new(eye.x, eye.y, eye.z), rotation)
}

/// Angle (radians) and translation distance (metres) between two poses.
pub fn pose_difference(a: &Pose, b: &Pose) -> (f64, f64) {
    let delta = a.inverse() * b;
    (delta.rotation.angle(), delta.translation.vector.norm())
}

/// A direction drawn uniformly from the unit sphere (by rejection from the
/// cube, away from the centre where normalising would lose precision).
pub fn random_unit_vector(rng: &mut impl rand::Rng) -> Vector3<f64> {
    loop {
        let v = Vector3::new(
            rng.random::<f64>() * 2.0 - 1.0,
            rng.random::<f64>() * 2.0 - 1.0,
            rng.random::<f64>() * 2.0 - 1.0,
        );
        if v.norm() > 0.1 && v.norm() <= 1.0 {
            return v.normalize();
        }
    }
}

/// The rotation by `angle` radians about the line through `centre` along
/// `axis`.
pub fn rotation_about(
    centre: &Point3<f64>,
    axis: &nalgebra::Unit<Vector3<f64>>,
    angle: f64,
) -> Pose {
    let about_origin = Isometry3::from_parts(
        Translation3::identity(),
        UnitQuaternion::from_axis_angle(axis, angle),
    );
    let to_centre = Isometry3::translation(centre.x, centre.y, centre.z);
    to_centre * about_origin * to_centre.inverse()
}

/// Builds a rotation from orthonormal column vectors (x, y, z axes of the
/// rotated frame expressed in the parent frame).
pub fn rotation_from_axes(
    x: Vector3<f64>,
    y: Vector3<f64>,
    z: Vector3<f64>,
) -> UnitQuaternion<f64> {
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::from_columns(
        &[x, y, z],
    )))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;

    #[test]
    fn random_unit_vectors_are_unit_and_cover_the_sphere_evenly() {
        use rand::SeedableRng;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let n = 20_000;
        let (mut mean, mut upper) = (Vector3::zeros(), 0usize);
        for _ in 0..n {
            let v = random_unit_vector(&mut rng);
            assert!((v.norm() - 1.0).abs() < 1e-12);
            mean += v / n as f64;
            // A uniform direction's z is uniform on [-1, 1] (Archimedes).
            upper += usize::from(v.z > 0.5);
        }
        assert!(mean.norm() < 0.03, "{mean:?}");
        let share = upper as f64 / n as f64;
        assert!((share - 0.25).abs() < 0.015, "{share}");
    }

    #[test]
    fn rows_round_trip() {
        let pose = Isometry3::new(Vector3::new(0.1, -0.2, 0.3), Vector3::new(0.2, 0.5, -1.0));
        let back = pose_from_rows(&pose_to_rows(&pose)).unwrap();
        let (angle, dist) = pose_difference(&pose, &back);
        assert!(angle < 1e-12 && dist < 1e-12);
    }

    #[test]
    fn matrices_slightly_off_orthonormal_give_unit_rotations() {
        // Rows rounded to 7 digits, as a JSON file may hold them.
        let pose = Isometry3::new(Vector3::new(0.1, -0.2, 0.3), Vector3::new(0.2, 0.5, -1.0));
        let rows = pose_to_rows(&pose).map(|row| row.map(|v| (v * 1e7).round() / 1e7));
        let back = pose_from_rows(&rows).unwrap();
        assert!((back.rotation.quaternion().norm() - 1.0).abs() < 1e-15);
        // Its quaternion and its matrix move points alike.
        let p = Point3::new(0.7, -0.4, 1.1);
        let by_matrix = back.rotation.to_rotation_matrix() * p;
        assert!((back.rotation * p - by_matrix).norm() < 1e-15);
        assert!(pose_difference(&back, &pose).0 < 1e-6);
    }

    #[test]
    fn rotation_about_a_line_keeps_the_line_and_turns_the_rest() {
        let centre = Point3::new(1.0, 2.0, 3.0);
        let axis = nalgebra::Unit::new_normalize(Vector3::z());
        let turn = rotation_about(&centre, &axis, FRAC_PI_2);
        let on_line = Point3::new(1.0, 2.0, 7.0);
        assert!((turn * on_line - on_line).norm() < 1e-12);
        // One unit along x from the line goes one unit along y.
        let off = turn * Point3::new(2.0, 2.0, 3.0);
        assert!((off - Point3::new(1.0, 3.0, 3.0)).norm() < 1e-12);
    }

    #[test]
    fn rejects_bad_matrices() {
        let mut m = pose_to_rows(&Pose::identity());
        m[1][2] = f64::NAN;
        assert_eq!(
            pose_from_rows(&m),
            Err(MatrixError::NonFinite { row: 1, col: 2 })
        );
        let mut m = pose_to_rows(&Pose::identity());
        m[0][0] = 2.0;
        assert!(matches!(
            pose_from_rows(&m),
            Err(MatrixError::NotOrthonormal { .. })
        ));
        let mut m = pose_to_rows(&Pose::identity());
        m[2][2] = -1.0;
        assert!(matches!(
            pose_from_rows(&m),
            Err(MatrixError::Reflection { .. })
        ));
        let mut m = pose_to_rows(&Pose::identity());
        m[3][0] = 0.5;
        assert!(matches!(pose_from_rows(&m), Err(MatrixError::BottomRow(_))));
    }

    #[test]
    fn look_at_points_z_forward_and_y_down() {
        let eye = Point3::new(1.0, 0.0, 0.5);
        let target = Point3::new(0.0, 0.0, 0.5);
        let pose = look_at(&eye, &target, &Vector3::z());
        let forward = pose.rotation * Vector3::z();
        let down = pose.rotation * Vector3::y();
        assert!((forward - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-12);
        assert!((down - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        // The target projects onto the optical axis.
        let in_camera = pose.inverse() * target;
        assert!(in_camera.x.abs() < 1e-12 && in_camera.y.abs() < 1e-12 && in_camera.z > 0.0);
        let _ = FRAC_PI_2;
    }
}
