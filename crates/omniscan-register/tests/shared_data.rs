//! Conformance on real data from `../shared` (`OMNISCAN_SHARED`): the
//! colored RGB-D fragment, a 3DMatch PCD and the Omni-Scan splat models.
//! Run with `cargo test -- --include-ignored`; the full 20-rotation figures
//! come from `omniscan bench registration`.

use std::path::PathBuf;

use nalgebra::{Translation3, Unit, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use omniscan_core::Pose;
use omniscan_core::geometry::pose_difference;
use omniscan_register::PointCloud;
use omniscan_register::cloud::read_cloud;
use omniscan_register::global::{GlobalSettings, global_registration, median_spacing};
use omniscan_register::icp::{Criteria, Estimator, Kernel, Target, icp};
use omniscan_register::preprocess::estimate_normals;

fn shared() -> PathBuf {
    std::env::var_os("OMNISCAN_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"))
}

fn halves(cloud: &PointCloud, seed: u64) -> (PointCloud, PointCloud) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (a, b): (Vec<usize>, Vec<usize>) = (0..cloud.len()).partition(|_| rng.random_bool(0.5));
    (cloud.select(&a), cloud.select(&b))
}

fn random_pose(rng: &mut ChaCha8Rng, shift: f64) -> Pose {
    let axis = Vector3::new(
        rng.random::<f64>() - 0.5,
        rng.random::<f64>() - 0.5,
        rng.random::<f64>() - 0.5,
    );
    let t = Vector3::new(
        rng.random::<f64>() - 0.5,
        rng.random::<f64>() - 0.5,
        rng.random::<f64>() - 0.5,
    ) * shift;
    Pose::from_parts(
        Translation3::from(t),
        UnitQuaternion::from_axis_angle(
            &Unit::new_normalize(axis),
            rng.random::<f64>() * std::f64::consts::PI,
        ),
    )
}

#[test]
#[ignore = "needs ../shared"]
fn colored_icp_on_frag_115_halves() {
    let frag = read_cloud(&shared().join("data/registration/frag_115.ply")).unwrap();
    assert!(frag.has_colors() && frag.len() > 60_000);
    let c = frag.centroid();
    let frag = frag.transformed(&Pose::translation(-c.x, -c.y, -c.z));
    let spacing = median_spacing(&frag);
    let (mut target, source) = halves(&frag, 1);
    let perturb = Pose::from_parts(
        Translation3::new(0.01, 0.0, 0.0),
        UnitQuaternion::from_axis_angle(
            &Unit::new_normalize(Vector3::new(0.3, -0.5, 0.81)),
            10f64.to_radians(),
        ),
    );
    let source = source.transformed(&perturb);
    estimate_normals(&mut target, 4.0 * spacing, 30);
    let tt = Target::new(&target);
    let crit = Criteria::default();
    let colored = icp(
        &source,
        &tt,
        0.016,
        &Pose::identity(),
        Estimator::COLORED,
        Kernel::L2,
        &crit,
    )
    .unwrap();
    let plane = icp(
        &source,
        &tt,
        0.016,
        &Pose::identity(),
        Estimator::PointToPlane,
        Kernel::L2,
        &crit,
    )
    .unwrap();
    let (rot, trans) = pose_difference(&colored.transformation, &perturb.inverse());
    // Open3D 0.20 reaches the same transform on these inputs (omniscan bench
    // registration compares them): 0.025° and 0.6 mm here.
    assert!(
        rot.to_degrees() < 0.05 && trans < 0.001,
        "{:.4}° {:.2} mm",
        rot.to_degrees(),
        trans * 1e3
    );
    assert!(colored.fitness > 0.999);
    // Geometry alone slides along the fragment's flat parts; colour pins it.
    let (plane_rot, _) = pose_difference(&plane.transformation, &perturb.inverse());
    assert!(plane_rot > 10.0 * rot);
}

#[test]
#[ignore = "needs ../shared"]
fn pcd_and_every_splat_model_load() {
    let pcd = read_cloud(&shared().join("data/registration/cloud_bin_0.pcd")).unwrap();
    assert!(pcd.len() > 1000, "{}", pcd.len());
    let dir = shared().join("data/real-splats");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let cloud = read_cloud(&path).unwrap();
        assert!(
            cloud.len() > 2000 && cloud.has_colors(),
            "{}: {} points",
            path.display(),
            cloud.len()
        );
        n += 1;
    }
    assert_eq!(n, 14);
}

/// Global registration of `trials` random rotations of each file's halves
/// (paths under `data/`): the trials and the misses (error over 0.5°).
fn global_misses(rng: &mut ChaCha8Rng, files: &[&str], trials: u64) -> (usize, Vec<String>) {
    let mut count = 0;
    let mut missed = Vec::new();
    for file in files {
        let cloud = read_cloud(&shared().join("data").join(file)).unwrap();
        let (target, half) = halves(&cloud, 3);
        for trial in 0..trials {
            let truth = random_pose(rng, cloud.extent());
            let source = half.transformed(&truth.inverse());
            let settings = GlobalSettings {
                seed: trial,
                ..GlobalSettings::default()
            };
            let r = global_registration(&source, &target, &settings).unwrap();
            let (rot, _) = pose_difference(&r.best.registration.transformation, &truth);
            count += 1;
            if rot.to_degrees() > 0.5 {
                missed.push(format!("{file} trial {trial}: {:.2}°", rot.to_degrees()));
            }
        }
    }
    (count, missed)
}

#[test]
#[ignore = "needs ../shared"]
fn global_registration_of_real_halves() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let files = [
        "registration/frag_115.ply",
        "real-splats/expo.ply",
        "real-splats/remote_merge.ply",
        "real-splats/garden_stake.ply",
    ];
    let (trials, missed) = global_misses(&mut rng, &files, 2);
    let good = trials - missed.len();
    assert!(
        good >= trials - 1,
        "{good} of {trials} within 0.5°: {missed:?}"
    );
}

/// Parts whose feature hypotheses land degrees off, or on a half-turned
/// twin (a flat card, an elongated opener, a bracket): before the wide first
/// ICP pass of each hypothesis 6 of these 30 trials missed 0.5°.
#[test]
#[ignore = "needs ../shared"]
fn global_registration_converges_from_hypotheses_degrees_off() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let files = [
        "real-splats/postcard.ply",
        "real-splats/wine_opener.ply",
        "real-splats/l_bracket.ply",
    ];
    let (_, missed) = global_misses(&mut rng, &files, 10);
    assert!(missed.len() <= 1, "missed 0.5°: {missed:?}");
}

/// The final refinement of a global registration must not lock a fused
/// RGB-D fragment (points on a lattice, normals given) a lattice step off:
/// point to point ended 8.5 mm off on these halves, point to plane 0.5 mm.
#[test]
#[ignore = "needs ../shared"]
fn global_registration_of_a_fragment_with_normals_ends_on_it() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let cloud = read_cloud(&shared().join("data/registration/frag_115.ply")).unwrap();
    assert!(cloud.has_normals());
    let (target, half) = halves(&cloud, 3);
    for trial in 0..2 {
        let truth = random_pose(&mut rng, cloud.extent());
        let source = half.transformed(&truth.inverse());
        let settings = GlobalSettings {
            seed: trial,
            ..GlobalSettings::default()
        };
        let r = global_registration(&source, &target, &settings).unwrap();
        let (rot, trans) = pose_difference(&r.best.registration.transformation, &truth);
        assert!(
            rot.to_degrees() < 0.05 && trans < 0.002,
            "trial {trial}: {:.4}° {:.2} mm",
            rot.to_degrees(),
            trans * 1e3
        );
    }
}
