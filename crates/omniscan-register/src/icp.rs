//! ICP with Open3D's semantics, so users can compare numbers one to one
//! (`registration_icp`, `registration_colored_icp`, `evaluate_registration`):
//!
//! - correspondences: each transformed source point's nearest target point
//!   within `max_distance`;
//! - `fitness` = share of source points with a correspondence, `inlier_rmse`
//!   = RMS Euclidean distance over them (whatever the estimator);
//! - loop: estimate an update from the current correspondences, apply it,
//!   re-evaluate; stop when fitness and RMSE both change by less than the
//!   criteria or after `max_iteration` updates.
//!
//! Estimators:
//! - point-to-point (closed form, Kabsch/Umeyama);
//! - point-to-plane (Gauss-Newton on (p − q)·n_q);
//! - colored ICP (Park, Zhou, Koltun, "Colored Point Cloud Registration
//!   Revisited", ICCV 2017): a joint objective of the point-to-plane term
//!   and the difference between the source intensity and the target's
//!   intensity extrapolated along its tangent-plane colour gradient,
//!   weighted λ and 1 − λ;
//! - generalized ICP (Segal, Haehnel, Thrun, RSS 2009), plane to plane as
//!   Open3D runs it: the residual p − q weighted by (C_q + R C_p Rᵀ)^(−1/2),
//!   each C the point's tangent plane with variance ε along its normal.
//!
//! Robust kernels
//! reweight residuals (iteratively reweighted least squares). Sums are
//! reduced in a fixed order, so results do not depend on thread timing.

use nalgebra::{
    Cholesky, Matrix3, Matrix6, Point3, Rotation3, SVD, Translation3, UnitQuaternion, Vector3,
    Vector6,
};
use rayon::prelude::*;
use serde::Serialize;

use std::borrow::Cow;

use crate::grid::{Grid, Nearest, coherent_order};
use crate::neighbors::Neighbors;
use crate::{PointCloud, RegisterError};
use omniscan_core::Pose;

/// When to stop iterating (Open3D's `ICPConvergenceCriteria`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Criteria {
    pub relative_fitness: f64,
    pub relative_rmse: f64,
    pub max_iteration: usize,
}

impl Default for Criteria {
    fn default() -> Self {
        Criteria {
            relative_fitness: 1e-6,
            relative_rmse: 1e-6,
            max_iteration: 30,
        }
    }
}

/// A robust loss for the residuals.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub enum Kernel {
    L2,
    Huber(f64),
    Tukey(f64),
    Cauchy(f64),
}

impl Kernel {
    /// The square root of [`Kernel::weight`], which scales a residual's
    /// row. Plain least squares skips the root, one per correspondence on
    /// the way to its sums (point-to-plane ICP on `frag_115`: 64.2 → 63.0
    /// ms, median of eight alternated rounds; the same bits).
    fn root_weight(self, r: f64) -> f64 {
        match self {
            Kernel::L2 => 1.0,
            _ => self.weight(r).sqrt(),
        }
    }

    fn weight(self, r: f64) -> f64 {
        match self {
            Kernel::L2 => 1.0,
            Kernel::Huber(k) => {
                if r.abs() <= k {
                    1.0
                } else {
                    k / r.abs()
                }
            }
            Kernel::Tukey(k) => {
                if r.abs() <= k {
                    (1.0 - (r / k).powi(2)).powi(2)
                } else {
                    0.0
                }
            }
            Kernel::Cauchy(k) => 1.0 / (1.0 + (r / k).powi(2)),
        }
    }
}

/// How each ICP iteration computes its update.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub enum Estimator {
    PointToPoint,
    PointToPlane,
    /// `lambda_geometric` in [0, 1] weighs the geometric term (Open3D default 0.968).
    Colored {
        lambda_geometric: f64,
    },
    /// Generalized ICP (Segal, Haehnel, Thrun, "Generalized-ICP", RSS 2009),
    /// plane to plane: each point's covariance is its tangent plane, variance
    /// 1 along it and `epsilon` (Open3D default 1e-3) along the normal.
    Generalized {
        epsilon: f64,
    },
}

impl Estimator {
    pub fn name(&self) -> &'static str {
        match self {
            Estimator::PointToPoint => "icp",
            Estimator::PointToPlane => "plane",
            Estimator::Colored { .. } => "colored",
            Estimator::Generalized { .. } => "gicp",
        }
    }
    pub const COLORED: Estimator = Estimator::Colored {
        lambda_geometric: 0.968,
    };
    pub const GENERALIZED: Estimator = Estimator::Generalized { epsilon: 1e-3 };
}

/// Result of a registration (Open3D's `RegistrationResult`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Registration {
    /// Maps source points into the target's frame.
    #[serde(serialize_with = "serialize_pose")]
    pub transformation: Pose,
    pub fitness: f64,
    pub inlier_rmse: f64,
    /// Number of correspondences at the final evaluation.
    pub correspondences: usize,
    /// Updates applied.
    pub iterations: usize,
}

fn serialize_pose<S: serde::Serializer>(p: &Pose, s: S) -> Result<S::Ok, S::Error> {
    omniscan_core::geometry::pose_to_rows(p).serialize(s)
}

impl Registration {
    /// Open3D's ranking: higher fitness, then lower RMSE.
    pub fn is_better_than(&self, other: &Registration) -> bool {
        self.fitness > other.fitness
            || (self.fitness == other.fitness && self.inlier_rmse < other.inlier_rmse)
    }
}

/// A target cloud prepared for repeated registration.
///
/// Besides a k-d tree it keeps, once ICP asks for them, a grid of cells
/// twice the correspondence distance wide ([`Grid`]: fresh nearest-point
/// queries, colored ICP's gradients; the k-d tree answers those instead when
/// the distance is wide against the cloud) and the 15 nearest neighbours of
/// every target point (taken from the gradients' 30 nearest when colored ICP
/// comes first: on `frag_115` that saved the graph's own pass, about a fifth
/// of a colored ICP run). ICP's correspondence step starts each query at the previous
/// iteration's match and walks this graph downhill; the answer is exact when
/// the distance found is under half the radius of the point's neighbour list
/// (every closer point would have to be in that list), and otherwise the
/// query asks the grid. Since ICP moves the source a little per iteration,
/// nearly every query is answered from a few dozen distances. A lower
/// bound on each source point's nearest distance (last distance minus how
/// far the point moved) skips points that cannot have a correspondence.
pub struct Target<'a> {
    /// The cloud, its points in a spatially coherent order
    /// ([`coherent_order`]), so that a walk's neighbour lists and
    /// coordinates lie near each other in memory: the target's indices
    /// (its k-d tree's answers, for one) are of this order, not the caller's.
    /// A shuffled cloud (splat centres) then costs no more than a scanned one.
    pub cloud: Cow<'a, PointCloud>,
    /// The k-d tree, built by the first query that needs it: ICP on a grid
    /// never does, and the build is a twentieth of a point-to-plane run.
    tree: std::sync::OnceLock<Neighbors>,
    grid: std::sync::OnceLock<Grid>,
    graph: std::sync::OnceLock<NeighborGraph>,
    /// The cloud's points in f32, for the graph walk.
    coords: Vec<[f32; 3]>,
}

/// The `GRAPH_K` nearest neighbours of every point (itself first, the
/// others in no order), one cache line per point: their indices and a
/// distance within which the list holds every point, at most the farthest
/// entry's (never more: a walk's answers are exact whatever lists it walks,
/// as long as each holds every point nearer than its reach). A walk step
/// reads the neighbours' coordinates from the target's f32 copy, small
/// enough to stay in cache: lists holding their neighbours' coordinates
/// took 264 bytes a point, four times a 2 MB L2 on a 32k-point cloud, and
/// the walk waited on them.
struct NeighborGraph {
    lists: Vec<NeighborList>,
}

#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct NeighborList {
    ids: [u32; GRAPH_K],
    reach: f32,
}

impl NeighborList {
    /// Point `i`'s list from `found` (at most `k`, `i` among them or not),
    /// which holds every point within `covers` of `i`; `k` less than
    /// [`GRAPH_K`] means the cloud has no other points.
    fn new(i: usize, found: impl Iterator<Item = u32>, covers: f64, k: usize) -> NeighborList {
        // The point itself first, so a walk can stay where it is; short
        // lists repeat their last entry.
        let mut ids = [i as u32; GRAPH_K];
        let mut others = found.filter(|&id| id != i as u32);
        let mut filled = 1;
        for (slot, id) in ids.iter_mut().skip(1).zip(&mut others) {
            *slot = id;
            filled += 1;
        }
        let last = ids[filled - 1];
        ids[filled..].fill(last);
        let reach = if others.next().is_some() {
            // A list of k others, `i` not among them (k duplicates of it):
            // one is left out, and the list covers nothing for sure.
            0.0
        } else if k < GRAPH_K {
            // With every point in the list, nothing lies outside it.
            f32::INFINITY
        } else {
            // Rounded down, so it never overstates what the list covers.
            let rounded = covers as f32;
            if rounded as f64 > covers {
                rounded.next_down()
            } else {
                rounded
            }
        };
        NeighborList { ids, reach }
    }

