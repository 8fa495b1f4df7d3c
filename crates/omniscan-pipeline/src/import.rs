//! Recordings of real robots to captures: `omniscan import ros2` (a rosbag2
//! recording, MCAP or sqlite3; docs/ros2.md). The work is
//! [`omniscan_ros`]'s; this is the stage's entry with progress.

use std::path::Path;

use anyhow::Result;
pub use omniscan_ros::ImportReport;
use omniscan_ros::Ros2ImportSettings;
use serde::{Deserialize, Serialize};

use crate::Progress;
use crate::settings::{RobotArgs, default_from_flags};

/// How a ROS 2 bag becomes a capture: the recording's conventions
/// (docs/ros2.md) and the robot.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ImportSettings {
    #[command(flatten)]
    #[serde(flatten)]
    pub ros: Ros2ImportSettings,
    #[command(flatten)]
    #[serde(flatten)]
    pub robot: RobotArgs,
}

default_from_flags!(ImportSettings);

/// Imports the ROS 2 bag at `bag` into a new capture folder `out` (which
/// must not exist; it appears whole or not at all).
pub fn import_ros2(
    bag: &Path,
    out: &Path,
    settings: &ImportSettings,
    progress: &dyn Progress,
) -> Result<ImportReport> {
    // The robot's gripper is loaded first: a capture that names a
    // description the masks cannot use is not made. Its finger joints'
    // positions become openings through the openings measured on it.
    let gripper = match settings.robot.spec() {
        Some(spec) => Some((
            omniscan_sim::gripper::GripperModel::from_robot(&spec, Path::new("."))?,
            spec,
        )),
        None => None,
    };
    let opening_m = |joint: &str, position: f64| {
        let (model, _) = gripper.as_ref()?;
        model.robot()?.opening_at(joint, position)
    };
    let robot = gripper.as_ref().map(|(_, spec)| omniscan_ros::Robot {
        spec: spec.clone(),
        opening_m: &opening_m,
    });
    progress.start("reading the bag", 0, "images");
    // The library's errors name the bag, topic, frame and time already.
    let report = omniscan_ros::import_ros2(bag, out, &settings.ros, robot.as_ref(), &|images| {
        progress.set(images as u64)
    });
    progress.finish();
    Ok(report?)
}
