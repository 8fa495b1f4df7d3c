//! Conformance on the real meshes in `../shared` (scanned objects, the YuMi
//! gripper). Run with `cargo test -- --include-ignored`; the path comes from
//! `OMNISCAN_SHARED` or defaults to the `shared` folder beside the checkout.

use std::path::PathBuf;

use omniscan_core::plan::ScanPlanConfig;
use omniscan_sim::raster::Label;
use omniscan_sim::simulate::Layers;
use omniscan_sim::{SimConfig, Simulation};

fn shared() -> PathBuf {
    std::env::var_os("OMNISCAN_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"))
}

#[test]
#[ignore = "needs ../shared"]
fn every_shared_object_loads_renders_and_is_grasped_or_refused_clearly() {
    let objects = shared().join("data/objects");
    let gripper = shared().join("data/grippers/yumi");
    let mut ran = 0;
    for entry in std::fs::read_dir(&objects).expect("shared objects") {
        let dir = entry.unwrap().path();
        let source = std::fs::read_to_string(dir.join("SOURCE.md")).unwrap();
        let scale = if source.contains("centimetres") {
            0.01
        } else {
            1.0
        };
        let config = SimConfig {
            object: dir.join("model.obj").display().to_string(),
            object_scale: Some(scale),
            width: 160,
            height: 120,
            supersample: 1,
            gripper_dir: Some(gripper.clone()),
            plan: ScanPlanConfig {
                wrist_angles: 2,
                latitudes: 1,
                ..ScanPlanConfig::default()
            },
            empty_pass: false,
            ..SimConfig::default()
        };
        let extent = {
            let o =
                omniscan_sim::simulate::load_object(&config.object, config.object_scale).unwrap();
            let (lo, hi) = o.mesh.bounds();
            let e = hi - lo;
            e.x.min(e.y).min(e.z)
        };
        match Simulation::new(config) {
            Ok(sim) => {
                for frame in &sim.frames {
                    let view = sim.render_frame(frame, Layers::ALL, 1);
                    let object = view.labels.iter().filter(|&&l| l == Label::Object).count();
                    assert!(
                        object > 50,
                        "{}: object barely visible ({object} px)",
                        dir.display()
                    );
                    assert!(view.labels.contains(&Label::Gripper));
                }
                ran += 1;
            }
            // Only objects wider than the gripper's 50 mm opening in every direction may be refused.
            Err(e) => assert!(
                extent > 0.046 && e.to_string().contains("no antipodal grasp"),
                "{}: {e}",
                dir.display()
            ),
        }
    }
    assert!(ran >= 8, "only {ran} shared objects simulated");
}
