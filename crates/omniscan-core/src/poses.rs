//! Pose processing (paper, "Pose Processing" and "Aligning the scans").
//!
//! The object is reconstructed in the frame of the gripper that holds it. For
//! image i with holding-gripper pose T_i (gripper to world) and the fixed
//! camera T_c (camera to world), the camera pose in the object's frame is
//! T_ic = T_i⁻¹·T_c. A right-arm image is brought into the left scan's frame
//! by the right-to-left transform; the robot's estimate of it is the handover
//! transform T_lh⁻¹·T_rh, which ICP later refines.

use crate::capture::{Arm, Capture};
use crate::geometry::Pose;

/// T_ic = T_i⁻¹·T_c: the camera's pose in the holding gripper's frame.
pub fn camera_to_object(gripper_to_world: &Pose, camera_to_world: &Pose) -> Pose {
    gripper_to_world.inverse() * camera_to_world
}

/// T_lh⁻¹·T_rh: the handover estimate of the transform that maps the right
/// gripper's frame (the right scan) into the left gripper's frame (the left scan).
pub fn handover_right_to_left(left_gripper_to_world: &Pose, right_gripper_to_world: &Pose) -> Pose {
    left_gripper_to_world.inverse() * right_gripper_to_world
}

/// A camera of the training set: which frame, and where the camera is in the
/// reconstruction frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraView {
    /// Index into the capture's `frames`.
    pub frame_index: usize,
    pub arm: Arm,
    /// Camera-to-reconstruction-frame pose, OpenCV axes.
    pub camera_to_object: Pose,
}

/// Which frames a reconstruction uses, and in which frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ViewSet {
    /// One arm's frames, in that arm's gripper frame (capture_L or capture_R).
    Arm(Arm),
    /// Both arms in the left gripper's frame, right frames mapped by the given
    /// right-to-left transform (capture_merge).
    Merged { right_to_left: Pose },
}

/// The capture's recorded handover estimate T_lh⁻¹·T_rh (right gripper's
/// frame to the left's).
pub fn handover_estimate(capture: &Capture) -> Pose {
    let h = &capture.file.handover;
    handover_right_to_left(&h.left_gripper_to_world.0, &h.right_gripper_to_world.0)
}

impl ViewSet {
    /// Both arms merged with the robot's handover estimate T_lh⁻¹·T_rh.
    pub fn merged_from_handover(capture: &Capture) -> ViewSet {
        ViewSet::Merged {
            right_to_left: handover_estimate(capture),
        }
    }
}

/// Camera poses for the frames of `set`, in capture order.
pub fn camera_views(capture: &Capture, set: ViewSet) -> Vec<CameraView> {
    let camera = capture.camera_to_world();
    capture
        .file
        .frames
        .iter()
        .enumerate()
        .filter_map(|(frame_index, frame)| {
            let own = camera_to_object(&frame.gripper_to_world.0, &camera);
            let camera_to_object = match set {
                ViewSet::Arm(arm) if arm == frame.arm => own,
                ViewSet::Arm(_) => return None,
                ViewSet::Merged { right_to_left } => match frame.arm {
                    Arm::Left => own,
                    Arm::Right => right_to_left * own,
                },
            };
            Some(CameraView {
                frame_index,
                arm: frame.arm,
                camera_to_object,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::pose_difference;
    use nalgebra::{Isometry3, Point3, Vector3};

    fn pose(t: [f64; 3], axis_angle: [f64; 3]) -> Pose {
        Isometry3::new(Vector3::from(t), Vector3::from(axis_angle))
    }

    #[test]
    fn camera_to_object_closed_form() {
        // Gripper rotated 90° about world z and shifted; camera at the world origin.
        let gripper = pose([1.0, 0.0, 0.0], [0.0, 0.0, std::f64::consts::FRAC_PI_2]);
        let camera = Pose::identity();
        let t_ic = camera_to_object(&gripper, &camera);
        // The camera centre (world origin) seen from the gripper: world (0,0,0)
        // is at gripper-frame (0, 1, 0) because the gripper x axis points along world y.
        let centre = t_ic * Point3::origin();
        assert!(
            (centre - Point3::new(0.0, 1.0, 0.0)).norm() < 1e-12,
            "{centre}"
        );
        // A world point projects identically whether through world or object frames.
        let p_world = Point3::new(0.3, -0.2, 2.0);
        let p_object = gripper.inverse() * p_world;
        let via_world = camera.inverse() * p_world;
        let via_object = t_ic.inverse() * p_object;
        assert!((via_world - via_object).norm() < 1e-12);
    }

    #[test]
    fn handover_transform_maps_right_frame_to_left_frame() {
        let t_lh = pose([0.4, 0.05, 0.3], [0.1, -0.4, 1.2]);
        let t_rh = pose([0.42, -0.03, 0.31], [-0.7, 0.2, 2.5]);
        let right_to_left = handover_right_to_left(&t_lh, &t_rh);
        // A point fixed in the world at handover, in each gripper frame:
        let p_world = Point3::new(0.41, 0.0, 0.33);
        let in_left = t_lh.inverse() * p_world;
        let in_right = t_rh.inverse() * p_world;
        assert!((right_to_left * in_right - in_left).norm() < 1e-12);
        // And a right camera pose mapped into the left frame equals the camera
        // pose computed as if the left gripper still held the object.
        let camera = pose([1.0, 0.0, 0.4], [0.0, -1.5, 0.0]);
        let merged = right_to_left * camera_to_object(&t_rh, &camera);
        let direct = camera_to_object(&t_lh, &camera);
        let (angle, dist) = pose_difference(&merged, &direct);
        assert!(angle < 1e-12 && dist < 1e-12);
    }
}
