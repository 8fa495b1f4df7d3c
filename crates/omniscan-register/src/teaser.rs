//! Robust registration from putative correspondences in the manner of
//! TEASER++ (Yang, Shi, Carlone, "TEASER: Fast and Certifiable Point Cloud
//! Registration", T-RO 2020), with scale fixed to 1:
//!
//! 1. pairwise consistency: correspondences i and j are compatible when the
//!    distance between the two source points and between the two target
//!    points differ by at most 2β (β = noise bound);
//! 2. inlier selection: a maximum clique of the compatibility graph, found
//!    by branch and bound with greedy-colouring bounds over a degeneracy
//!    ordering (the ideas of PMC), under a time limit, with a k-core greedy
//!    clique as the fallback (an exact clique can take minutes on real splat
//!    data);
//! 3. rotation: graduated non-convexity with a truncated least squares cost
//!    (GNC-TLS) over translation-invariant measurements (differences of
//!    consecutive clique members);
//! 4. translation: truncated least squares by adaptive voting, per component.
//!
//! Written here because no Rust crate offers it (TEASER++ is C++).

use std::time::{Duration, Instant};

use nalgebra::{Matrix3, Point3, Rotation3, SVD, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use omniscan_core::Pose;

/// A fixed-size bitset over graph vertices.
#[derive(Clone, PartialEq, Debug)]
pub struct Bitset(Vec<u64>);

impl Bitset {
    pub fn new(n: usize) -> Bitset {
        Bitset(vec![0; n.div_ceil(64)])
    }
    pub fn set(&mut self, i: usize) {
        self.0[i / 64] |= 1 << (i % 64);
    }
    pub fn clear(&mut self, i: usize) {
        self.0[i / 64] &= !(1 << (i % 64));
    }
    pub fn contains(&self, i: usize) -> bool {
        self.0[i / 64] & (1 << (i % 64)) != 0
    }
    pub fn is_empty(&self) -> bool {
        self.0.iter().all(|&w| w == 0)
    }
    pub fn count(&self) -> usize {
        self.0.iter().map(|w| w.count_ones() as usize).sum()
    }
    pub fn and(&self, other: &Bitset) -> Bitset {
        Bitset(self.0.iter().zip(&other.0).map(|(a, b)| a & b).collect())
    }
    pub fn and_not(&self, other: &Bitset) -> Bitset {
        Bitset(self.0.iter().zip(&other.0).map(|(a, b)| a & !b).collect())
    }
    pub fn first(&self) -> Option<usize> {
        self.0
            .iter()
            .enumerate()
            .find(|(_, w)| **w != 0)
            .map(|(k, w)| k * 64 + w.trailing_zeros() as usize)
    }
    pub fn iter(&self) -> impl Iterator<Item = usize> + '_ {
        self.0.iter().enumerate().flat_map(|(k, &w)| {
            let mut w = w;
            std::iter::from_fn(move || {
                if w == 0 {
                    return None;
                }
                let b = w.trailing_zeros() as usize;
                w &= w - 1;
                Some(k * 64 + b)
            })
        })
    }
}

/// An undirected graph as adjacency bitsets.
pub struct Graph {
    pub adjacency: Vec<Bitset>,
}

impl Graph {
    pub fn new(n: usize) -> Graph {
        Graph {
            adjacency: vec![Bitset::new(n); n],
        }
    }
    pub fn add_edge(&mut self, i: usize, j: usize) {
        self.adjacency[i].set(j);
        self.adjacency[j].set(i);
    }
    pub fn len(&self) -> usize {
        self.adjacency.len()
    }
    pub fn is_empty(&self) -> bool {
        self.adjacency.is_empty()
    }