    /// The entries' f32 squared distances to `q`, padded with an infinite
    /// one to [`LANES`].
    fn distances2(&self, coords: &[[f32; 3]], q: [f32; 3]) -> [f32; LANES] {
        let mut d = [f32::INFINITY; LANES];
        for (dk, &id) in d.iter_mut().zip(&self.ids) {
            let p = coords[id as usize];
            let (dx, dy, dz) = (p[0] - q[0], p[1] - q[1], p[2] - q[2]);
            *dk = dx * dx + dy * dy + dz * dz;
        }
        d
    }
}

/// A list's distances padded to a whole number of vectors.
const LANES: usize = 16;
const _: () = assert!(GRAPH_K < LANES);

/// The lesser of two distances, one `minss`: `f32::min`'s NaN handling
/// took four instructions, and a walk's minimums are on its critical path.
fn lesser(a: f32, b: f32) -> f32 {
    if a < b { a } else { b }
}

/// The greater of two distances, one `maxss`.
fn greater(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

/// The least and the second least of `d` (the same when the least occurs
/// twice), by a tree of pairwise minimums and maximums that the compiler
/// turns into vector instructions.
fn least_two(d: &[f32; LANES]) -> (f32, f32) {
    // Lane i holds the least and second least of the values folded into it.
    let mut lo: [f32; 8] = std::array::from_fn(|i| lesser(d[i], d[i + 8]));
    let mut hi: [f32; 8] = std::array::from_fn(|i| greater(d[i], d[i + 8]));
    for width in [4, 2, 1] {
        for i in 0..width {
            let (a, b) = (lo[i], lo[i + width]);
            hi[i] = lesser(greater(a, b), lesser(hi[i], hi[i + width]));
            lo[i] = lesser(a, b);
        }
    }
    (lo[0], hi[0])
}

/// The first entry of `d` equal to `x` (0 if none is: a NaN query), from a
/// bit mask rather than a scan: the scan's exit branch, taken at entry 0 in
/// about two queries of three and elsewhere at random, was mispredicted
/// late, after the list's loads.
fn first_index_of(d: &[f32; LANES], x: f32) -> usize {
    let mask = d
        .iter()
        .enumerate()
        .fold(0u32, |m, (i, &v)| m | ((v == x) as u32) << i);
    let first = mask.trailing_zeros() as usize;
    if first < LANES { first } else { 0 }
}

const GRAPH_K: usize = 15;
// Colored ICP takes the graph from its gradients' neighbour lists.
const _: () = assert!(GRAPH_K <= GRADIENT_NN);

impl<'a> Target<'a> {
    pub fn new(cloud: &'a PointCloud) -> Target<'a> {
        let order = coherent_order(&cloud.points);
        let cloud = if order.iter().enumerate().all(|(i, &o)| i == o as usize) {
            Cow::Borrowed(cloud)
        } else {
            let order: Vec<usize> = order.iter().map(|&i| i as usize).collect();
            Cow::Owned(cloud.select(&order))
        };
        Target {
            tree: std::sync::OnceLock::new(),
            grid: std::sync::OnceLock::new(),
            graph: std::sync::OnceLock::new(),
            coords: cloud
                .points
                .iter()
                .map(|p| [p.x as f32, p.y as f32, p.z as f32])
                .collect(),
            cloud,
        }
    }

    /// The k-d tree over the target's points.
    pub fn neighbors(&self) -> &Neighbors {
        self.tree.get_or_init(|| Neighbors::new(&self.cloud.points))
    }

    /// A grid with cells at least `cell` wide (the kept one, made by the
    /// first call, unless it is too narrow or needlessly wide for this one),
    /// or none where the k-d tree is the cheaper way to answer.
    fn grid(&self, cell: f64) -> Option<Cow<'_, Grid>> {
        let kept = self
            .grid
            .get_or_init(|| Grid::new(&self.cloud.points, cell));
        let grid = if kept.cell() >= cell && kept.cell() <= 4.0 * cell {
            Cow::Borrowed(kept)
        } else {
            Cow::Owned(Grid::new(&self.cloud.points, cell))
        };
        grid.suits(GRADIENT_NN).then_some(grid)
    }

    /// Point `i`'s entry of the neighbour graph, from its `GRAPH_K` nearest
    /// (or the whole cloud's points, if fewer), nearest first, as a grid
    /// found them (where it found fewer within its reach, those, covering
    /// that reach); without a grid's answer the k-d tree finds them.
    fn neighbor_list(&self, i: usize, nearest: Option<&mut Nearest>) -> NeighborList {
        let k = GRAPH_K.min(self.cloud.len());
        let pts = &self.cloud.points;
        let tree;
        let farthest = |found: &[(usize, f64)]| found.iter().fold(0.0f64, |m, x| m.max(x.1)).sqrt();
        // The list, and the distance within which it holds every point.
        let (found, covers) = match nearest {
            Some(n) if n.points().len() < k => (n.points(), n.reach),
            Some(n) => {
                let found = n.first(k).unwrap_or_default();
                (found, farthest(found))
            }
            None => {
                tree = self.neighbors().knn(&pts[i], k);
                (&tree[..], farthest(&tree))
            }
        };
        NeighborList::new(i, found.iter().map(|x| x.0 as u32), covers, k)
    }

    fn graph(&self, grid: Option<&Grid>) -> &NeighborGraph {
        self.graph.get_or_init(|| {
            let lists = match grid {
                Some(grid) => {
                    let k = GRAPH_K.min(self.cloud.len());
                    grid.knn_lists(k, |i, found, covers| {
                        NeighborList::new(i, found.iter().copied(), covers, k)
                    })
                }
                None => (0..self.cloud.len())
                    .into_par_iter()
                    .map(|i| self.neighbor_list(i, None))
                    .collect(),
            };
            NeighborGraph { lists }
        })
    }

    /// One word of each cache line a search from target point `j` reads
    /// first, and the pair it usually ends in: `j`'s neighbour list, its
    /// point and its normal (0 for [`NO_TARGET`]; without the list while
    /// the graph is not built yet).
    ///
    /// A pass calls this for the point a few places ahead and discards the
    /// value: the loads start those cache misses early. The processor
    /// cannot, being hundreds of instructions behind; the lists, points and
    /// normals of a 32k-point target are 3.5 MB against a 2 MB L2. Lists,
    /// points and normals together: each alone gained about half as much
    /// (docs/results.md).
    /// Stable Rust has no safe prefetch instruction, and this crate has no
    /// `unsafe`.
    fn touch(&self, j: u32) -> u64 {
        let j = j as usize;
        if j >= self.cloud.len() {
            return 0;
        }
        let list = self.graph.get().map_or(0, |g| g.lists[j].ids[0] as u64);
        let normal = self.cloud.normals.get(j).map_or(0, |n| n.x.to_bits());
        list ^ self.cloud.points[j].x.to_bits() ^ normal
    }

    /// Searches the nearest target point to `q` from the target point
    /// `start` and returns a certificate for it (see [`Hint`]).
    ///
    /// The walk moves to the nearest entry of the current point's list until
    /// a list certifies its nearest entry: every point within `reach − |q −
    /// cur|` of `q` is in `cur`'s list, so its nearest entry is the true
    /// nearest when closer than that. A query that moved about one spacing
    /// is usually certified by its first list, without the step to the new
    /// nearest point and a second list that only confirms it (on `frag_115`,
    /// point-to-plane ICP took 1.7 list reads per search before).
    fn search(&self, grid: Option<&Grid>, q: &Point3<f64>, start: u32) -> Hint {
        let g = self.graph(grid);
        let mut cur = start as usize;
        // The walk runs in f32 on the target's f32 copy; `certify` settles
        // in f64 what f32 rounding could have ordered wrongly.
        let qf = [q.x as f32, q.y as f32, q.z as f32];
        loop {
            let list = &g.lists[cur];
            let d = list.distances2(&self.coords, qf);
            let (best, second) = least_two(&d);
            // The first entry at the least distance; entry 0 is `cur` itself.
            let k = first_index_of(&d, best);
            // A test in f32 with slack spares the exact one below on lists
            // that clearly cannot certify.
            let slack = 1.0 + 64.0 * f32::EPSILON;
            if (best.sqrt() + d[0].sqrt()) < list.reach * slack
                && let Some(hint) = self.certify(list, &d, k, (best, second), q)
            {
                return hint;
            }
            let next = list.ids[k] as usize;
            if next == cur {
                break;
            }
            cur = next;
        }
        // The nearest is at most as far as `cur`: a fresh search need not
        // read the cells beyond.
        let bound = (self.cloud.points[cur] - q).norm();
        Hint::fresh_within(self, grid, q, FRESH_MARGIN * bound)
    }

    /// The certificate `list` (the list of its first entry, `cur`) gives for
    /// `q`, given the entries' f32 squared distances `d` and the entry `k`
    /// least of them; `None` when the list does not cover the nearest point.
    fn certify(
        &self,
        list: &NeighborList,
        d: &[f32; LANES],
        k: usize,
        (best, second): (f32, f32),
        q: &Point3<f64>,
    ) -> Option<Hint> {
        // The exact distances, in f64, of every entry f32 rounding could
        // have ordered wrongly: those within `tolerance` of the nearest.
        let scale = q.x.abs().max(q.y.abs()).max(q.z.abs()) as f32 + best.sqrt();
        let tolerance = 8.0 * f32::EPSILON * scale;
        let near2 = (best.sqrt() + 2.0 * tolerance).powi(2);
        let pts = &self.cloud.points;
        let (d1, nearest, d2, far2) = if second > near2 {
            // Nearly always: every other entry is clearly farther.
            let id = list.ids[k] as usize;
            ((pts[id] - q).norm_squared(), id, f64::INFINITY, second)
        } else {
            let (mut d1, mut nearest) = (f64::INFINITY, usize::MAX);
            let mut d2 = f64::INFINITY;
            let mut far2 = f32::INFINITY;
            for (&dk, &id) in d.iter().zip(&list.ids) {
                let id = id as usize;
                if dk > near2 {
                    far2 = lesser(far2, dk);
                } else if id != nearest {
                    let exact = (pts[id] - q).norm_squared();
                    if exact < d1 {
                        d2 = d2.min(d1);
                        d1 = exact;
                        nearest = id;
                    } else {
                        d2 = d2.min(exact);
                    }
                }
            }
            (d1, nearest, d2, far2)
        };
        // For the second nearest a lower bound is enough.
        let far = (far2.sqrt() - tolerance).max(0.0) as f64;
        let (d1, d2) = (d1.sqrt(), d2.sqrt().min(far));
        let cur = list.ids[0] as usize;
        let from_cur = (pts[cur] - q).norm();
        // Every point within reach − |q − cur| of q is in the list: the
        // list's nearest is the true nearest if it is closer than that, and
        // the second nearest is at least min(d2, reach − |q − cur|) away.
        let covered = list.reach as f64 - from_cur;
        (d1 < covered).then(|| Hint {
            target: nearest as u32,
            nearest: d1,
            gap: d2.min(covered) - d1,
            moved: 0.0,
        })
    }
}

const CHUNK: usize = 2048;

/// How many points ahead of the one it matches a pass touches the target
/// data of a point's last match ([`Target::touch`]).
const LOOKAHEAD: usize = 3;

/// A walk that cannot certify its answer bounds the nearest distance by its
/// last point's; the fresh search reads the grid cells within this many
/// times that bound (margin for rounding, and room for a gap to the second
/// nearest that lets later passes skip the point).
const FRESH_MARGIN: f64 = 1.5;

/// What ICP knows of a source point's nearest target point: at the last
/// search, `target` was nearest at distance `nearest`, and every other target
/// point was at least `gap` farther; since then the point has moved by at
/// most `moved`. While `gap > 2·moved` the nearest cannot have changed, and
/// while `nearest − moved` exceeds the correspondence distance the point has
/// no correspondence, so late ICP iterations, which move points very little,
/// need almost no searching. The answers are exactly those of a fresh search.
#[derive(Clone, Copy)]
struct Hint {
    target: u32,
    nearest: f64,
    gap: f64,
    moved: f64,
}

/// The target index of a hint that found no target point within its reach.
const NO_TARGET: u32 = u32::MAX;

/// Colored ICP's gradients use at most this many neighbours.
const GRADIENT_NN: usize = 30;

impl Hint {
    /// A fresh certificate from the two nearest target points: within the
    /// grid's cell size (with none there, the nearest is at least that far),
    /// or anywhere by the k-d tree.
    fn fresh(target: &Target, grid: Option<&Grid>, q: &Point3<f64>) -> Hint {
        Hint::fresh_within(target, grid, q, f64::INFINITY)
    }

    /// [`Hint::fresh`] reading only the grid cells within `radius` of `q`
    /// (at least the grid's cell size is read otherwise).
    fn fresh_within(target: &Target, grid: Option<&Grid>, q: &Point3<f64>, radius: f64) -> Hint {
        match grid {
            Some(grid) => {
                let radius = radius.min(grid.cell());
                Hint::from_nearest_two(grid.nearest_two(q, radius), radius)
            }
            None => {
                let r = target.neighbors().knn(q, 2);
                let second = r.get(1).map_or(f64::INFINITY, |s| s.1);
                Hint::from_nearest_two((r.first().copied(), second), f64::INFINITY)
            }
        }
    }

    fn from_nearest_two(nearest: (Option<(usize, f64)>, f64), reach: f64) -> Hint {
        match nearest {
            (Some((j, e1)), e2) => Hint {
                target: j as u32,
                nearest: e1.sqrt(),
                gap: e2.sqrt().min(reach) - e1.sqrt(),
                moved: 0.0,
            },
            (None, _) => Hint {
                target: NO_TARGET,
                nearest: reach,
                gap: 0.0,
                moved: 0.0,
            },
        }
    }
}

/// One correspondence: source point `source`, moved to `at`, and its
/// nearest target point `target`, `distance2` away (squared).
#[derive(Clone, Copy)]
struct Pair {
    source: usize,
    at: Point3<f64>,
    target: usize,
    distance2: f64,
}

/// What a correspondence pass found in one chunk of source points: how many
/// correspondences, the sum of their squared distances, and the estimator's
/// sums over them.
struct Found<A> {
    count: usize,
    distance2: f64,
    sums: A,
}

/// The correspondences of a source cloud under a sequence of poses, each
/// pass keeping every point's [`Hint`] from the last. A pass also hands
/// each correspondence to the estimator's sums while the points and their
/// matches are in cache: moving the points, searching and summing in
/// separate passes re-read every point three times and built a list of
/// the pairs (docs/results.md).
struct Matcher<'a> {
    /// The source points in a spatially coherent order ([`coherent_order`]),
    /// and each one's index in the source.
    source: Vec<Point3<f64>>,
    order: Vec<u32>,
    target: &'a Target<'a>,
    grid: Option<Cow<'a, Grid>>,
    max_distance: f64,
    hints: Vec<Hint>,
    /// The pose of the last pass, as a matrix and translation.
    last_pose: Option<(Matrix3<f64>, Vector3<f64>)>,
}

