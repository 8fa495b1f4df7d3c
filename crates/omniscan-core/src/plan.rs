//! The scan plan (paper, "Scan Trajectory" and "Bi-Manual Handover"): the
//! holding gripper rotates its wrist through `wrist_angles` evenly spaced
//! angles about its own z-axis at each of `latitudes` latitudes, evenly
//! spaced from `latitude_min` to `latitude_max` (-10° to 70° in the paper),
//! with the object held at a fixed point in front of one fixed camera.
//!
//! Conventions. World: the robot base frame, x forward (towards the camera),
//! y to the robot's left, z up, the table top at z = 0. Gripper (TCP) frame:
//! origin midway between the finger pads, z the approach direction (wrist to
//! fingertips), x the closing direction of the fingers. The latitude is the
//! elevation of the direction from the object to the camera above the
//! gripper's x-y plane: 90° looks straight at the fingertips, negative values
//! look from the wrist side, where the arm starts to hide the object. The arm
//! reaches in from its own side (+y for the left arm), so the approach axis
//! points across the camera's view.

use nalgebra::{Point3, Translation3, Vector3};
use serde::{Deserialize, Serialize};

use crate::camera::Intrinsics;
use crate::capture::{Arm, TrajectoryIndex};
use crate::geometry::{Pose, RigidTransform, look_at, rotation_from_axes};

/// Where the rig's parts are and how the trajectory is sampled.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ScanPlanConfig {
    /// Number of wrist angles per latitude (paper: 20).
    pub wrist_angles: u32,
    /// Number of latitudes (paper: 5).
    pub latitudes: u32,
    /// Lowest latitude, radians (paper: -10°).
    pub latitude_min_rad: f64,
    /// Highest latitude, radians (paper: 70°).
    pub latitude_max_rad: f64,
    /// Where the TCP holds the object during the scan, world frame, metres.
    pub scan_point_m: [f64; 3],
    /// Distance from the camera to the scan point, metres.
    pub camera_distance_m: f64,
    /// Elevation of the camera above the scan point's horizontal plane, radians.
    pub camera_elevation_rad: f64,
    /// Horizontal field of view of the camera, radians.
    pub camera_fov_x_rad: f64,
}

impl Default for ScanPlanConfig {
    fn default() -> Self {
        ScanPlanConfig {
            wrist_angles: 20,
            latitudes: 5,
            latitude_min_rad: (-10f64).to_radians(),
            latitude_max_rad: 70f64.to_radians(),
            scan_point_m: [0.42, 0.0, 0.32],
            camera_distance_m: 0.40,
            camera_elevation_rad: 12f64.to_radians(),
            camera_fov_x_rad: 42f64.to_radians(),
        }
    }
}

/// One pose of the plan.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PlannedPose {
    pub arm: Arm,
    #[serde(flatten)]
    pub trajectory: TrajectoryIndex,
    /// T_i: gripper (TCP) to world, metres.
    pub gripper_to_world: RigidTransform,
}

/// The most poses one arm's scan may have.
const MAX_POSES_PER_ARM: u32 = 10_000;

impl ScanPlanConfig {
    pub fn validate(&self) -> Result<(), String> {
        if self.wrist_angles == 0 || self.latitudes == 0 {
            return Err("the scan needs at least one wrist angle and one latitude".into());
        }
        // The paper's scan is 100 poses an arm; 10⁸ (a typo) ran the machine
        // out of memory planning them.
        let poses = self.wrist_angles.checked_mul(self.latitudes);
        if poses.is_none_or(|n| n > MAX_POSES_PER_ARM) {
            return Err(format!(
                "{} wrist angles x {} latitudes is more than {MAX_POSES_PER_ARM} poses an arm",
                self.wrist_angles, self.latitudes
            ));
        }
        let lat_ok = |v: f64| v.is_finite() && v.abs() < std::f64::consts::FRAC_PI_2;
        if !lat_ok(self.latitude_min_rad) || !lat_ok(self.latitude_max_rad) {
            return Err("latitudes must lie strictly between -90° and 90°".into());
        }
        if self.latitude_min_rad > self.latitude_max_rad {
            return Err("latitude_min must not exceed latitude_max".into());
        }
        if !(self.camera_distance_m > 0.05 && self.camera_distance_m <= 10.0) {
            return Err(format!(
                "camera distance {} m is outside 0.05-10 m (an in-hand object 10 m away spans a few pixels)",
                self.camera_distance_m
            ));
        }
        if !(self.camera_fov_x_rad > 0.05 && self.camera_fov_x_rad < 3.0) {
            return Err("camera field of view must be between 3° and 170°".into());
        }
        Ok(())
    }

    pub fn scan_point(&self) -> Point3<f64> {
        Point3::from(self.scan_point_m)
    }

    /// T_c: the fixed camera, in front of the robot looking back at the scan point.
    pub fn camera_to_world(&self) -> Pose {
        let p = self.scan_point();
        let (s, c) = self.camera_elevation_rad.sin_cos();
        let eye = p + self.camera_distance_m * Vector3::new(c, 0.0, s);
        look_at(&eye, &p, &Vector3::z())
    }

    pub fn intrinsics(&self, width: u32, height: u32) -> Intrinsics {
        Intrinsics::from_horizontal_fov(width, height, self.camera_fov_x_rad)
    }

    /// Latitude of index `j`, radians.
    pub fn latitude(&self, j: u32) -> f64 {
        if self.latitudes <= 1 {
            self.latitude_min_rad
        } else {
            self.latitude_min_rad
                + (self.latitude_max_rad - self.latitude_min_rad) * j as f64
                    / (self.latitudes - 1) as f64
        }
    }