    /// Core numbers and a degeneracy ordering (Batagelj-Zaversnik).
    pub fn cores(&self) -> (Vec<usize>, Vec<usize>) {
        let n = self.len();
        let mut degree: Vec<usize> = self.adjacency.iter().map(Bitset::count).collect();
        let max_degree = degree.iter().copied().max().unwrap_or(0);
        let mut buckets: Vec<Vec<usize>> = vec![Vec::new(); max_degree + 1];
        for (v, &d) in degree.iter().enumerate() {
            buckets[d].push(v);
        }
        let mut removed = vec![false; n];
        let mut core = vec![0; n];
        let mut order = Vec::with_capacity(n);
        let mut d = 0;
        while order.len() < n {
            // Lowest non-empty bucket; entries may be stale.
            d = d.min(max_degree);
            while d <= max_degree && buckets[d].is_empty() {
                d += 1;
            }
            let v = buckets[d].pop().unwrap();
            if removed[v] || degree[v] != d {
                continue;
            }
            removed[v] = true;
            core[v] = d;
            order.push(v);
            for u in self.adjacency[v].iter() {
                if !removed[u] && degree[u] > d {
                    degree[u] -= 1;
                    buckets[degree[u]].push(u);
                }
            }
            d = d.saturating_sub(1);
        }
        // Core numbers never decrease along the removal order.
        let mut running = 0;
        for &v in &order {
            running = running.max(core[v]);
            core[v] = running;
        }
        (core, order)
    }
}

/// A clique and whether it is proven maximum.
#[derive(Debug, Clone, PartialEq)]
pub struct Clique {
    pub vertices: Vec<usize>,
    pub exact: bool,
}

/// Greedy clique from the k-core structure: from each vertex, in decreasing
/// core number, add neighbours of highest core number while they fit.
fn greedy_clique(graph: &Graph, core: &[usize]) -> Vec<usize> {
    let mut by_core: Vec<usize> = (0..graph.len()).collect();
    by_core.sort_by(|&a, &b| core[b].cmp(&core[a]).then(a.cmp(&b)));
    let mut best: Vec<usize> = Vec::new();
    for &v in by_core.iter().take(200) {
        if core[v] < best.len() {
            break;
        }
        let mut clique = vec![v];
        let mut candidates = graph.adjacency[v].clone();
        loop {
            let next = candidates
                .iter()
                .filter(|&u| core[u] >= best.len())
                .max_by(|&a, &b| core[a].cmp(&core[b]).then(b.cmp(&a)));
            let Some(u) = next else { break };
            clique.push(u);
            candidates = candidates.and(&graph.adjacency[u]);
        }
        if clique.len() > best.len() {
            best = clique;
        }
    }
    best
}

struct Search<'a> {
    graph: &'a Graph,
    best: Vec<usize>,
    deadline: Instant,
    steps: u64,
    timed_out: bool,
}

impl Search<'_> {
    /// Greedy colouring of `p`: vertices in colour order with their colours.
    fn colour(&self, p: &Bitset) -> (Vec<usize>, Vec<usize>) {
        let mut uncoloured = p.clone();
        let mut order = Vec::new();
        let mut colours = Vec::new();
        let mut colour = 0;
        while !uncoloured.is_empty() {
            colour += 1;
            let mut q = uncoloured.clone();
            while let Some(v) = q.first() {
                uncoloured.clear(v);
                q.clear(v);
                q = q.and_not(&self.graph.adjacency[v]);
                order.push(v);
                colours.push(colour);
            }
        }
        (order, colours)
    }

    fn expand(&mut self, clique: &mut Vec<usize>, mut p: Bitset) {
        self.steps += 1;
        if self.steps.is_multiple_of(256) && Instant::now() > self.deadline {
            self.timed_out = true;
        }
        if self.timed_out {
            return;
        }
        let (order, colours) = self.colour(&p);
        for k in (0..order.len()).rev() {
            if clique.len() + colours[k] <= self.best.len() || self.timed_out {
                return;
            }
            let v = order[k];
            clique.push(v);
            let next = p.and(&self.graph.adjacency[v]);
            if next.is_empty() {
                if clique.len() > self.best.len() {
                    self.best = clique.clone();
                }
            } else {
                self.expand(clique, next);
            }
            clique.pop();
            p.clear(v);
        }
    }
}