impl<'a> Matcher<'a> {
    fn new(source: &[Point3<f64>], target: &'a Target<'a>, max_distance: f64) -> Matcher<'a> {
        let order = coherent_order(source);
        Matcher {
            source: order.iter().map(|&i| source[i as usize]).collect(),
            order,
            target,
            grid: target.grid(2.0 * max_distance),
            max_distance,
            hints: Vec::new(),
            last_pose: None,
        }
    }

    /// The correspondences of the source moved by `pose`, chunk by chunk in
    /// the matcher's order: `add` sums each (with the pose's rotation) into
    /// its chunk's `empty()`. Exactly the pairs a fresh nearest-point search
    /// would give.
    fn pass<A: Send>(
        &mut self,
        pose: &Pose,
        empty: impl Fn() -> A + Sync,
        add: impl Fn(&mut A, &Pair, &Matrix3<f64>) + Sync,
    ) -> Vec<Found<A>> {
        let rotation = *pose.rotation.to_rotation_matrix().matrix();
        let translation = pose.translation.vector;
        let move_point =
            |r: &Matrix3<f64>, t: &Vector3<f64>, p: &Point3<f64>| Point3::from(r * p.coords + t);
        let grid = self.grid.as_deref();
        let target = self.target;
        let before = match self.last_pose.replace((rotation, translation)) {
            Some(before) if self.hints.len() == self.source.len() => Some(before),
            _ => {
                // First pass: fresh searches seed the hints (batched by grid
                // cell they were slower). They read only the cells within
                // the correspondence distance (at most half a cell), so at
                // most 8 of the block's 27: a point with nothing that near is
                // searched again once it moves, but the first pass costs far
                // less (docs/results.md).
                let radius = self.max_distance;
                self.hints = self
                    .source
                    .par_iter()
                    .map(|p| {
                        let at = move_point(&rotation, &translation, p);
                        Hint::fresh_within(target, grid, &at, radius)
                    })
                    .collect();
                None
            }
        };
        let (max_distance, cloud, order) = (self.max_distance, &*target.cloud, &self.order);
        self.source
            .par_chunks(CHUNK)
            .zip(self.hints.par_chunks_mut(CHUNK))
            .enumerate()
            .map(|(c, (chunk, hint))| {
                let mut found = Found {
                    count: 0,
                    distance2: 0.0,
                    sums: empty(),
                };
                // Neighbouring points come one after another, so the previous
                // point's match is a good start for one without its own.
                let mut last: Option<u32> = None;
                let mut touched = 0u64;
                for k in 0..chunk.len() {
                    if let Some(ahead) = hint.get(k + LOOKAHEAD) {
                        touched ^= target.touch(ahead.target);
                    }
                    let (p, h) = (&chunk[k], &mut hint[k]);
                    let at = move_point(&rotation, &translation, p);
                    if let Some((r, t)) = &before {
                        h.moved += (at - move_point(r, t, p)).norm();
                    }
                    if h.nearest - h.moved > max_distance {
                        continue;
                    }
                    // A point that has not moved keeps its match.
                    if h.moved > 0.0 && h.gap <= 2.0 * h.moved {
                        // Start from the point's own last match or, without
                        // one, the previous point's. (Starting from the nearer
                        // of the two cost point-to-plane ICP on `frag_115` 4%
                        // and gained colored ICP nothing.)
                        let start = Some(h.target).filter(|&t| t != NO_TARGET).or(last);
                        *h = match start {
                            Some(start) => target.search(grid, &at, start),
                            None => Hint::fresh(target, grid, &at),
                        };
                    }
                    if h.target == NO_TARGET {
                        continue;
                    }
                    last = Some(h.target);
                    let j = h.target as usize;
                    let distance2 = (cloud.points[j] - at).norm_squared();
                    if distance2 <= max_distance * max_distance {
                        let pair = Pair {
                            source: order[c * CHUNK + k] as usize,
                            at,
                            target: j,
                            distance2,
                        };
                        found.count += 1;
                        found.distance2 += pair.distance2;
                        add(&mut found.sums, &pair, &rotation);
                    }
                }
                std::hint::black_box(touched);
                found
            })
            .collect()
    }
}

