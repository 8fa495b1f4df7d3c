//! Point-cloud preprocessing with Open3D's semantics where users compare:
//! voxel downsampling (per-voxel means, voxel grid anchored half a voxel
//! below the minimum bound), normals by PCA over hybrid radius/k neighbours,
//! consistent orientation (Hoppe et al. 1992: propagate along a minimum
//! spanning tree of the k-NN graph, seeded outwards from the centroid),
//! statistical outlier removal and DBSCAN.

use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use rayon::prelude::*;

use crate::PointCloud;
use crate::grid::hybrid_search;
use crate::neighbors::Neighbors;

/// Averages the points (and colours, normals) that fall in each voxel of
/// `voxel` size. Output is ordered by voxel index, so it is deterministic.
pub fn voxel_downsample(cloud: &PointCloud, voxel: f64) -> PointCloud {
    if cloud.is_empty() || voxel.is_nan() || voxel <= 0.0 {
        return cloud.clone();
    }
    let mut lo = cloud.points[0];
    for p in &cloud.points {
        lo = lo.inf(p);
    }
    let origin = lo.coords - Vector3::repeat(0.5 * voxel);
    #[derive(Default)]
    struct Acc {
        p: Vector3<f64>,
        c: [f64; 3],
        n: Vector3<f64>,
        count: usize,
    }
    let mut voxels: HashMap<[i64; 3], Acc> = HashMap::new();
    for (i, p) in cloud.points.iter().enumerate() {
        let r = (p.coords - origin) / voxel;
        let key = [r.x.floor() as i64, r.y.floor() as i64, r.z.floor() as i64];
        let a = voxels.entry(key).or_default();
        a.p += p.coords;
        if cloud.has_colors() {
            for k in 0..3 {
                a.c[k] += cloud.colors[i][k] as f64;
            }
        }
        if cloud.has_normals() {
            a.n += cloud.normals[i];
        }
        a.count += 1;
    }
    let mut keys: Vec<[i64; 3]> = voxels.keys().copied().collect();
    keys.sort_unstable();
    let mut out = PointCloud::default();
    for key in keys {
        let a = &voxels[&key];
        let n = a.count as f64;
        out.points.push((a.p / n).into());
        if cloud.has_colors() {
            out.colors.push(a.c.map(|c| (c / n) as f32));
        }
        if cloud.has_normals() {
            let m = a.n.norm();
            out.normals.push(if m > 0.0 { a.n / m } else { a.n });
        }
    }
    out
}

/// Normal of a neighbourhood: the eigenvector of the smallest eigenvalue of
/// its covariance; `None` with fewer than three points.
fn pca_normal(points: &[nalgebra::Point3<f64>], indices: &[(usize, f64)]) -> Option<Vector3<f64>> {
    if indices.len() < 3 {
        return None;
    }
    let n = indices.len() as f64;
    let mean: Vector3<f64> = indices
        .iter()
        .map(|&(i, _)| points[i].coords)
        .sum::<Vector3<f64>>()
        / n;
    let mut cov = Matrix3::zeros();
    for &(i, _) in indices {
        let d = points[i].coords - mean;
        cov += d * d.transpose();
    }
    let eig = SymmetricEigen::new(cov / n);
    let k = eig.eigenvalues.imin();
    Some(eig.eigenvectors.column(k).into_owned())
}

/// Estimates normals from at most `max_nn` neighbours within `radius`, then
/// orients them consistently (see [`orient_normals`]).
pub fn estimate_normals(cloud: &mut PointCloud, radius: f64, max_nn: usize) {
    let normals = hybrid_search(&cloud.points, radius, max_nn, |_, neighbours| {
        pca_normal(&cloud.points, neighbours).unwrap_or_else(Vector3::z)
    });
    cloud.normals = normals;
    orient_normals(cloud, 10);
}

#[derive(PartialEq)]
struct Edge {
    cost: f64,
    from: usize,
    to: usize,
}
impl Eq for Edge {}
impl Ord for Edge {
    fn cmp(&self, o: &Self) -> Ordering {
        // Min-heap on cost, ties by index for determinism.
        o.cost
            .total_cmp(&self.cost)
            .then_with(|| o.to.cmp(&self.to))
            .then_with(|| o.from.cmp(&self.from))
    }
}
impl PartialOrd for Edge {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}

/// Orients normals consistently: in each connected part of the k-NN graph,
/// the point farthest from the centroid gets an outward normal, and the
/// orientation spreads along the minimum spanning tree with edge cost
/// 1 − |n_i·n_j| (Hoppe et al.), flipping where neighbours disagree.
pub fn orient_normals(cloud: &mut PointCloud, k: usize) {
    let n = cloud.len();
    if n == 0 || !cloud.has_normals() {
        return;
    }
    let nn = Neighbors::new(&cloud.points);
    let graph: Vec<Vec<usize>> = cloud
        .points
        .par_iter()
        .map(|p| nn.knn(p, k + 1).into_iter().map(|(i, _)| i).collect())
        .collect();
    // Make the graph symmetric so the tree can reach every neighbour.
    let mut adjacency: Vec<Vec<usize>> = graph.clone();
    for (i, list) in graph.iter().enumerate() {
        for &j in list {
            if j != i {
                adjacency[j].push(i);
            }
        }
    }
    let centroid = cloud.centroid();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| {
        (cloud.points[b] - centroid)
            .norm_squared()
            .total_cmp(&(cloud.points[a] - centroid).norm_squared())
            .then(a.cmp(&b))
    });
    let mut visited = vec![false; n];
    for &seed in &order {
        if visited[seed] {
            continue;
        }
        if cloud.normals[seed].dot(&(cloud.points[seed] - centroid)) < 0.0 {
            cloud.normals[seed] = -cloud.normals[seed];
        }
        visited[seed] = true;
        let mut heap = BinaryHeap::new();
        let push = |heap: &mut BinaryHeap<Edge>,
                    normals: &[Vector3<f64>],
                    from: usize,
                    adjacency: &[Vec<usize>],
                    visited: &[bool]| {
            for &to in &adjacency[from] {
                if !visited[to] {
                    heap.push(Edge {
                        cost: 1.0 - normals[from].dot(&normals[to]).abs(),
                        from,
                        to,
                    });
                }
            }
        };
        push(&mut heap, &cloud.normals, seed, &adjacency, &visited);
        while let Some(Edge { from, to, .. }) = heap.pop() {
            if visited[to] {
                continue;
            }
            visited[to] = true;
            if cloud.normals[from].dot(&cloud.normals[to]) < 0.0 {
                cloud.normals[to] = -cloud.normals[to];
            }
            push(&mut heap, &cloud.normals, to, &adjacency, &visited);
        }
    }
}

