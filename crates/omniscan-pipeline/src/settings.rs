//! Settings defaults written once: every settings struct derives
//! `clap::Args`, whose `default_value_t` attributes are the one place a
//! default is written, and its `Default` parses an empty command line.

/// The settings `T` with every field at its documented default: an empty
/// command line parsed by `T`'s own flags. Panics only if `T` has a
/// required field, which the settings' `defaults_parse` tests rule out.
pub fn defaults<T: clap::Args + clap::FromArgMatches>() -> T {
    let command = T::augment_args(clap::Command::new("defaults").no_binary_name(true));
    let matches = command
        .try_get_matches_from(std::iter::empty::<String>())
        .unwrap_or_else(|e| panic!("settings with a required field have no default: {e}"));
    T::from_arg_matches(&matches).unwrap_or_else(|e| panic!("settings defaults: {e}"))
}

/// `impl Default` by [`defaults`] for settings structs.
macro_rules! default_from_flags {
    ($($t:ty),* $(,)?) => {$(
        impl Default for $t {
            fn default() -> Self {
                $crate::settings::defaults()
            }
        }
    )*};
}
pub(crate) use default_from_flags;

/// Another robot's gripper, the flags `sim` and `import ros2` share.
#[derive(clap::Args, Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct RobotArgs {
    /// Another robot's gripper: its URDF (meshes STL, OBJ or PLY; package:// paths resolve the ROS way). The capture records it, so `mask` draws the same gripper. Default: the ABB YuMi. docs/simulate.md
    #[arg(long, group = "robot", requires = "gripper_root")]
    pub robot_urdf: Option<std::path::PathBuf>,
    /// Another robot's gripper from a MuJoCo MJCF file (bodies, hinge and slide joints, equality couplings and connect loops, actuators).
    #[arg(long, group = "robot", requires = "gripper_root")]
    pub robot_mjcf: Option<std::path::PathBuf>,
    /// The link (MJCF: body) whose subtree is the gripper.
    #[arg(long, requires = "robot")]
    pub gripper_root: Option<String>,
    /// The tool (TCP) frame: a link (or MJCF site) fixed to the gripper root, z the approach, x the closing direction, its origin between the pads.
    #[arg(long, requires = "robot", conflicts_with = "tcp_offset_m")]
    pub tcp_link: Option<String>,
    /// The TCP as an offset from the gripper root's origin in its axes, metres: X,Y,Z.
    #[arg(
        long,
        requires = "robot",
        value_delimiter = ',',
        allow_negative_numbers = true
    )]
    pub tcp_offset_m: Option<Vec<f64>>,
}

impl RobotArgs {
    /// The robot the flags name, its description's path made absolute (a
    /// capture records it and is read from elsewhere); `None` for the YuMi.
    pub fn spec(&self) -> Option<omniscan_core::capture::RobotSpec> {
        let path = self.robot_urdf.as_ref().or(self.robot_mjcf.as_ref())?;
        Some(omniscan_core::capture::RobotSpec {
            description: std::path::absolute(path)
                .unwrap_or_else(|_| path.clone())
                .display()
                .to_string(),
            gripper_root: self.gripper_root.clone().unwrap_or_default(),
            tcp_link: self.tcp_link.clone(),
            tcp_offset_m: self.tcp_offset_m.as_ref().map(|v| match v.as_slice() {
                [x, y, z] => [*x, *y, *z],
                // Refused by the gripper's loader, which names it.
                _ => [f64::NAN; 3],
            }),
        })
    }
}

#[cfg(test)]
mod tests {
    use crate::align::{AlignSettings, Method};
    use crate::evaluate::EvalSettings;
    use crate::geometry::{AssetSettings, MeshSettings};
    use crate::inspect::{InspectionSettings, MakeCopySettings};
    use crate::mask::{GripperMethod, MaskingSettings};
    use crate::render::RenderSettings;
    use crate::simulate::{PlanSettings, SimulateSettings};
    use crate::train::TrainSettings;
    use crate::twin::TwinSettings;

    /// Every settings struct has a default (no required field), and the
    /// default is the documented one, here where the docs state it.
    #[test]
    fn defaults_parse() {
        let twin = TwinSettings::default();
        assert_eq!(
            (twin.steps, twin.downscale, twin.checkpoint_every),
            (3000, 2, 500)
        );
        let align = AlignSettings::default();
        assert_eq!(
            (align.method, align.iterations, align.downscale),
            (Method::Auto, 30, 2)
        );
        let eval = EvalSettings::default();
        assert_eq!((eval.downscale, eval.held_out_every), (1, 0));
        let mask = MaskingSettings::default();
        assert_eq!(mask.gripper, GripperMethod::Kinematic);
        assert_eq!(
            (mask.non_robot_threshold_mm, mask.non_gripper_threshold),
            (8.0, 0.89)
        );
        assert_eq!(PlanSettings::default().wrist_angles, 20);
        let mesh = MeshSettings::default();
        assert_eq!(
            (mesh.faces, mesh.views, mesh.view_px, mesh.texture_px),
            (20_000, 64, 320, 2048)
        );
        assert_eq!(
            (mesh.voxel_mm, mesh.scale_m_per_unit, mesh.inside_vote),
            (None, 1.0, 0.65)
        );
        let asset = AssetSettings::default();
        assert_eq!(
            (
                asset.hulls,
                asset.decomposition_resolution,
                asset.density_kg_m3,
                asset.mass_kg
            ),
            (16, 64, None, None)
        );
        let from_json: AssetSettings =
            serde_json::from_str(r#"{"faces": 100, "hulls": 4}"#).unwrap();
        assert_eq!((from_json.mesh.faces, from_json.hulls), (100, 4));
        let _ = (
            TrainSettings::default(),
            RenderSettings::default(),
            InspectionSettings::default(),
            MakeCopySettings::default(),
            SimulateSettings::default(),
        );
    }

    /// A settings file names only what it changes.
    #[test]
    fn settings_read_from_json_keep_the_other_defaults() {
        let twin: TwinSettings = serde_json::from_str(r#"{"steps": 100}"#).unwrap();
        assert_eq!(
            twin,
            TwinSettings {
                steps: 100,
                ..TwinSettings::default()
            }
        );
        let back: TwinSettings =
            serde_json::from_str(&serde_json::to_string(&twin).unwrap()).unwrap();
        assert_eq!(back, twin);
    }
}