/// Open3D's fitness and inlier RMSE from the number of correspondences
/// and the sum of their squared distances.
fn score(n_source: usize, count: usize, distance2: f64) -> (f64, f64) {
    match count {
        0 => (0.0, 0.0),
        count => (
            count as f64 / n_source as f64,
            (distance2 / count as f64).sqrt(),
        ),
    }
}

/// Fitness and RMSE of `source` moved by `transformation` against `target`
/// (Open3D's `evaluate_registration`).
pub fn evaluate(
    source: &PointCloud,
    target: &Target,
    max_distance: f64,
    transformation: &Pose,
) -> Registration {
    let max2 = max_distance * max_distance;
    // The squared distances, summed in source order so the RMSE is the same on every run.
    let distances2: Vec<f64> = source
        .points
        .par_iter()
        .filter_map(|p| {
            target
                .neighbors()
                .nearest(&(transformation * p))
                .map(|(_, d2)| d2)
                .filter(|&d2| d2 <= max2)
        })
        .collect();
    let sum: f64 = distances2.iter().sum();
    let (fitness, inlier_rmse) = score(source.len(), distances2.len(), sum);
    Registration {
        transformation: *transformation,
        fitness,
        inlier_rmse,
        correspondences: distances2.len(),
        iterations: 0,
    }
}

/// Rotation Rz(γ)·Ry(β)·Rx(α) and translation from ξ = (α, β, γ, tx, ty, tz).
fn pose_from_twist(x: &Vector6<f64>) -> Pose {
    let r = Rotation3::from_axis_angle(&Vector3::z_axis(), x[2])
        * Rotation3::from_axis_angle(&Vector3::y_axis(), x[1])
        * Rotation3::from_axis_angle(&Vector3::x_axis(), x[0]);
    Pose::from_parts(
        Translation3::new(x[3], x[4], x[5]),
        UnitQuaternion::from_rotation_matrix(&r),
    )
}

/// Solves JᵀJ ξ = −Jᵀr; the identity where the system is singular (as Open3D does).
fn gauss_newton_step(jtj: &Matrix6<f64>, jtr: &Vector6<f64>) -> Pose {
    match Cholesky::new(*jtj) {
        Some(ch) => {
            let x = ch.solve(&(-jtr));
            if x.iter().all(|v| v.is_finite()) {
                pose_from_twist(&x)
            } else {
                Pose::identity()
            }
        }
        None => Pose::identity(),
    }
}

/// The Gauss-Newton normal equations JᵀWJ ξ = −JᵀWr, summed row by row
/// (JᵀJ is symmetric: only its upper triangle, 21 entries).
#[derive(Clone, Copy)]
struct NormalEquations {
    upper: [f64; 21],
    jtr: Vector6<f64>,
}

impl Default for NormalEquations {
    fn default() -> Self {
        NormalEquations {
            upper: [0.0; 21],
            jtr: Vector6::zeros(),
        }
    }
}

impl NormalEquations {
    fn add(&mut self, jacobian: &Vector6<f64>, residual: f64) {
        let mut k = 0;
        for a in 0..6 {
            for b in a..6 {
                self.upper[k] += jacobian[a] * jacobian[b];
                k += 1;
            }
        }
        self.jtr += jacobian * residual;
    }

    fn merge(&mut self, other: NormalEquations) {
        self.upper
            .iter_mut()
            .zip(other.upper)
            .for_each(|(x, y)| *x += y);
        self.jtr += other.jtr;
    }

    fn solve(&self) -> Pose {
        let mut jtj = Matrix6::zeros();
        let mut k = 0;
        for a in 0..6 {
            for b in a..6 {
                jtj[(a, b)] = self.upper[k];
                jtj[(b, a)] = self.upper[k];
                k += 1;
            }
        }
        gauss_newton_step(&jtj, &self.jtr)
    }
}

/// The sums the closed-form rigid fit needs: the pairs' count, the sums of
/// their source and target points, and of their outer products p qᵀ, all
/// taken from `origin` (a point near the clouds: far from the coordinates'
/// zero, Σ p qᵀ − n p̄ q̄ᵀ would cancel away the digits that matter).
#[derive(Clone, Copy)]
struct CrossCovariance {
    origin: Vector3<f64>,
    count: f64,
    source: Vector3<f64>,
    target: Vector3<f64>,
    outer: Matrix3<f64>,
}

impl CrossCovariance {
    fn around(origin: &Point3<f64>) -> Self {
        CrossCovariance {
            origin: origin.coords,
            count: 0.0,
            source: Vector3::zeros(),
            target: Vector3::zeros(),
            outer: Matrix3::zeros(),
        }
    }

    fn add(&mut self, p: &Point3<f64>, q: &Point3<f64>) {
        let (p, q) = (p.coords - self.origin, q.coords - self.origin);
        self.count += 1.0;
        self.source += p;
        self.target += q;
        self.outer += p * q.transpose();
    }

    fn merge(&mut self, other: CrossCovariance) {
        self.count += other.count;
        self.source += other.source;
        self.target += other.target;
        self.outer += other.outer;
    }

    /// The rigid transform minimising Σ‖q − (R p + t)‖² over the pairs summed.
    fn solve(&self) -> Pose {
        if self.count == 0.0 {
            return Pose::identity();
        }
        let (ps, qs) = (self.source / self.count, self.target / self.count);
        // Σ (p − p̄)(q − q̄)ᵀ = Σ p qᵀ − n p̄ q̄ᵀ.
        let h = self.outer - ps * qs.transpose() * self.count;
        fit_rotation(h, &(ps + self.origin), &(qs + self.origin))
    }
}

/// Closed-form rigid transform minimising Σ‖q − (R p + t)‖² (Kabsch).
pub fn kabsch(pairs: &[(Point3<f64>, Point3<f64>)]) -> Pose {
    if pairs.is_empty() {
        return Pose::identity();
    }
    let n = pairs.len() as f64;
    let ps: Vector3<f64> = pairs.iter().map(|p| p.0.coords).sum::<Vector3<f64>>() / n;
    let qs: Vector3<f64> = pairs.iter().map(|p| p.1.coords).sum::<Vector3<f64>>() / n;
    let mut h = Matrix3::zeros();
    for (p, q) in pairs {
        h += (p.coords - ps) * (q.coords - qs).transpose();
    }
    fit_rotation(h, &ps, &qs)
}

/// Kabsch's rotation from the cross-covariance `h` of centred pairs, and
/// the translation taking the source centroid `ps` onto the target's `qs`.
fn fit_rotation(h: Matrix3<f64>, ps: &Vector3<f64>, qs: &Vector3<f64>) -> Pose {
    let svd = SVD::new(h, true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return Pose::identity();
    };
    let v = vt.transpose();
    let d = (v * u.transpose()).determinant().signum();
    let r = v * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * u.transpose();
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    let t = qs - rotation * ps;
    Pose::from_parts(Translation3::from(t), rotation)
}

