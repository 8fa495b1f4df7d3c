//! Simulating a bimanual in-hand scan (the paper's "Bimanual scanning"):
//! a real textured mesh held by a real gripper model, turned through the
//! scan plan by each arm in turn, rendered with depth and ground truth.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use omniscan_core::plan::ScanPlanConfig;
use omniscan_sim::{SimConfig, SimSummary, Simulation};

use crate::Progress;
use crate::settings::{RobotArgs, default_from_flags};

/// The scan trajectory: wrist angles at each of several latitudes.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PlanSettings {
    /// Wrist angles per latitude.
    #[arg(long, default_value_t = ScanPlanConfig::default().wrist_angles)]
    pub wrist_angles: u32,
    /// Number of latitudes.
    #[arg(long, default_value_t = ScanPlanConfig::default().latitudes)]
    pub latitudes: u32,
    /// Lowest latitude, degrees.
    #[arg(long, default_value_t = -10.0, allow_hyphen_values = true)]
    pub latitude_min_deg: f64,
    /// Highest latitude, degrees.
    #[arg(long, default_value_t = 70.0, allow_hyphen_values = true)]
    pub latitude_max_deg: f64,
}

default_from_flags!(PlanSettings);

impl PlanSettings {
    pub fn config(&self) -> ScanPlanConfig {
        ScanPlanConfig {
            wrist_angles: self.wrist_angles,
            latitudes: self.latitudes,
            latitude_min_rad: self.latitude_min_deg.to_radians(),
            latitude_max_rad: self.latitude_max_deg.to_radians(),
            ..ScanPlanConfig::default()
        }
    }
}

/// Everything `sim` can be told besides the output folder.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SimulateSettings {
    /// `builtin:NAME` (flashlight, t_connector, wire_connector, l_bracket, remote) or a mesh file (.obj/.stl/.ply).
    #[arg(long, default_value_t = SimConfig::default().object)]
    pub object: String,
    /// Metres per mesh unit (0.01 for a mesh in centimetres).
    #[arg(long)]
    pub object_scale: Option<f64>,
    /// Image width, pixels.
    #[arg(long, default_value_t = SimConfig::default().width)]
    pub width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = SimConfig::default().height)]
    pub height: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// A planted defect: geometric:dent|bump|cut,size_mm=S or visual:scratch|tape,size_mm=S.
    #[arg(long)]
    pub defect: Option<String>,
    /// Rotation of the object at handover, degrees (the recorded handover stays as planned).
    #[arg(long, default_value_t = 0.0)]
    pub slip_deg: f64,
    /// Translation of the object at handover, millimetres.
    #[arg(long, default_value_t = 0.0)]
    pub slip_mm: f64,
    /// Supersampling per axis (2 = 4 samples per pixel).
    #[arg(long, default_value_t = SimConfig::default().supersample)]
    pub supersample: u32,
    /// Sensor depth noise at 1 m, millimetres (grows with distance squared); 0 for clean depth.
    #[arg(long, default_value_t = 2.0)]
    pub depth_noise_mm_at_1m: f64,
    /// Directory with the YuMi gripper meshes (e.g. ../shared/data/grippers/yumi).
    #[arg(long, conflicts_with = "robot")]
    pub gripper_dir: Option<PathBuf>,
    /// Camera distance from the object, metres (default: from the object's size).
    #[arg(long)]
    pub camera_distance_m: Option<f64>,
    /// Skip the empty-gripper calibration pass.
    #[arg(long)]
    pub no_empty_pass: bool,
    /// Calibration error of the recorded gripper poses: a seeded random rotation per frame of this RMS angle, degrees (images keep the true pose, recorded in each frame's gt).
    #[arg(long, default_value_t = 0.0)]
    pub pose_noise_deg: f64,
    /// The same for translation: RMS offset per frame, millimetres.
    #[arg(long, default_value_t = 0.0)]
    pub pose_noise_mm: f64,
    #[command(flatten)]
    #[serde(flatten)]
    pub robot: RobotArgs,
    #[command(flatten)]
    #[serde(flatten)]
    pub plan: PlanSettings,
}

default_from_flags!(SimulateSettings);

impl SimulateSettings {
    /// The simulator's configuration, in metres and radians.
    pub fn config(&self) -> SimConfig {
        SimConfig {
            object: self.object.clone(),
            object_scale: self.object_scale,
            width: self.width,
            height: self.height,
            seed: self.seed,
            defect: self.defect.clone(),
            slip_deg: self.slip_deg,
            slip_mm: self.slip_mm,
            supersample: self.supersample,
            depth_noise_m_at_1m: self.depth_noise_mm_at_1m * 1e-3,
            plan: self.plan.config(),
            gripper_dir: self.gripper_dir.clone(),
            camera_distance_m: self.camera_distance_m,
            empty_pass: !self.no_empty_pass,
            pose_noise_deg: self.pose_noise_deg,
            pose_noise_mm: self.pose_noise_mm,
            robot: self.robot.spec(),
        }
    }
}

/// Simulates a scan into the capture folder `out` (resumable: frames
/// already written are kept).
pub fn simulate(
    settings: &SimulateSettings,
    out: &Path,
    progress: &dyn Progress,
) -> Result<SimSummary> {
    simulate_config(settings.config(), out, progress)
}

/// [`simulate`] from the simulator's own configuration.
pub fn simulate_config(
    config: SimConfig,
    out: &Path,
    progress: &dyn Progress,
) -> Result<SimSummary> {
    let sim = Simulation::new(config).context("cannot set up the simulation")?;
    let _lock = omniscan_core::lock::OutputLock::folder(out, "sim")?;
    progress.start("simulating", sim.frames.len() as u64, "frames");
    let summary = sim
        .run(out, &|done, _| progress.set(done as u64))
        .with_context(|| format!("simulation into {} failed", out.display()))?;
    progress.finish();
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_simulators() {
        let s = SimulateSettings::default();
        let c = SimConfig::default();
        let made = s.config();
        assert_eq!(made.object, c.object);
        assert_eq!(
            (made.width, made.height, made.supersample),
            (c.width, c.height, c.supersample)
        );
        assert_eq!(made.depth_noise_m_at_1m, c.depth_noise_m_at_1m);
        assert_eq!(made.plan.latitude_min_rad, c.plan.latitude_min_rad);
        assert_eq!(made.plan.latitude_max_rad, c.plan.latitude_max_rad);
        assert_eq!(made.empty_pass, c.empty_pass);
    }
}
