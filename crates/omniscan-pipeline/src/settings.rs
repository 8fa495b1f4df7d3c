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