/// A maximum clique, exact unless `time_limit` runs out (then the largest found).
pub fn max_clique(graph: &Graph, time_limit: Duration) -> Clique {
    if graph.is_empty() {
        return Clique {
            vertices: vec![],
            exact: true,
        };
    }
    let (core, order) = graph.cores();
    let mut search = Search {
        graph,
        best: greedy_clique(graph, &core),
        deadline: Instant::now() + time_limit,
        steps: 0,
        timed_out: false,
    };
    // Root at each vertex in degeneracy order, with the neighbours later in the order.
    let mut later = Bitset::new(graph.len());
    for &v in &order {
        later.set(v);
    }
    for &v in &order {
        later.clear(v);
        if core[v] < search.best.len() {
            continue;
        }
        let p = graph.adjacency[v].and(&later);
        let mut clique = vec![v];
        if p.is_empty() {
            if search.best.is_empty() {
                search.best = clique;
            }
            continue;
        }
        search.expand(&mut clique, p);
        if search.timed_out {
            break;
        }
    }
    let mut vertices = search.best;
    vertices.sort_unstable();
    Clique {
        vertices,
        exact: !search.timed_out,
    }
}

/// Settings of the robust solver (TEASER++'s parameter names).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TeaserSettings {
    /// β: bound on the noise of a correspondence, in the clouds' units.
    pub noise_bound: f64,
    pub cbar2: f64,
    pub rotation_gnc_factor: f64,
    pub rotation_max_iterations: usize,
    pub rotation_cost_threshold: f64,
    pub max_clique_time: Duration,
}

impl TeaserSettings {
    pub fn with_noise_bound(noise_bound: f64) -> TeaserSettings {
        TeaserSettings {
            noise_bound,
            cbar2: 1.0,
            rotation_gnc_factor: 1.4,
            rotation_max_iterations: 100,
            rotation_cost_threshold: 1e-6,
            max_clique_time: Duration::from_millis(500),
        }
    }
}

/// The solver's answer.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TeaserSolution {
    #[serde(skip)]
    pub pose: Pose,
    /// Indices of the correspondences in the maximum clique.
    pub clique: Vec<usize>,
    pub clique_exact: bool,
    /// Clique members also consistent with the estimated translation.
    pub inliers: Vec<usize>,
    /// At least three correspondences agree.
    pub valid: bool,
}

/// Weighted rotation aligning vectors `a` onto `b` (no translation).
fn weighted_rotation(a: &[Vector3<f64>], b: &[Vector3<f64>], w: &[f64]) -> Rotation3<f64> {
    let mut h = Matrix3::zeros();
    for ((x, y), &wi) in a.iter().zip(b).zip(w) {
        h += wi * x * y.transpose();
    }
    let svd = SVD::new(h, true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return Rotation3::identity();
    };
    let v = vt.transpose();
    let d = (v * u.transpose()).determinant().signum();
    Rotation3::from_matrix_unchecked(
        v * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * u.transpose(),
    )
}

/// GNC-TLS rotation from measurement pairs with noise bound `bound`.
fn gnc_tls_rotation(
    a: &[Vector3<f64>],
    b: &[Vector3<f64>],
    bound: f64,
    s: &TeaserSettings,
) -> Rotation3<f64> {
    let mut w = vec![1.0; a.len()];
    let bound2 = bound * bound * s.cbar2;
    let mut rotation = weighted_rotation(a, b, &w);
    let mut mu = 1.0;
    let mut previous_cost = f64::INFINITY;
    for iteration in 0..s.rotation_max_iterations {
        let r2: Vec<f64> = a
            .iter()
            .zip(b)
            .map(|(x, y)| (y - rotation * x).norm_squared())
            .collect();
        if iteration == 0 {
            let max_r2 = r2.iter().copied().fold(0.0, f64::max);
            mu = 1.0 / (2.0 * max_r2 / bound2 - 1.0);
            if mu <= 0.0 {
                // Every residual is within the bound already.
                break;
            }
        }
        let upper = (mu + 1.0) / mu * bound2;
        let lower = mu / (mu + 1.0) * bound2;
        for (wi, &r) in w.iter_mut().zip(&r2) {
            *wi = if r >= upper {
                0.0
            } else if r <= lower {
                1.0
            } else {
                (bound2 * mu * (mu + 1.0) / r).sqrt() - mu
            };
        }
        let cost: f64 = w.iter().zip(&r2).map(|(wi, r)| wi * r).sum();
        rotation = weighted_rotation(a, b, &w);
        if (cost - previous_cost).abs() < s.rotation_cost_threshold {
            break;
        }
        previous_cost = cost;
        mu *= s.rotation_gnc_factor;
    }
    rotation
}