/// Per-target-point intensity gradients in the tangent plane (colored ICP's
/// precomputation: least squares over up to 30 neighbours within
/// `2 · max_distance`, with the orthogonality constraint; zero with fewer
/// than four neighbours).
pub fn color_gradients(target: &Target, max_distance: f64) -> Vec<Vector3<f64>> {
    let cloud = &*target.cloud;
    let radius = 2.0 * max_distance;
    let gradient = |i: usize, nbrs: &[(usize, f64)]| {
        let p = cloud.points[i];
        let n = cloud.normals[i];
        let it = cloud.intensity(i);
        let nn = nbrs.len();
        if nn < 4 {
            return Vector3::zeros();
        }
        let mut ata = Matrix3::zeros();
        let mut atb = Vector3::zeros();
        for &(j, _) in nbrs.iter().filter(|n| n.0 != i) {
            let q = cloud.points[j];
            let proj = q - n * (q - p).dot(&n);
            let a = proj - p;
            ata += a * a.transpose();
            atb += a * (cloud.intensity(j) - it);
        }
        let c = n * (nn - 1) as f64;
        ata += c * c.transpose();
        match Cholesky::new(ata) {
            Some(ch) => ch.solve(&atb),
            None => Vector3::zeros(),
        }
    };
    let from_tree = |i: usize| {
        let nbrs = target
            .neighbors()
            .hybrid(&cloud.points[i], radius, GRADIENT_NN);
        gradient(i, &nbrs)
    };
    match target.grid(radius) {
        // The neighbour graph ICP walks is the first GRAPH_K of the same k
        // nearest, so the first colored ICP on a target builds both in one
        // pass (the hybrid search's answer is the k nearest cut at its radius).
        Some(grid) if target.graph.get().is_none() => {
            let k = GRADIENT_NN.min(cloud.len());
            let (gradients, lists) = grid
                .knn_map(k, |i, mut nearest| {
                    // The block reaches at least the gradients' radius, so
                    // the grid answers them, and the graph's lists, without
                    // the k-d tree: on `frag_115`'s target half 701 of
                    // 32,097 points have fewer than 30 points within the
                    // block's reach, and they made the tree's build part of
                    // every first colored ICP on a target.
                    let gradient = match nearest.within(radius) {
                        Some(within) => gradient(i, within),
                        None => {
                            let tree = target.neighbors().hybrid(&cloud.points[i], radius, k);
                            gradient(i, &tree)
                        }
                    };
                    (gradient, target.neighbor_list(i, Some(&mut nearest)))
                })
                .into_iter()
                .unzip();
            // A concurrent call may have set it meanwhile, from f32
            // distances ([`Grid::knn_lists`]): lists of the same points but
            // for near ties, reaches shorter by rounding, the same answers.
            let _ = target.graph.set(NeighborGraph { lists });
            gradients
        }
        Some(grid) => grid.hybrid_map(radius, GRADIENT_NN, gradient),
        None => (0..cloud.len()).into_par_iter().map(from_tree).collect(),
    }
}

/// Runs ICP from `init`. Point-to-plane and colored ICP need target normals;
/// colored ICP needs colours on both clouds.
pub fn icp(
    source: &PointCloud,
    target: &Target,
    max_distance: f64,
    init: &Pose,
    estimator: Estimator,
    kernel: Kernel,
    criteria: &Criteria,
) -> Result<Registration, RegisterError> {
    source.validate("source")?;
    target.cloud.validate("target")?;
    if !(max_distance.is_finite() && max_distance > 0.0) {
        return Err(RegisterError::Invalid(format!(
            "the correspondence distance must be positive, got {max_distance}"
        )));
    }
    let needs_normals = !matches!(estimator, Estimator::PointToPoint);
    if needs_normals && !target.cloud.has_normals() {
        return Err(RegisterError::Invalid(format!(
            "{} ICP needs target normals; estimate them first",
            estimator.name()
        )));
    }
    if let Estimator::Generalized { epsilon } = estimator {
        if !source.has_normals() {
            return Err(RegisterError::Invalid(
                "generalized ICP needs source normals too; estimate them first".into(),
            ));
        }
        if !(epsilon > 0.0 && epsilon < 1.0) {
            return Err(RegisterError::Invalid(format!(
                "generalized ICP's epsilon must be in (0, 1), got {epsilon}"
            )));
        }
    }
    let gradients = match estimator {
        Estimator::Colored { lambda_geometric } => {
            if !source.has_colors() || !target.cloud.has_colors() {
                return Err(RegisterError::Invalid(
                    "colored ICP needs colours on both point clouds".into(),
                ));
            }
            if !(0.0..=1.0).contains(&lambda_geometric) {
                return Err(RegisterError::Invalid(format!(
                    "lambda_geometric must be in [0, 1], got {lambda_geometric}"
                )));
            }
            color_gradients(target, max_distance)
        }
        _ => Vec::new(),
    };
    // The passes move points by the rotation's matrix, `evaluate` and
    // callers by its quaternion: they agree when that has unit length.
    let init = &Pose::from_parts(
        init.translation,
        UnitQuaternion::new_normalize(init.rotation.into_inner()),
    );
    let tc = &*target.cloud;
    let mut matcher = Matcher::new(&source.points, target, max_distance);
    let registration = match estimator {
        Estimator::PointToPoint => {
            let origin = tc.centroid();
            iterate(
                &mut matcher,
                init,
                criteria,
                || CrossCovariance::around(&origin),
                |sums, pair, _| sums.add(&pair.at, &tc.points[pair.target]),
                CrossCovariance::merge,
                CrossCovariance::solve,
            )
        }
        Estimator::PointToPlane => iterate(
            &mut matcher,
            init,
            criteria,
            NormalEquations::default,
            |sums, pair, _| {
                let (p, q, n) = (pair.at, tc.points[pair.target], tc.normals[pair.target]);
                let r = (p - q).dot(&n);
                let w = kernel.root_weight(r);
                let c = p.coords.cross(&n);
                sums.add(&(Vector6::new(c.x, c.y, c.z, n.x, n.y, n.z) * w), r * w);
            },
            NormalEquations::merge,
            NormalEquations::solve,
        ),
        Estimator::Colored { lambda_geometric } => {
            let (sg, sc) = (lambda_geometric.sqrt(), (1.0 - lambda_geometric).sqrt());
            iterate(
                &mut matcher,
                init,
                criteria,
                NormalEquations::default,
                |sums, pair, _| {
                    let (s, j) = (pair.at, pair.target);
                    let (q, n, d) = (tc.points[j], tc.normals[j], gradients[j]);
                    let rg = (s - q).dot(&n);
                    let wg = kernel.root_weight(rg);
                    let c = s.coords.cross(&n);
                    sums.add(
                        &(Vector6::new(c.x, c.y, c.z, n.x, n.y, n.z) * (sg * wg)),
                        rg * sg * wg,
                    );
                    let projected = s - n * rg;
                    let predicted = tc.intensity(j) + d.dot(&(projected - q));
                    let rc = source.intensity(pair.source) - predicted;
                    // −(I − n nᵀ)·d: the gradient's part in the tangent plane, negated.
                    let dm = n * n.dot(&d) - d;
                    let wc = kernel.root_weight(rc);
                    let c = s.coords.cross(&dm);
                    sums.add(
                        &(Vector6::new(c.x, c.y, c.z, dm.x, dm.y, dm.z) * (sc * wc)),
                        rc * sc * wc,
                    );
                },
                NormalEquations::merge,
                NormalEquations::solve,
            )
        }
        Estimator::Generalized { epsilon } => {
            // Each point's plane, by its normal; the source's turn with it.
            let source_axes: Vec<Vector3<f64>> =
                source.normals.iter().map(covariance_axis).collect();
            let target_axes: Vec<Vector3<f64>> = tc.normals.iter().map(covariance_axis).collect();
            let inverse_root = PlaneCovariances::new(epsilon);
            iterate(
                &mut matcher,
                init,
                criteria,
                NormalEquations::default,
                |sums, pair, rotation| {
                    let (p, q) = (pair.at, tc.points[pair.target]);
                    let w = inverse_root.of_sum(
                        &target_axes[pair.target],
                        &(rotation * source_axes[pair.source]),
                    );
                    // W·(p − q) and W·[−[p]× | I], row by row.
                    let r = w * (p - q);
                    for row in 0..3 {
                        let wr = w.row(row).transpose();
                        let c = p.coords.cross(&wr);
                        let weight = kernel.root_weight(r[row]);
                        sums.add(
                            &(Vector6::new(c.x, c.y, c.z, wr.x, wr.y, wr.z) * weight),
                            r[row] * weight,
                        );
                    }
                },
                NormalEquations::merge,
                NormalEquations::solve,
            )
        }
    };
    Ok(registration)
}

/// The axis of a point's plane covariance: its (unit) normal, as Open3D
/// builds it, including its choice of the x axis for normals within about
/// 8° of −x (its rotation taking x onto the normal is the identity there),
/// so that results compare one to one.
fn covariance_axis(normal: &Vector3<f64>) -> Vector3<f64> {
    if normal.x < -0.99 {
        Vector3::x()
    } else {
        normal.normalize()
    }
}

/// Generalized ICP's weight W = (C_target + C_source)^(−1/2) for plane
/// covariances C = ε a aᵀ + (I − a aᵀ) = I − k a aᵀ, k = 1 − ε, in closed
/// form: with a and b the two axes and c = a·b, M = 2I − k(a aᵀ + b bᵀ) has
/// the eigenvalue 2 across both axes and 2 − k(1 ± c) along a ± b, so
/// W = I/√2 + h(1 + c)(a + b)(a + b)ᵀ + h(1 − c)(a − b)(a − b)ᵀ with
/// h(x) = (λ^(−1/2) − 2^(−1/2)) / (2x), λ = 2 − kx, written without the
/// cancellation at x → 0. (Open3D takes a Schur-based matrix square root of
/// the inverse per correspondence; the values agree to rounding.)
struct PlaneCovariances {
    k: f64,
}

