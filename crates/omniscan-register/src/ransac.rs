//! RANSAC over putative correspondences, with Open3D's cheap pruning checks
//! (edge-length ratio, distance) and its early stop: after each batch of
//! trials the number needed for `confidence` is re-estimated from the best
//! inlier ratio so far. Trials are seeded by their index, so the result does
//! not depend on threads.

use nalgebra::Point3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::icp::kabsch;
use omniscan_core::Pose;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RansacSettings {
    pub max_iterations: usize,
    pub confidence: f64,
    /// A correspondence is an inlier when the transformed source point lies this close to its target.
    pub distance: f64,
    /// Edge-length checker: sample edges in the two clouds must agree within this ratio.
    pub edge_ratio: f64,
    pub seed: u64,
}

impl RansacSettings {
    pub fn with_distance(distance: f64) -> RansacSettings {
        RansacSettings {
            max_iterations: 100_000,
            confidence: 0.999,
            distance,
            edge_ratio: 0.9,
            seed: 0,
        }
    }
}

/// Best transform and its inlier correspondences; `None` with fewer than three correspondences.
pub fn ransac(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    settings: &RansacSettings,
) -> Option<(Pose, Vec<usize>)> {
    let n = source.len().min(target.len());
    if n < 3 {
        return None;
    }
    let d2 = settings.distance * settings.distance;
    let score = |pose: &Pose| -> (usize, f64) {
        let mut count = 0;
        let mut sum = 0.0;
        for i in 0..n {
            let e = (pose * source[i] - target[i]).norm_squared();
            if e <= d2 {
                count += 1;
                sum += e;
            }
        }
        (
            count,
            if count > 0 {
                sum / count as f64
            } else {
                f64::INFINITY
            },
        )
    };
    let trial = |t: usize| -> Option<(usize, f64, Pose)> {
        let mut rng = ChaCha8Rng::seed_from_u64(
            settings.seed ^ (t as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15),
        );
        let mut idx = [0usize; 3];
        for k in 0..3 {
            loop {
                let c = rng.random_range(0..n);
                if !idx[..k].contains(&c) {
                    idx[k] = c;
                    break;
                }
            }
        }
        for a in 0..3 {
            for b in a + 1..3 {
                let es = (source[idx[a]] - source[idx[b]]).norm();
                let et = (target[idx[a]] - target[idx[b]]).norm();
                if es < settings.edge_ratio * et || et < settings.edge_ratio * es {
                    return None;
                }
            }
        }
        let pose = kabsch(&idx.map(|i| (source[i], target[i])));
        if idx
            .iter()
            .any(|&i| (pose * source[i] - target[i]).norm_squared() > d2)
        {
            return None;
        }
        let (count, mse) = score(&pose);
        Some((count, mse, pose))
    };
    let mut best: Option<(usize, f64, Pose)> = None;
    let mut done = 0;
    let mut needed = settings.max_iterations;
    const BATCH: usize = 1024;
    while done < needed.min(settings.max_iterations) {
        let results: Vec<Option<(usize, f64, Pose)>> =
            (done..done + BATCH).into_par_iter().map(trial).collect();
        for r in results.into_iter().flatten() {
            let better = match &best {
                None => true,
                Some((c, m, _)) => r.0 > *c || (r.0 == *c && r.1 < *m),
            };
            if better {
                best = Some(r);
            }
        }
        done += BATCH;
        if let Some((count, _, _)) = &best {
            let w = *count as f64 / n as f64;
            let p = w.powi(3);
            if p >= 1.0 {
                break;
            }
            if p > 0.0 {
                needed = ((1.0 - settings.confidence).ln() / (1.0 - p).ln()).ceil() as usize;
            }
        }
    }
    let (_, _, pose) = best?;
    let inliers: Vec<usize> = (0..n)
        .filter(|&i| (pose * source[i] - target[i]).norm_squared() <= d2)
        .collect();
    let refit = kabsch(
        &inliers
            .iter()
            .map(|&i| (source[i], target[i]))
            .collect::<Vec<_>>(),
    );
    Some((refit, inliers))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn finds_the_transform_among_outliers() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let truth = Pose::new(Vector3::new(0.1, 0.2, -0.3), Vector3::new(-0.5, 2.5, 1.0));
        let (mut s, mut t) = (Vec::new(), Vec::new());
        for i in 0..300 {
            let p = Point3::new(
                rng.random::<f64>(),
                rng.random::<f64>(),
                rng.random::<f64>(),
            );
            s.push(p);
            t.push(if i % 5 == 0 {
                truth * p
            } else {
                Point3::new(rng.random(), rng.random(), rng.random()) * 3.0
            });
        }
        let (pose, inliers) = ransac(&s, &t, &RansacSettings::with_distance(0.01)).unwrap();
        assert_eq!(inliers.len(), 60);
        let (a, d) = omniscan_core::geometry::pose_difference(&pose, &truth);
        assert!(a < 1e-6 && d < 1e-6);
        assert!(ransac(&s[..2], &t[..2], &RansacSettings::with_distance(0.01)).is_none());
    }
}