/// Indices of the points whose mean distance to their `k` nearest
/// neighbours is at most the cloud's mean plus `std_ratio` standard
/// deviations (Open3D's `remove_statistical_outlier`).
pub fn statistical_inliers(cloud: &PointCloud, k: usize, std_ratio: f64) -> Vec<usize> {
    if cloud.len() <= k {
        return (0..cloud.len()).collect();
    }
    let nn = Neighbors::new(&cloud.points);
    let mean_d: Vec<f64> = cloud
        .points
        .par_iter()
        .map(|p| {
            let r = nn.knn(p, k + 1);
            r.iter().skip(1).map(|(_, d2)| d2.sqrt()).sum::<f64>() / k as f64
        })
        .collect();
    let m = mean_d.iter().sum::<f64>() / mean_d.len() as f64;
    let var = mean_d.iter().map(|d| (d - m).powi(2)).sum::<f64>() / (mean_d.len() - 1) as f64;
    let limit = m + std_ratio * var.sqrt();
    (0..cloud.len()).filter(|&i| mean_d[i] <= limit).collect()
}

/// DBSCAN clustering (Ester et al. 1996) as Open3D's `cluster_dbscan`:
/// label per point, −1 for noise, clusters numbered in order of discovery.
pub fn dbscan(cloud: &PointCloud, eps: f64, min_points: usize) -> Vec<i32> {
    let n = cloud.len();
    let nn = Neighbors::new(&cloud.points);
    let neighbours: Vec<Vec<usize>> = cloud
        .points
        .par_iter()
        .map(|p| nn.within(p, eps).into_iter().map(|(i, _)| i).collect())
        .collect();
    const UNSEEN: i32 = -2;
    let mut labels = vec![UNSEEN; n];
    let mut cluster = 0;
    for i in 0..n {
        if labels[i] != UNSEEN {
            continue;
        }
        if neighbours[i].len() < min_points {
            labels[i] = -1;
            continue;
        }
        labels[i] = cluster;
        let mut stack: Vec<usize> = neighbours[i].clone();
        while let Some(j) = stack.pop() {
            if labels[j] == -1 {
                labels[j] = cluster;
            }
            if labels[j] != UNSEEN {
                continue;
            }
            labels[j] = cluster;
            if neighbours[j].len() >= min_points {
                stack.extend_from_slice(&neighbours[j]);
            }
        }
        cluster += 1;
    }
    labels
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    fn sphere(n: usize, r: f64) -> PointCloud {
        // Fibonacci sphere.
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let points = (0..n)
            .map(|i| {
                let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
                let rr = (1.0 - y * y).sqrt();
                let t = golden * i as f64;
                Point3::new(r * rr * t.cos(), r * y, r * rr * t.sin())
            })
            .collect();
        PointCloud {
            points,
            ..Default::default()
        }
    }

    #[test]
    fn normals_of_a_sphere_point_outwards() {
        let mut c = sphere(2000, 0.05);
        estimate_normals(&mut c, 0.01, 30);
        for (p, n) in c.points.iter().zip(&c.normals) {
            let radial = p.coords.normalize();
            assert!(n.dot(&radial) > 0.98, "{n} at {p}");
        }
    }

    #[test]
    fn voxel_downsample_averages() {
        let c = PointCloud {
            points: vec![
                Point3::new(0.0, 0.0, 0.0),
                Point3::new(0.2, 0.0, 0.0),
                Point3::new(5.0, 0.0, 0.0),
            ],
            colors: vec![[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]],
            normals: vec![],
        };
        let d = voxel_downsample(&c, 1.0);
        assert_eq!(d.len(), 2);
        assert!((d.points[0].x - 0.1).abs() < 1e-12);
        assert_eq!(d.colors[0], [0.5, 0.0, 0.5]);
    }

    #[test]
    fn outliers_and_clusters() {
        let mut c = sphere(500, 0.05);
        c.points.push(Point3::new(1.0, 1.0, 1.0));
        let inliers = statistical_inliers(&c, 20, 2.0);
        assert!(!inliers.contains(&500));
        assert!(inliers.len() >= 490);
        let mut two = sphere(300, 0.05);
        two.extend(
            &sphere(300, 0.05).transformed(&omniscan_core::Pose::translation(1.0, 0.0, 0.0)),
        );
        two.points.push(Point3::new(0.5, 0.0, 0.0));
        let labels = dbscan(&two, 0.02, 5);
        assert_eq!(labels[0], 0);
        assert_eq!(labels[300], 1);
        assert_eq!(labels[600], -1);
        assert!(labels[..300].iter().all(|&l| l == 0) && labels[300..600].iter().all(|&l| l == 1));
    }
}
