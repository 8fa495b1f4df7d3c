// Throw-away probe (not committed): times ICP on frag_115 halves as the bench does.
use nalgebra::{Translation3, Unit, UnitQuaternion, Vector3};
use omniscan_core::Pose;
use omniscan_register::cloud::read_cloud;
use omniscan_register::global::median_spacing;
use omniscan_register::icp::{Criteria, Estimator, Kernel, Target, icp};
use omniscan_register::preprocess::estimate_normals;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let frag = read_cloud(std::path::Path::new(&args[1])).unwrap();
    let which = args.get(2).map(|s| s.as_str()).unwrap_or("plane");
    let runs: usize = args.get(3).map(|s| s.parse().unwrap()).unwrap_or(20);
    let c = frag.centroid();
    let frag = frag.transformed(&Pose::translation(-c.x, -c.y, -c.z));
    let spacing = median_spacing(&frag);
    eprintln!("spacing {spacing}");
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let (a, b): (Vec<usize>, Vec<usize>) = (0..frag.len()).partition(|_| rng.random_bool(0.5));
    let mut target = frag.select(&a);
    let mut source = frag.select(&b);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
    let mut normal = || {
        let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    };
    for p in &mut source.points {
        *p += Vector3::new(normal(), normal(), normal()) * (0.5 * spacing);
    }
    let perturb = Pose::from_parts(
        Translation3::new(0.01, 0.0, 0.0),
        UnitQuaternion::from_axis_angle(
            &Unit::new_normalize(Vector3::new(0.3, -0.5, 0.81)),
            10f64.to_radians(),
        ),
    );
    let mut source = source.transformed(&perturb);
    estimate_normals(&mut target, 4.0 * spacing, 30);
    estimate_normals(&mut source, 4.0 * spacing, 30);
    let est = match which {
        "plane" => Estimator::PointToPlane,
        "icp" => Estimator::PointToPoint,
        _ => Estimator::COLORED,
    };
    let crit = Criteria {
        max_iteration: 30,
        ..Criteria::default()
    };
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..runs {
        let t = Instant::now();
        let r = icp(
            &source,
            &Target::new(&target),
            0.016,
            &Pose::identity(),
            est,
            Kernel::L2,
            &crit,
        )
        .unwrap();
        times.push(t.elapsed().as_secs_f64());
        if std::env::var("EACH").is_ok() {
            eprint!("{:.3} ", t.elapsed().as_secs_f64());
        }
        last = Some(r);
    }
    times.sort_by(f64::total_cmp);
    let r = last.unwrap();
    println!(
        "{which}: median {:.4} s min {:.4} fitness {:.6} rmse {:.6e} iters {}",
        times[runs / 2],
        times[0],
        r.fitness,
        r.inlier_rmse,
        r.iterations
    );
}