    /// Wrist angle of index `k`, radians.
    pub fn wrist_angle(&self, k: u32) -> f64 {
        std::f64::consts::TAU * k as f64 / self.wrist_angles as f64
    }

    /// Unit direction from the scan point to the camera, world frame.
    fn direction_to_camera(&self) -> Vector3<f64> {
        (self.camera_to_world().translation.vector - self.scan_point().coords).normalize()
    }

    /// Direction the arm's approach axis points at latitude 0: across the
    /// view, away from the arm's own side.
    fn side(&self, arm: Arm) -> Vector3<f64> {
        let u = self.direction_to_camera();
        let across = match arm {
            Arm::Left => -Vector3::y(),
            Arm::Right => Vector3::y(),
        };
        (across - u * across.dot(&u)).normalize()
    }

    /// Gripper pose that shows the camera the held object from `latitude`
    /// and `wrist_angle` (both radians), with the TCP at `tcp`.
    pub fn gripper_pose(
        &self,
        arm: Arm,
        latitude: f64,
        wrist_angle: f64,
        tcp: &Point3<f64>,
    ) -> Pose {
        let u = self.direction_to_camera();
        let s = self.side(arm);
        let (sin_lat, cos_lat) = latitude.sin_cos();
        let z = sin_lat * u + cos_lat * s;
        let a = cos_lat * u - sin_lat * s;
        let b = z.cross(&a);
        let (sin_w, cos_w) = wrist_angle.sin_cos();
        let x = cos_w * a - sin_w * b;
        let y = sin_w * a + cos_w * b;
        Pose::from_parts(Translation3::from(tcp.coords), rotation_from_axes(x, y, z))
    }

    /// The scan trajectory of one arm, latitude by latitude.
    pub fn trajectory(&self, arm: Arm) -> Vec<PlannedPose> {
        let tcp = self.scan_point();
        let mut poses = Vec::with_capacity((self.latitudes * self.wrist_angles) as usize);
        for j in 0..self.latitudes {
            for k in 0..self.wrist_angles {
                let (latitude, wrist) = (self.latitude(j), self.wrist_angle(k));
                poses.push(PlannedPose {
                    arm,
                    trajectory: TrajectoryIndex {
                        wrist_index: k,
                        latitude_index: j,
                        wrist_angle_rad: wrist,
                        latitude_rad: latitude,
                    },
                    gripper_to_world: self.gripper_pose(arm, latitude, wrist, &tcp).into(),
                });
            }
        }
        poses
    }

    /// T_lh: where the left gripper presents the object for the handover:
    /// at the scan point, approach axis horizontal, fingers closing towards
    /// the camera so the right gripper can reach the far side.
    pub fn left_handover_pose(&self) -> Pose {
        let x = Vector3::z();
        let z = self.side(Arm::Left);
        let y = z.cross(&x);
        Pose::from_parts(
            Translation3::from(self.scan_point().coords),
            rotation_from_axes(x, y, z),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_trajectory_counts_and_latitudes() {
        let plan = ScanPlanConfig::default();
        let poses = plan.trajectory(Arm::Left);
        assert_eq!(poses.len(), 100);
        let lats: Vec<f64> = (0..5).map(|j| plan.latitude(j).to_degrees()).collect();
        for (got, want) in lats.iter().zip([-10.0, 10.0, 30.0, 50.0, 70.0]) {
            assert!((got - want).abs() < 1e-9, "{lats:?}");
        }
    }

    #[test]
    fn plans_out_of_range_are_errors() {
        assert!(ScanPlanConfig::default().validate().is_ok());
        let bad = [
            ScanPlanConfig {
                wrist_angles: 100_000,
                latitudes: 1000,
                ..Default::default()
            },
            ScanPlanConfig {
                wrist_angles: u32::MAX,
                latitudes: 2,
                ..Default::default()
            },
            ScanPlanConfig {
                camera_distance_m: f64::NAN,
                ..Default::default()
            },
            ScanPlanConfig {
                camera_distance_m: 1e9,
                ..Default::default()
            },
        ];
        for plan in bad {
            assert!(plan.validate().is_err(), "{plan:?}");
        }
    }

    #[test]
    fn camera_sees_the_gripper_from_the_planned_latitude_and_wrist_angle() {
        let plan = ScanPlanConfig::default();
        let camera = plan.camera_to_world().translation.vector;
        for arm in [Arm::Left, Arm::Right] {
            for p in plan.trajectory(arm) {
                let pose = p.gripper_to_world.0;
                // Direction to the camera in the gripper frame.
                let d = (pose.inverse() * nalgebra::Point3::from(camera))
                    .coords
                    .normalize();
                let latitude = d.z.asin();
                let wrist = d.y.atan2(d.x).rem_euclid(std::f64::consts::TAU);
                assert!((latitude - p.trajectory.latitude_rad).abs() < 1e-9);
                let want = p
                    .trajectory
                    .wrist_angle_rad
                    .rem_euclid(std::f64::consts::TAU);
                let diff = (wrist - want).abs();
                assert!(
                    diff < 1e-9 || (diff - std::f64::consts::TAU).abs() < 1e-9,
                    "{wrist} vs {want}"
                );
                // The approach axis points away from the arm's own side.
                let z = pose.rotation * Vector3::z();
                match arm {
                    Arm::Left => assert!(z.y < 0.0),
                    Arm::Right => assert!(z.y > 0.0),
                }
            }
        }
    }
}