/// Truncated least squares estimate of a scalar from values with a common
/// bound, by adaptive voting over the intervals' endpoints.
pub fn tls_scalar(values: &[f64], bound: f64, cbar2: f64) -> f64 {
    let n = values.len();
    if n == 0 {
        return 0.0;
    }
    let mut events: Vec<(f64, i32, f64)> = values
        .iter()
        .flat_map(|&x| [(x - bound, 1, x), (x + bound, -1, x)])
        .collect();
    events.sort_by(|a, b| a.0.total_cmp(&b.0).then(b.1.cmp(&a.1)));
    let (mut count, mut sum, mut sum2) = (0usize, 0.0, 0.0);
    let mut best = (f64::INFINITY, values[0]);
    for &(_, kind, x) in &events {
        if kind > 0 {
            count += 1;
            sum += x;
            sum2 += x * x;
        } else {
            count -= 1;
            sum -= x;
            sum2 -= x * x;
        }
        if count > 0 {
            let mean = sum / count as f64;
            let residual = (sum2 - count as f64 * mean * mean).max(0.0) / (bound * bound);
            let cost = residual + (n - count) as f64 * cbar2;
            if cost < best.0 {
                best = (cost, mean);
            }
        }
    }
    best.1
}

/// Solves for the rigid transform mapping `source[i]` onto `target[i]` for
/// the inlier correspondences.
pub fn teaser_solve(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    settings: &TeaserSettings,
) -> TeaserSolution {
    let n = source.len().min(target.len());
    let bound = 2.0 * settings.noise_bound * settings.cbar2.sqrt();
    let mut graph = Graph::new(n);
    for i in 0..n {
        for j in i + 1..n {
            let da = (source[j] - source[i]).norm();
            let db = (target[j] - target[i]).norm();
            if (da - db).abs() <= bound {
                graph.add_edge(i, j);
            }
        }
    }
    let clique = max_clique(&graph, settings.max_clique_time);
    let members = &clique.vertices;
    if members.len() < 3 {
        return TeaserSolution {
            pose: Pose::identity(),
            clique: members.clone(),
            clique_exact: clique.exact,
            inliers: vec![],
            valid: false,
        };
    }
    // Chain of translation-invariant measurements through the clique.
    let m = members.len();
    let a: Vec<Vector3<f64>> = (0..m)
        .map(|k| source[members[(k + 1) % m]] - source[members[k]])
        .collect();
    let b: Vec<Vector3<f64>> = (0..m)
        .map(|k| target[members[(k + 1) % m]] - target[members[k]])
        .collect();
    let rotation = gnc_tls_rotation(&a, &b, 2.0 * settings.noise_bound, settings);
    let per_axis = settings.noise_bound * settings.cbar2.sqrt();
    let offsets: Vec<Vector3<f64>> = members
        .iter()
        .map(|&i| target[i].coords - rotation * source[i].coords)
        .collect();
    let t = Vector3::from_fn(|axis, _| {
        tls_scalar(
            &offsets.iter().map(|o| o[axis]).collect::<Vec<_>>(),
            per_axis,
            settings.cbar2,
        )
    });
    let inliers: Vec<usize> = members
        .iter()
        .zip(&offsets)
        .filter(|(_, o)| (0..3).all(|k| (o[k] - t[k]).abs() <= per_axis))
        .map(|(&i, _)| i)
        .collect();
    let pose = Pose::from_parts(
        Translation3::from(t),
        UnitQuaternion::from_rotation_matrix(&rotation),
    );
    TeaserSolution {
        pose,
        clique: members.clone(),
        clique_exact: clique.exact,
        valid: inliers.len() >= 3,
        inliers,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn max_clique_on_known_graphs() {
        // A 6-clique hidden among 60 random vertices with sparse edges.
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut g = Graph::new(60);
        for i in 0..60 {
            for j in i + 1..60 {
                if rng.random::<f64>() < 0.1 {
                    g.add_edge(i, j);
                }
            }
        }
        let hidden = [3, 11, 17, 29, 41, 58];
        for (k, &i) in hidden.iter().enumerate() {
            for &j in &hidden[k + 1..] {
                g.add_edge(i, j);
            }
        }
        let c = max_clique(&g, Duration::from_secs(5));
        assert!(c.exact);
        assert_eq!(c.vertices, hidden.to_vec());
        // Every pair in the answer is adjacent.
        for &i in &c.vertices {
            for &j in &c.vertices {
                assert!(i == j || g.adjacency[i].contains(j));
            }
        }
        // A complete graph is its own maximum clique; an empty graph gives one vertex.
        let mut k5 = Graph::new(5);
        for i in 0..5 {
            for j in i + 1..5 {
                k5.add_edge(i, j);
            }
        }
        assert_eq!(max_clique(&k5, Duration::from_secs(1)).vertices.len(), 5);
        assert_eq!(
            max_clique(&Graph::new(4), Duration::from_secs(1))
                .vertices
                .len(),
            1
        );
    }

    #[test]
    fn core_numbers() {
        // A triangle with a pendant vertex: cores 2, 2, 2, 1.
        let mut g = Graph::new(4);
        g.add_edge(0, 1);
        g.add_edge(1, 2);
        g.add_edge(0, 2);
        g.add_edge(2, 3);
        let (core, order) = g.cores();
        assert_eq!(core, vec![2, 2, 2, 1]);
        assert_eq!(order[0], 3);
    }

    #[test]
    fn tls_scalar_ignores_outliers() {
        let mut v = vec![1.0, 1.01, 0.99, 1.02, 0.98];
        v.extend([5.0, -3.0, 7.0]);
        let est = tls_scalar(&v, 0.05, 1.0);
        assert!((est - 1.0).abs() < 1e-9, "{est}");
    }

    #[test]
    fn recovers_a_rotation_with_95_percent_outliers() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let truth = Pose::new(Vector3::new(0.3, -0.2, 0.5), Vector3::new(2.0, -1.0, 0.5));
        let mut src = Vec::new();
        let mut dst = Vec::new();
        for i in 0..400 {
            let p = Point3::new(
                rng.random::<f64>(),
                rng.random::<f64>(),
                rng.random::<f64>(),
            );
            src.push(p);
            if i % 20 == 0 {
                let noise = Vector3::new(
                    rng.random::<f64>() - 0.5,
                    rng.random::<f64>() - 0.5,
                    rng.random::<f64>() - 0.5,
                ) * 0.004;
                dst.push(truth * p + noise);
            } else {
                dst.push(
                    Point3::new(
                        rng.random::<f64>(),
                        rng.random::<f64>(),
                        rng.random::<f64>(),
                    ) * 2.0,
                );
            }
        }
        let s = teaser_solve(&src, &dst, &TeaserSettings::with_noise_bound(0.01));
        assert!(s.valid && s.clique_exact);
        assert!(s.inliers.iter().all(|i| i % 20 == 0), "{:?}", s.inliers);
        assert!(s.inliers.len() >= 18);
        let (angle, dist) = omniscan_core::geometry::pose_difference(&s.pose, &truth);
        assert!(
            angle.to_degrees() < 0.5 && dist < 0.01,
            "{} deg, {} m",
            angle.to_degrees(),
            dist
        );
    }
}
