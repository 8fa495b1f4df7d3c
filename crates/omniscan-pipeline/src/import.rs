//! Recordings of real robots to captures: `omniscan import ros2` (a rosbag2
//! recording, MCAP or sqlite3; docs/ros2.md). The work is
//! [`omniscan_ros`]'s; this is the stage's entry with progress.

use std::path::Path;

use anyhow::Result;
pub use omniscan_ros::{ImportReport, Ros2ImportSettings};

use crate::Progress;

/// Imports the ROS 2 bag at `bag` into a new capture folder `out` (which
/// must not exist; it appears whole or not at all).
pub fn import_ros2(
    bag: &Path,
    out: &Path,
    settings: &Ros2ImportSettings,
    progress: &dyn Progress,
) -> Result<ImportReport> {
    // The robot's gripper is loaded first: a capture that names a URDF
    // the masks cannot use is not made.
    if let Some(robot) = settings.robot() {
        omniscan_sim::gripper::GripperModel::from_robot(&robot, Path::new("."))?;
    }
    progress.start("reading the bag", 0, "images");
    // The library's errors name the bag, topic, frame and time already.
    let report =
        omniscan_ros::import_ros2(bag, out, settings, &|images| progress.set(images as u64));
    progress.finish();
    Ok(report?)
}