impl PlaneCovariances {
    fn new(epsilon: f64) -> Self {
        PlaneCovariances { k: 1.0 - epsilon }
    }

    fn of_sum(&self, a: &Vector3<f64>, b: &Vector3<f64>) -> Matrix3<f64> {
        let k = self.k;
        let root2 = std::f64::consts::SQRT_2;
        let h = |x: f64| {
            let root = (2.0 - k * x).sqrt();
            k / (2.0 * root2 * root * (root2 + root))
        };
        let c = a.dot(b);
        let (plus, minus) = (a + b, a - b);
        Matrix3::from_diagonal_element(std::f64::consts::FRAC_1_SQRT_2)
            + plus * plus.transpose() * h(1.0 + c)
            + minus * minus.transpose() * h(1.0 - c)
    }
}

/// ICP's loop, as Open3D runs it: the correspondences of the source at
/// `init`; then, until converged, an update solved from the estimator's
/// sums over them (`empty`, `add`, `merge`, `solve`) and the correspondences
/// of the source moved by it.
fn iterate<A: Send>(
    matcher: &mut Matcher,
    init: &Pose,
    criteria: &Criteria,
    empty: impl Fn() -> A + Sync,
    add: impl Fn(&mut A, &Pair, &Matrix3<f64>) + Sync,
    merge: impl Fn(&mut A, A),
    solve: impl Fn(&A) -> Pose,
) -> Registration {
    let n_source = matcher.source.len();
    let pass = |matcher: &mut Matcher, pose: &Pose| {
        let mut total = Found {
            count: 0,
            distance2: 0.0,
            sums: empty(),
        };
        // In the matcher's order, so results do not depend on thread timing.
        for found in matcher.pass(pose, &empty, &add) {
            total.count += found.count;
            total.distance2 += found.distance2;
            merge(&mut total.sums, found.sums);
        }
        let (fitness, rmse) = score(n_source, total.count, total.distance2);
        (total, fitness, rmse)
    };
    let mut transformation = *init;
    let (mut found, mut fitness, mut rmse) = pass(matcher, &transformation);
    if criteria.max_iteration > 0 {
        // Searches after the first walk the neighbour graph. Built here, it
        // has both threads; built by the first search that needs it, inside
        // the parallel correspondence pass, it had one, the other waiting
        // for it (on a 32k-point scan: 41 ms, against 21-33 ms here).
        matcher.target.graph(matcher.grid.as_deref());
    }
    let mut iterations = 0;
    for _ in 0..criteria.max_iteration {
        transformation = solve(&found.sums) * transformation;
        iterations += 1;
        let (next, f, r) = pass(matcher, &transformation);
        let converged = (fitness - f).abs() < criteria.relative_fitness
            && (rmse - r).abs() < criteria.relative_rmse;
        (found, fitness, rmse) = (next, f, r);
        if converged {
            break;
        }
    }
    Registration {
        transformation,
        fitness,
        inlier_rmse: rmse,
        correspondences: found.count,
        iterations,
    }
}

