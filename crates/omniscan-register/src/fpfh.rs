//! Fast Point Feature Histograms (Rusu, Blodow, Beetz, ICRA 2009) computed as
//! Open3D 0.20's `compute_fpfh_feature` does, so features agree with what
//! users know: 33 bins (α, φ, θ blocks of 11); each point's SPFH adds
//! 100/(k) per neighbour to each block; FPFH = SPFH(p) + the neighbours'
//! SPFH weighted by 1/d² (squared distance) and rescaled to 100 per block,
//! so every row sums to 600.
//!
//! Also: nearest-neighbour matching in feature space, with the mutual filter.

use std::num::NonZero;
use std::sync::Arc;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use crate::PointCloud;
use crate::grid::hybrid_search;

/// One 33-bin histogram per point.
pub type Fpfh = [f32; 33];

/// (α, φ, θ) of a point pair, Open3D's `ComputePairFeatures`; `None` when degenerate.
fn pair_features(
    p1: &Point3<f64>,
    n1: &Vector3<f64>,
    p2: &Point3<f64>,
    n2: &Vector3<f64>,
) -> Option<[f64; 3]> {
    let mut d = p2 - p1;
    let len = d.norm();
    if len == 0.0 {
        return None;
    }
    let (a1, a2) = (n1.dot(&d) / len, n2.dot(&d) / len);
    let (u, w2, theta) = if a1.abs().acos() > a2.abs().acos() {
        d = -d;
        (*n2, *n1, -a2)
    } else {
        (*n1, *n2, a1)
    };
    let v = d.cross(&u);
    let vn = v.norm();
    if vn == 0.0 {
        return None;
    }
    let v = v / vn;
    let w = u.cross(&v);
    let phi = v.dot(&w2);
    let alpha = w.dot(&w2).atan2(u.dot(&w2));
    Some([alpha, phi, theta])
}

fn bin(value: f64, lo: f64, hi: f64) -> usize {
    ((11.0 * (value - lo) / (hi - lo)).floor() as i64).clamp(0, 10) as usize
}

/// FPFH features over at most `max_nn` neighbours within `radius`. The cloud
/// needs (consistently oriented) normals.
pub fn compute_fpfh(cloud: &PointCloud, radius: f64, max_nn: usize) -> Vec<Fpfh> {
    // Shared lists: the search hands its results over by copying them into
    // point order, which for a list is then one reference count.
    let neighbourhoods: Vec<Arc<[(usize, f64)]>> =
        hybrid_search(&cloud.points, radius, max_nn, |_, n| Arc::from(n));
    let spfh: Vec<[f64; 33]> = (0..cloud.len())
        .into_par_iter()
        .map(|i| {
            let mut h = [0.0; 33];
            let nbrs = &neighbourhoods[i];
            if nbrs.len() > 1 {
                let incr = 100.0 / (nbrs.len() - 1) as f64;
                for &(j, _) in nbrs.iter().skip(1) {
                    if let Some([alpha, phi, theta]) = pair_features(
                        &cloud.points[i],
                        &cloud.normals[i],
                        &cloud.points[j],
                        &cloud.normals[j],
                    ) {
                        h[bin(alpha, -std::f64::consts::PI, std::f64::consts::PI)] += incr;
                        h[11 + bin(phi, -1.0, 1.0)] += incr;
                        h[22 + bin(theta, -1.0, 1.0)] += incr;
                    }
                }
            }
            h
        })
        .collect();
    (0..cloud.len())
        .into_par_iter()
        .map(|i| {
            let nbrs = &neighbourhoods[i];
            let mut f = [0.0f64; 33];
            if nbrs.len() > 1 {
                let mut sums = [0.0; 3];
                for &(j, d2) in nbrs.iter().skip(1) {
                    if d2 == 0.0 {
                        continue;
                    }
                    for k in 0..33 {
                        let v = spfh[j][k] / d2;
                        sums[k / 11] += v;
                        f[k] += v;
                    }
                }
                for k in 0..33 {
                    if sums[k / 11] != 0.0 {
                        f[k] *= 100.0 / sums[k / 11];
                    }
                    f[k] += spfh[i][k];
                }
            }
            f.map(|v| v as f32)
        })
        .collect()
}