/// Colored ICP over a coarse-to-fine schedule of voxel sizes (Open3D's
/// tutorial: voxels [v, v/2, v/4], iterations [50, 30, 14]): at each scale both
/// clouds are downsampled, normals estimated (radius 2·voxel, 30 neighbours)
/// and colored ICP run with the voxel size as correspondence distance.
pub fn multiscale_colored_icp(
    source: &PointCloud,
    target: &PointCloud,
    init: &Pose,
    voxels: &[f64],
    iterations: &[usize],
) -> Result<Registration, RegisterError> {
    let mut current = *init;
    let mut last = None;
    for (&voxel, &iters) in voxels.iter().zip(iterations) {
        let mut s = crate::preprocess::voxel_downsample(source, voxel);
        let mut t = crate::preprocess::voxel_downsample(target, voxel);
        crate::preprocess::estimate_normals(&mut s, 2.0 * voxel, 30);
        crate::preprocess::estimate_normals(&mut t, 2.0 * voxel, 30);
        let tt = Target::new(&t);
        let criteria = Criteria {
            max_iteration: iters,
            ..Criteria::default()
        };
        let r = icp(
            &s,
            &tt,
            voxel,
            &current,
            Estimator::COLORED,
            Kernel::L2,
            &criteria,
        )?;
        current = r.transformation;
        last = Some(r);
    }
    last.ok_or_else(|| RegisterError::Invalid("multi-scale ICP needs at least one scale".into()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A wavy, coloured surface patch: enough structure to constrain all six degrees of freedom.
    fn surface(n: usize, seed: u64) -> PointCloud {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut c = PointCloud::default();
        for _ in 0..n {
            let (u, v): (f64, f64) = (
                rng.random::<f64>() * 0.2 - 0.1,
                rng.random::<f64>() * 0.2 - 0.1,
            );
            let z = 0.02 * (u * 40.0).sin() * (v * 25.0).cos() + 0.01 * (u * 13.0 + v * 7.0).sin();
            c.points.push(Point3::new(u, v, z));
            let t = (0.5 + 0.5 * (u * 60.0).sin() * (v * 45.0).cos()) as f32;
            c.colors.push([t, 0.3 + 0.4 * t, 1.0 - t]);
        }
        c
    }

    /// [`surface`] with normals (1 cm radius, 30 neighbours), for targets.
    fn surface_with_normals(n: usize, seed: u64) -> PointCloud {
        let mut cloud = surface(n, seed);
        crate::preprocess::estimate_normals(&mut cloud, 0.01, 30);
        cloud
    }

    #[test]
    fn gradients_pass_and_graph_alone_list_the_nearest_as_the_tree() {
        // A surface, and a cluster of six points half a metre off it: fewer
        // than GRAPH_K points lie within the grid's reach of those.
        let mut cloud = surface(3000, 5);
        for m in 0..6 {
            let a = m as f64;
            cloud.points.push(Point3::new(
                0.003 * a.cos(),
                0.003 * a.sin(),
                0.5 + 0.001 * a,
            ));
            cloud.colors.push([0.2, 0.1 * a as f32, 0.5]);
        }
        crate::preprocess::estimate_normals(&mut cloud, 0.01, 30);
        let max_distance = 0.01;
        // Colored ICP first: the graph comes from the gradients' lists.
        let shared = Target::new(&cloud);
        let gradients = color_gradients(&shared, max_distance);
        assert!(shared.graph.get().is_some());
        // The graph alone, from the grid's nearest in f32.
        let alone = Target::new(&cloud);
        // Indices are of the targets' (one) order.
        let cloud = &*shared.cloud;
        assert_eq!(cloud.points, alone.cloud.points);
        let cluster: Vec<usize> = (0..cloud.len())
            .filter(|&i| cloud.points[i].z > 0.4)
            .collect();
        assert_eq!(cluster.len(), 6);
        let graph = alone.graph(alone.grid(2.0 * max_distance).as_deref());
        // Both against the k-d tree, point by point.
        let radius = 2.0 * max_distance;
        for i in (0..cloud.len()).step_by(7).chain(cluster.iter().copied()) {
            let tree = shared.neighbors().knn(&cloud.points[i], GRAPH_K);
            let ids: Vec<u32> = tree.iter().map(|n| n.0 as u32).collect();
            for (exact, lists) in [
                (true, &shared.graph.get().unwrap().lists),
                (false, &graph.lists),
            ] {
                // The point itself first, the others in any order.
                let list = &lists[i];
                assert_eq!(list.ids[0] as usize, i);
                let mut listed = list.ids.to_vec();
                listed.sort_unstable();
                listed.dedup();
                if cluster.contains(&i) {
                    // Its own six, and a reach past them but short of the
                    // surface.
                    let mut own: Vec<u32> = ids[..6].to_vec();
                    own.sort_unstable();
                    assert_eq!(listed, own, "neighbours of point {i}");
                    assert!(
                        list.reach as f64 >= tree[5].1.sqrt()
                            && (list.reach as f64) < tree[6].1.sqrt()
                    );
                } else {
                    let mut nearest = ids.clone();
                    nearest.sort_unstable();
                    assert_eq!(listed, nearest, "neighbours of point {i}");
                    let reach = tree[GRAPH_K - 1].1.sqrt();
                    // The gradients' lists give the k-th distance rounded
                    // down to f32; the graph's own, measured in f32, less
                    // its bound on their rounding (here under a micrometre).
                    let least = if exact {
                        list.reach.next_up() as f64
                    } else {
                        list.reach as f64 + 1e-6
                    };
                    assert!(
                        list.reach as f64 <= reach && least > reach,
                        "point {i}: reach {} against {reach}",
                        list.reach
                    );
                }
            }
            let hybrid = shared
                .neighbors()
                .hybrid(&cloud.points[i], radius, GRADIENT_NN);
            let mut ata = Matrix3::zeros();
            let mut atb = Vector3::zeros();
            let (p, n) = (cloud.points[i], cloud.normals[i]);
            for &(j, _) in hybrid.iter().filter(|n| n.0 != i) {
                let a = cloud.points[j] - n * (cloud.points[j] - p).dot(&n) - p;
                ata += a * a.transpose();
                atb += a * (cloud.intensity(j) - cloud.intensity(i));
            }
            let c = n * (hybrid.len() - 1) as f64;
            let expected = Cholesky::new(ata + c * c.transpose()).unwrap().solve(&atb);
            assert!(
                (gradients[i] - expected).norm() <= 1e-9 * expected.norm().max(1.0),
                "gradient of point {i}: {} vs {expected}",
                gradients[i]
            );
        }
    }

    #[test]
    fn least_two_and_first_index_agree_with_a_sort() {
        // Few distinct values, so ties (at the least too) are common; the
        // padding lane is infinite, as in a list's distances.
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        for _ in 0..5000 {
            let mut d = [f32::INFINITY; LANES];
            let filled = rng.random_range(1..=GRAPH_K);
            for x in d.iter_mut().take(filled) {
                *x = rng.random_range(0..12) as f32 * 0.25;
            }
            let mut sorted = d.to_vec();
            sorted.sort_by(f32::total_cmp);
            assert_eq!(least_two(&d), (sorted[0], sorted[1]), "{d:?}");
            let first = d.iter().position(|&x| x == sorted[0]).unwrap();
            assert_eq!(first_index_of(&d, sorted[0]), first, "{d:?}");
        }
        // A NaN query's distances: the list's own entry, not one past it.
        let d = [f32::NAN; LANES];
        assert_eq!(first_index_of(&d, least_two(&d).0), 0);
    }

    #[test]
    fn gradients_and_graph_do_not_depend_on_the_thread_count() {
        // Which cells a thread took before depends on the scheduling; the
        // bits of the gradients (sums over the neighbours, in the order they
        // were selected in) and the graph's lists must not.
        let cloud = surface_with_normals(6000, 9);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let target = Target::new(&cloud);
                let gradients = color_gradients(&target, 0.01);
                let lists: Vec<[u32; GRAPH_K]> = target
                    .graph
                    .get()
                    .unwrap()
                    .lists
                    .iter()
                    .map(|l| l.ids)
                    .collect();
                let bits: Vec<[u64; 3]> = gradients
                    .iter()
                    .map(|g| [g.x.to_bits(), g.y.to_bits(), g.z.to_bits()])
                    .collect();
                (bits, lists)
            })
        };
        let one = run(1);
        for threads in [2, 3, 4, 7] {
            for _ in 0..3 {
                assert!(run(threads) == one, "{threads} threads differ from one");
            }
        }
    }

    #[test]
    fn kabsch_recovers_a_rigid_transform_exactly() {
        let c = surface(200, 1);
        let t = Pose::new(Vector3::new(0.1, -0.3, 0.05), Vector3::new(0.4, -1.2, 2.0));
        let pairs: Vec<_> = c.points.iter().map(|p| (*p, t * p)).collect();
        let est = kabsch(&pairs);
        let (a, d) = omniscan_core::geometry::pose_difference(&est, &t);
        assert!(a < 1e-9 && d < 1e-9);
    }

    /// 60 ICP iterations of `est` from the identity; the result and its
    /// angle (radians) and shift (metres) from `truth`.
    fn icp_from_identity(
        source: &PointCloud,
        target: &Target,
        max_distance: f64,
        est: Estimator,
        truth: &Pose,
    ) -> (Registration, f64, f64) {
        let crit = Criteria {
            max_iteration: 60,
            ..Criteria::default()
        };
        let r = icp(
            source,
            target,
            max_distance,
            &Pose::identity(),
            est,
            Kernel::L2,
            &crit,
        )
        .unwrap();
        let (a, d) = omniscan_core::geometry::pose_difference(&r.transformation, truth);
        (r, a, d)
    }

    #[test]
    fn point_to_point_stays_exact_far_from_the_coordinates_zero() {
        // A 20 cm patch 100 km out: the closed-form fit's sums are taken
        // from a point near the clouds, not from the zero.
        let far = Pose::translation(1.0e5, -2.0e5, 3.0e4);
        let target = surface(3000, 12).transformed(&far);
        let turn = Pose::from_parts(
            Translation3::new(0.003, -0.002, 0.001),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 2f64.to_radians()),
        );
        // The truth turns about a point of the patch, as a scan's would.
        let truth = far * turn * far.inverse();
        let source = target.transformed(&truth.inverse());
        let (r, a, d) = icp_from_identity(
            &source,
            &Target::new(&target),
            0.02,
            Estimator::PointToPoint,
            &truth,
        );
        assert!(
            a.to_degrees() < 0.01 && d < 1e-4,
            "{:.5}° {d:.2e} m",
            a.to_degrees()
        );
        assert!(r.fitness > 0.999, "{r:?}");
    }

    #[test]
    fn nearest_points_come_from_the_grid_or_from_the_tree_with_one_result() {
        // 1 cm on this 0.2 m patch is searched on the grid; 15 cm would put
        // the whole cloud in every grid block, so the k-d tree answers.
        let target = surface_with_normals(3000, 3);
        let tt = Target::new(&target);
        assert!(tt.grid(0.02).is_some() && tt.grid(0.3).is_none());
        let truth = Pose::from_parts(
            Translation3::new(0.004, -0.003, 0.002),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 2f64.to_radians()),
        );
        let source = target.transformed(&truth.inverse());
        for max_distance in [0.01, 0.15] {
            for est in [Estimator::PointToPlane, Estimator::COLORED] {
                let (r, a, d) = icp_from_identity(&source, &tt, max_distance, est, &truth);
                let case = format!("{est:?} at {max_distance} m");
                assert!(a.to_degrees() < 0.01 && d < 1e-4, "{case}: {a} rad {d} m");
                assert!(r.fitness == 1.0 && r.inlier_rmse < 1e-5, "{case}: {r:?}");
            }
        }
    }

    #[test]
    fn kept_correspondences_are_those_of_a_fresh_search_after_every_move() {
        // A source sampled apart from the target, moved as ICP moves it:
        // large steps first, then small ones back and forth, so that some
        // points keep their match on a certificate and others search again.
        let target = surface_with_normals(4000, 8);
        let mut source = surface(3000, 9);
        let mut rng = ChaCha8Rng::seed_from_u64(10);
        for p in &mut source.points {
            p.z += 0.002 * (rng.random::<f64>() - 0.5);
        }
        let tt = Target::new(&target);
        // On the grid (1 cm) and on the k-d tree (15 cm).
        for max_distance in [0.01, 0.15] {
            let mut matcher = Matcher::new(&source.points, &tt, max_distance);
            let (mut kept, mut visits) = (0, 0);
            for step in 0..40 {
                let size = 0.01 * 0.8f64.powi(step) * if step % 2 == 0 { 1.0 } else { -0.7 };
                let pose = Pose::from_parts(
                    Translation3::new(size, -0.5 * size, 0.3 * size),
                    UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 3.0 * size),
                );
                let mut found: Vec<(usize, usize, f64)> = matcher
                    .pass(&pose, Vec::new, |pairs, pair, _| {
                        pairs.push((pair.source, pair.target, pair.distance2))
                    })
                    .into_iter()
                    .flat_map(|found| found.sums)
                    .collect();
                // The matcher takes the source in its own order.
                found.sort_by_key(|f| f.0);
                if step > 0 {
                    // A search starts the point's move afresh.
                    kept += matcher.hints.iter().filter(|h| h.moved > 0.0).count();
                    visits += source.len();
                }
                let fresh: Vec<(usize, usize, f64)> = source
                    .points
                    .iter()
                    .enumerate()
                    .filter_map(|(i, p)| {
                        let (j, d2) = tt.neighbors().knn(&(pose * p), 1)[0];
                        (d2 <= max_distance * max_distance).then_some((i, j, d2))
                    })
                    .collect();
                assert_eq!(found.len(), fresh.len(), "step {step} at {max_distance} m");
                for (f, e) in found.iter().zip(&fresh) {
                    assert!(
                        f.0 == e.0 && f.1 == e.1 && (f.2 - e.2).abs() <= 1e-15,
                        "step {step} at {max_distance} m: {f:?} vs {e:?}"
                    );
                }
            }
            // The certificates did some of the work.
            assert!(kept > visits / 10, "{kept} of {visits} kept");
        }
    }

    #[test]
    fn identical_clouds_under_random_transforms_align_exactly() {
        let target = surface_with_normals(3000, 2);
        let tt = Target::new(&target);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for _ in 0..5 {
            let axis = Vector3::new(
                rng.random::<f64>() - 0.5,
                rng.random::<f64>() - 0.5,
                rng.random::<f64>() - 0.5,
            )
            .normalize();
            let truth = Pose::from_parts(
                Translation3::new(0.004, -0.003, 0.002),
                UnitQuaternion::from_axis_angle(
                    &nalgebra::Unit::new_normalize(axis),
                    3f64.to_radians(),
                ),
            );
            let source = target.transformed(&truth.inverse());
            for est in [
                Estimator::PointToPoint,
                Estimator::PointToPlane,
                Estimator::COLORED,
                Estimator::GENERALIZED,
            ] {
                let (r, a, d) = icp_from_identity(&source, &tt, 0.02, est, &truth);
                assert!(
                    a.to_degrees() < 0.01 && d < 1e-4,
                    "{est:?}: {:.4}° {:.2e} m",
                    a.to_degrees(),
                    d
                );
                assert!(r.fitness > 0.999 && r.inlier_rmse < 1e-5, "{est:?}: {r:?}");
            }
        }
    }

    #[test]
    fn plane_covariance_weight_is_the_inverse_square_root_of_the_sum() {
        // Against an eigendecomposition of C_a + C_b, for random planes and
        // for nearly parallel and nearly opposite ones (the closed form's
        // h(x) at x → 0).
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let mut unit = || {
            Vector3::new(
                rng.random::<f64>() - 0.5,
                rng.random::<f64>() - 0.5,
                rng.random::<f64>() - 0.5,
            )
            .normalize()
        };
        let mut pairs: Vec<(Vector3<f64>, Vector3<f64>)> =
            (0..50).map(|_| (unit(), unit())).collect();
        let a = unit();
        let tilt = unit() * 1e-9;
        pairs.extend([
            (a, a),
            (a, -a),
            (a, (a + tilt).normalize()),
            (a, (tilt - a).normalize()),
        ]);
        for epsilon in [1e-3, 0.3] {
            let weight = PlaneCovariances::new(epsilon);
            let plane =
                |n: &Vector3<f64>| Matrix3::identity() - n * n.transpose() * (1.0 - epsilon);
            for (a, b) in &pairs {
                let eigen = (plane(a) + plane(b)).symmetric_eigen();
                let expected = eigen.eigenvectors
                    * Matrix3::from_diagonal(&eigen.eigenvalues.map(|l| 1.0 / l.sqrt()))
                    * eigen.eigenvectors.transpose();
                let w = weight.of_sum(a, b);
                assert!(
                    (w - expected).norm() < 1e-9 * expected.norm(),
                    "ε {epsilon}, a·b {}: {w} vs {expected}",
                    a.dot(b)
                );
            }
        }
    }

    #[test]
    fn a_start_pose_off_unit_length_is_used_as_its_rotation() {
        // A quaternion 1e-6 off unit length (nalgebra trusts it): the
        // reported fitness and RMSE are those of the transform returned.
        let target = surface_with_normals(3000, 14);
        let tt = Target::new(&target);
        let truth = Pose::new(
            Vector3::new(0.002, -0.001, 0.003),
            Vector3::new(0.01, 0.02, -0.015),
        );
        let mut source = target.transformed(&truth.inverse());
        let mut rng = ChaCha8Rng::seed_from_u64(15);
        for p in &mut source.points {
            p.z += 0.001 * (rng.random::<f64>() - 0.5);
        }
        let off = UnitQuaternion::new_unchecked(
            UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 0.01).into_inner() * (1.0 + 1e-6),
        );
        let start = Pose::from_parts(Translation3::identity(), off);
        for estimator in [Estimator::PointToPoint, Estimator::PointToPlane] {
            let criteria = Criteria {
                max_iteration: 3,
                ..Criteria::default()
            };
            let r = icp(&source, &tt, 0.02, &start, estimator, Kernel::L2, &criteria).unwrap();
            let e = evaluate(&source, &tt, 0.02, &r.transformation);
            assert_eq!(r.fitness, e.fitness, "{estimator:?}");
            assert!(
                (r.inlier_rmse - e.inlier_rmse).abs() < 1e-12 * e.inlier_rmse,
                "{estimator:?}: {} vs {}",
                r.inlier_rmse,
                e.inlier_rmse
            );
        }
    }

    #[test]
    fn fitness_and_rmse_follow_open3d_definitions() {
        let target = PointCloud {
            points: vec![Point3::origin(), Point3::new(1.0, 0.0, 0.0)],
            ..Default::default()
        };
        let source = PointCloud {
            points: vec![
                Point3::new(0.0, 0.1, 0.0),
                Point3::new(1.0, 0.0, 0.3),
                Point3::new(5.0, 0.0, 0.0),
            ],
            ..Default::default()
        };
        let r = evaluate(&source, &Target::new(&target), 0.5, &Pose::identity());
        assert!((r.fitness - 2.0 / 3.0).abs() < 1e-12);
        assert!((r.inlier_rmse - ((0.01 + 0.09) / 2f64).sqrt()).abs() < 1e-12);
        // No overlap is a result, not an error.
        let far = source.transformed(&Pose::translation(100.0, 0.0, 0.0));
        let r = icp(
            &far,
            &Target::new(&target),
            0.5,
            &Pose::identity(),
            Estimator::PointToPoint,
            Kernel::L2,
            &Criteria::default(),
        )
        .unwrap();
        assert_eq!((r.fitness, r.inlier_rmse), (0.0, 0.0));
    }

    #[test]
    fn clear_errors_for_bad_inputs() {
        let c = surface(100, 3);
        let tt = Target::new(&c);
        let crit = Criteria::default();
        let error_of = |source: &PointCloud, target: &Target, estimator: Estimator| {
            icp(
                source,
                target,
                0.1,
                &Pose::identity(),
                estimator,
                Kernel::L2,
                &crit,
            )
            .unwrap_err()
            .to_string()
        };
        let mut with_normals = c.clone();
        crate::preprocess::estimate_normals(&mut with_normals, 0.02, 30);
        let mut grey = c.clone();
        grey.colors.clear();
        let tn = Target::new(&with_normals);
        for (source, target, estimator, expected) in [
            (&c, &tt, Estimator::PointToPlane, "normals"),
            (&grey, &tn, Estimator::COLORED, "colours"),
            // Generalized ICP needs the source's planes too.
            (&grey, &tn, Estimator::GENERALIZED, "source normals"),
            (
                &with_normals,
                &tn,
                Estimator::Generalized { epsilon: 0.0 },
                "epsilon",
            ),
        ] {
            let err = error_of(source, target, estimator);
            assert!(err.contains(expected), "{estimator:?}: {err}");
        }
        let empty = PointCloud::default();
        assert!(
            icp(
                &empty,
                &tt,
                0.1,
                &Pose::identity(),
                Estimator::PointToPoint,
                Kernel::L2,
                &crit
            )
            .unwrap_err()
            .to_string()
            .contains("empty")
        );
        let mut nan = c.clone();
        nan.points[5].x = f64::NAN;
        assert!(
            icp(
                &nan,
                &tt,
                0.1,
                &Pose::identity(),
                Estimator::PointToPoint,
                Kernel::L2,
                &crit
            )
            .unwrap_err()
            .to_string()
            .contains("NaN")
        );
        assert!(
            icp(
                &c,
                &tt,
                0.0,
                &Pose::identity(),
                Estimator::PointToPoint,
                Kernel::L2,
                &crit
            )
            .is_err()
        );
    }

    #[test]
    fn robust_kernels_resist_outliers() {
        let target = surface_with_normals(3000, 4);
        let tt = Target::new(&target);
        let truth = Pose::new(
            Vector3::new(0.003, 0.002, -0.001),
            Vector3::new(0.02, -0.03, 0.04),
        );
        let mut source = target.transformed(&truth.inverse());
        // A tenth of the points become junk 1-2 cm off the surface.
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        for p in source.points.iter_mut().step_by(10) {
            p.z += 0.01 + 0.01 * rng.random::<f64>();
        }
        let crit = Criteria {
            max_iteration: 60,
            ..Criteria::default()
        };
        // Generalized ICP's residuals along the normal are scaled by about
        // 1/√(2ε): its kernel's width is too.
        for (estimator, width) in [
            (Estimator::PointToPlane, 0.003),
            (Estimator::GENERALIZED, 0.003 / (2.0 * 1e-3f64).sqrt()),
        ] {
            let robust = icp(
                &source,
                &tt,
                0.03,
                &Pose::identity(),
                estimator,
                Kernel::Tukey(width),
                &crit,
            )
            .unwrap();
            let plain = icp(
                &source,
                &tt,
                0.03,
                &Pose::identity(),
                estimator,
                Kernel::L2,
                &crit,
            )
            .unwrap();
            let err = |r: &Registration| {
                omniscan_core::geometry::pose_difference(&r.transformation, &truth).1
            };
            assert!(err(&robust) < 2e-4, "{estimator:?}: {}", err(&robust));
            assert!(
                err(&robust) < err(&plain) / 3.0,
                "{estimator:?}: {} vs {}",
                err(&robust),
                err(&plain)
            );
        }
    }
}