/// For each source feature, the index of its nearest target feature.
fn nearest_features(from: &[Fpfh], to: &[Fpfh]) -> Vec<usize> {
    if to.is_empty() {
        return vec![];
    }
    let tree: ImmutableKdTree<f32, 33> =
        ImmutableKdTree::new_from_slice(to).expect("non-empty feature set");
    from.par_iter()
        .map(|f| {
            tree.query(f)
                .nearest_n::<SquaredEuclidean<f32>>(NonZero::new(1).unwrap())
                .execute()[0]
                .item as usize
        })
        .collect()
}

/// Feature correspondences (source index, target index). With `mutual`, only
/// pairs that are each other's nearest neighbours are kept, unless fewer than
/// a tenth of the source points survive (Open3D's fallback).
pub fn match_features(source: &[Fpfh], target: &[Fpfh], mutual: bool) -> Vec<(usize, usize)> {
    let forward = nearest_features(source, target);
    let all: Vec<(usize, usize)> = forward.iter().copied().enumerate().collect();
    if !mutual {
        return all;
    }
    let backward = nearest_features(target, source);
    let kept: Vec<(usize, usize)> = all
        .iter()
        .copied()
        .filter(|&(i, j)| backward[j] == i)
        .collect();
    if (kept.len() as f64) < 0.1 * source.len() as f64 {
        all
    } else {
        kept
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::preprocess::estimate_normals;
    use omniscan_core::Pose;

    fn blob(n: usize) -> PointCloud {
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let points = (0..n)
            .map(|i| {
                let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
                let r = (1.0 - y * y).sqrt();
                let t = golden * i as f64;
                let bump = 1.0 + 0.3 * (3.0 * t).sin() * y + 0.2 * (2.0 * y).cos();
                Point3::new(bump * r * t.cos(), bump * y, bump * r * t.sin() * 0.7)
            })
            .collect();
        PointCloud {
            points,
            ..Default::default()
        }
    }

    #[test]
    fn rows_sum_to_600_and_are_invariant_to_rigid_motion() {
        let mut a = blob(1500);
        estimate_normals(&mut a, 0.2, 30);
        let t = Pose::new(Vector3::new(0.5, -2.0, 1.0), Vector3::new(1.0, 2.0, -0.5));
        let b = a.transformed(&t);
        let fa = compute_fpfh(&a, 0.5, 100);
        let fb = compute_fpfh(&b, 0.5, 100);
        for (x, y) in fa.iter().zip(&fb) {
            let sum: f32 = x.iter().sum();
            assert!((sum - 600.0).abs() < 1e-2, "{sum}");
            for k in 0..33 {
                assert!((x[k] - y[k]).abs() < 1e-2, "bin {k}: {} vs {}", x[k], y[k]);
            }
        }
        // Matching a cloud against its moved copy finds (mostly) the same points.
        let m = match_features(&fa, &fb, true);
        let right = m.iter().filter(|(i, j)| i == j).count();
        assert!(
            right as f64 > 0.8 * m.len() as f64,
            "{right} of {}",
            m.len()
        );
    }

    #[test]
    fn pair_features_of_a_known_pair() {
        // Normals both along z, points along x: θ = 0, φ = 0, α = 0.
        let f = pair_features(
            &Point3::origin(),
            &Vector3::z(),
            &Point3::new(1.0, 0.0, 0.0),
            &Vector3::z(),
        )
        .unwrap();
        assert!(f.iter().all(|v| v.abs() < 1e-12), "{f:?}");
        assert!(
            pair_features(
                &Point3::origin(),
                &Vector3::z(),
                &Point3::origin(),
                &Vector3::z()
            )
            .is_none()
        );
    }
}
