//! Fixed-radius neighbour search over a uniform grid of cubic cells.
//!
//! Registration asks the same kinds of question of every point of a cloud:
//! normals and colored ICP's intensity gradients want at most k neighbours
//! within a radius (Open3D's hybrid search), FPFH the same with a larger k,
//! and ICP the nearest target point within the correspondence distance. A
//! k-d tree (kiddo, [`crate::neighbors`]) answers each query on its own, with a
//! heap of candidates, which was most of colored ICP's time. With cells at
//! least as wide as the radius, a ball around any point of a cell lies inside
//! that cell's 3x3x3 block, so all points of one cell share one candidate
//! list: it is gathered once per cell and every query in the cell scans it
//! with plain distance arithmetic. The answers are exact (ties aside); a k
//! nearest query whose k-th may lie beyond the block answers with what it is
//! sure of (every point within the block's reach) and a caller that needs
//! more asks the k-d tree. A single query for the nearest two (ICP's fresh
//! searches) reads only the cells its ball reaches.
//!
//! Written here because the crates we use answer one query at a time
//! (kiddo's batch queries still search the tree once per point); the k-d
//! tree stays for what a grid does badly (k nearest without a radius, far
//! outliers). The figures are in docs/results.md.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use nalgebra::Point3;
use rayon::prelude::*;

/// Bits per axis of a packed cell key.
const AXIS_BITS: u32 = 21;
const AXIS_CELLS: i64 = 1 << AXIS_BITS;

/// Multiplicative hashing of packed cell keys: they are already well spread
/// in their low bits, so SipHash's strength buys nothing here.
#[derive(Default)]
struct CellHasher(u64);

impl Hasher for CellHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ b as u64).wrapping_mul(0x100_0000_01b3);
        }
    }
    fn write_u64(&mut self, key: u64) {
        self.0 = (key ^ (key >> 29)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    }
}

type CellMap = HashMap<u64, (u32, u32), BuildHasherDefault<CellHasher>>;

/// What [`Grid::each_point`]'s queries carry from one to the next within
/// a job.
#[derive(Default)]
struct Scratch {
    /// The query's neighbours, (index, squared distance).
    found: Vec<(usize, f64)>,
    /// The k-th nearest distance of the cell's previous query, 0 for none
    /// ([`Grid::knn_map`]'s guess).
    last_kth: f64,
    /// [`Grid::knn_lists`]'s candidates as keys (f32 squared distance bits
    /// above the index), and its answer.
    keys: Vec<u64>,
    list: Vec<u32>,
    split: Vec<u64>,
}

/// A query's nearest points as far as a grid is sure of them, in no
/// particular order: the query's `asked` nearest, or, when fewer lie within
/// the grid's `reach` of it, every point within that reach.
pub struct Nearest<'a> {
    points: &'a mut [(usize, f64)],
    pub asked: usize,
    pub reach: f64,
}

impl Nearest<'_> {
    /// Every point found, (index, squared distance).
    pub fn points(&self) -> &[(usize, f64)] {
        self.points
    }

    /// The `k` nearest, in no particular order, if the grid is sure of that
    /// many.
    pub fn first(&mut self, k: usize) -> Option<&[(usize, f64)]> {
        if self.points.len() < k {
            return None;
        }
        keep_nearest_in(self.points, k);
        Some(&self.points[..k])
    }

    /// Open3D's hybrid answer, in no particular order: the nearest within
    /// `radius`, at most as many as were asked for, if the grid is sure of
    /// them.
    pub fn within(&mut self, radius: f64) -> Option<&[(usize, f64)]> {
        if self.points.len() < self.asked && radius > self.reach {
            return None;
        }
        let mut inside = 0;
        for m in 0..self.points.len() {
            if self.points[m].1 <= radius * radius {
                self.points.swap(inside, m);
                inside += 1;
            }
        }
        Some(&self.points[..inside])
    }
}

/// Points bucketed into cubic cells; see the module documentation.
#[derive(Clone)]
pub struct Grid {
    cell: f64,
    origin: [f64; 3],
    /// Where each cell's points are in `sorted`/`ids`: a dense table of
    /// starts when the cloud's box holds few enough cells, else a map from
    /// packed cell key to range (clouds with far-flung outliers).
    dense: Option<DenseCells>,
    cells: CellMap,
    /// The points in cell order, and the original index of each.
    sorted: Vec<[f64; 3]>,
    ids: Vec<u32>,
}

/// Cells counted along x, y and z; `starts[c]..starts[c + 1]` is the range of
/// cell `c = (z·ny + y)·nx + x`.
#[derive(Clone)]
struct DenseCells {
    dims: [i64; 3],
    starts: Vec<u32>,
}

/// A query's candidates: the points of the 3x3x3 block of cells around it,
/// coordinates apart so the distance loop vectorises.
#[derive(Default)]
struct Candidates {
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
    ids: Vec<u32>,
    /// Squared distances to the current query.
    d2: Vec<f64>,
}

/// What [`Grid::each_point`] gathers of a block, once for all the points
/// of its centre cell.
trait Block: Default + Send {
    fn gather(&mut self, grid: &Grid, centre: [i64; 3]);
}

impl Block for Candidates {
    fn gather(&mut self, grid: &Grid, centre: [i64; 3]) {
        let columns = [&mut self.x, &mut self.y, &mut self.z];
        grid.gather_columns(centre, columns, &mut self.ids, |_, v| v);
    }
}

/// A block's points in f32, relative to the grid's origin, for a query
/// that accounts for the rounding ([`Grid::knn_lists`]): four distances to
/// a vector instruction where f64 gives two, and keys of one word.
#[derive(Default)]
struct CandidatesF32 {
    x: Vec<f32>,
    y: Vec<f32>,
    z: Vec<f32>,
    ids: Vec<u32>,
    d2: Vec<f32>,
}

impl Block for CandidatesF32 {
    fn gather(&mut self, grid: &Grid, centre: [i64; 3]) {
        let o = grid.origin;
        let columns = [&mut self.x, &mut self.y, &mut self.z];
        grid.gather_columns(centre, columns, &mut self.ids, |a, v| (v - o[a]) as f32);
    }
}

impl CandidatesF32 {
    /// Squared distances to `q`, four to a vector instruction.
    fn measure(&mut self, q: [f32; 3]) {
        self.d2.clear();
        self.d2
            .extend(self.x.iter().zip(&self.y).zip(&self.z).map(|((x, y), z)| {
                let (dx, dy, dz) = (x - q[0], y - q[1], z - q[2]);
                dx * dx + dy * dy + dz * dz
            }));
    }

    /// The measured candidates within squared distance `r2`, as keys: the
    /// distance's bits (which order like the distances, none being
    /// negative) above the index. Branch-free, as [`Candidates::within`].
    fn keys_within(&self, r2: f32, keys: &mut Vec<u64>) {
        keys.resize(self.ids.len(), 0);
        let mut kept = 0;
        for (slot, (&d, &id)) in self.d2.iter().zip(&self.ids).enumerate() {
            keys[kept.min(slot)] = (d.to_bits() as u64) << 32 | id as u64;
            kept += (d <= r2) as usize;
        }
        keys.truncate(kept);
    }
}

impl Candidates {
    fn measure(&mut self, p: &[f64; 3]) {
        self.d2.clear();
        self.d2
            .extend(self.x.iter().zip(&self.y).zip(&self.z).map(|((x, y), z)| {
                let (dx, dy, dz) = (x - p[0], y - p[1], z - p[2]);
                dx * dx + dy * dy + dz * dz
            }));
    }

    /// The measured candidates within squared distance `r2`, into `found`.
    ///
    /// Every candidate is written and only those inside advance the end,
    /// so the loop has no branch on the distance: about two in five are
    /// kept, in no order the predictor can learn, and the filtering
    /// version's mispredictions were most of its time (docs/results.md).
    fn within(&self, r2: f64, found: &mut Vec<(usize, f64)>) {
        found.resize(self.d2.len(), (0, 0.0));
        let mut kept = 0;
        for ((slot, &d), &id) in (0..found.len()).zip(&self.d2).zip(&self.ids) {
            // `kept` never passes `slot`; the `min` tells the compiler so.
            found[kept.min(slot)] = (id as usize, d);
            kept += (d <= r2) as usize;
        }
        found.truncate(kept);
    }
}

/// An order of `points` in which neighbours in space are mostly neighbours
/// in the order: the Z-order (Morton) curve through cells 1/255 of the
/// bounding box's longest side, points of one cell in index order.
///
/// ICP runs over its source in this order, and a target keeps its points
/// in it, so that consecutive queries read the neighbour lists and
/// coordinates of nearby target points one after another. A cloud's stored
/// order can jump across it: marching cubes' vertex order, or splat centres
/// after densification. The keys are sorted by radix, three times faster
/// than `par_sort_unstable` here (docs/results.md).
pub fn coherent_order(points: &[Point3<f64>]) -> Vec<u32> {
    const BITS: u32 = 8;
    let (lo, hi) = bounds(points);
    let span = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
    let scale = if span > 0.0 {
        ((1 << BITS) - 1) as f64 / span
    } else {
        0.0
    };
    // A cell number with two zero bits between its bits.
    let spread = |v: f64| {
        // Truncation is the floor here: the clamp leaves no negative value.
        let mut x = if v.is_finite() {
            v.clamp(0.0, ((1 << BITS) - 1) as f64) as u64
        } else {
            0
        };
        x = (x | x << 16) & 0x0300_00ff;
        x = (x | x << 8) & 0x0300_f00f;
        x = (x | x << 4) & 0x030c_30c3;
        (x | x << 2) & 0x0924_9249
    };
    // The Morton key above the index, sorted by radix, eight bits a pass.
    let mut keyed: Vec<u64> = points
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let [x, y, z] = [0, 1, 2].map(|a| spread((p[a] - lo[a]) * scale));
            (x | y << 1 | z << 2) << 32 | i as u64
        })
        .collect();
    let mut spare = vec![0u64; keyed.len()];
    for shift in (32..32 + 3 * BITS).step_by(8) {
        let mut starts = [0usize; 257];
        for &k in &keyed {
            starts[(k >> shift & 0xff) as usize + 1] += 1;
        }
        for b in 1..257 {
            starts[b] += starts[b - 1];
        }
        for &k in &keyed {
            let slot = &mut starts[(k >> shift & 0xff) as usize];
            spare[*slot] = k;
            *slot += 1;
        }
        std::mem::swap(&mut keyed, &mut spare);
    }
    keyed.into_iter().map(|k| k as u32).collect()
}

/// `v.floor() as i64` (saturating) for a finite `v`, without the call to
/// libm's `floor` that baseline x86-64 (no SSE4.1 rounding) compiles
/// `f64::floor` to: 1% of point-to-plane ICP, three calls per grid query.
fn floor_to_int(v: f64) -> i64 {
    let toward_zero = v as i64;
    toward_zero.saturating_sub(((toward_zero as f64) > v) as i64)
}

/// The bounding box of the finite points (inverted when there are none).
fn bounds(points: &[Point3<f64>]) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points.iter().filter(|p| p.iter().all(|c| c.is_finite())) {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    (lo, hi)
}

fn distance2(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    let (dx, dy, dz) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    dx * dx + dy * dy + dz * dz
}

impl Grid {
    /// Buckets `points` into cells of side at least `cell` (wider when the
    /// cloud spans more than 2²¹ cells along an axis).
    pub fn new(points: &[Point3<f64>], cell: f64) -> Grid {
        let (mut lo, mut hi) = bounds(points);
        if lo[0] > hi[0] {
            lo = [0.0; 3];
            hi = [0.0; 3];
        }
        let span = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
        let cell = if cell.is_finite() && cell > 0.0 {
            cell
        } else {
            span.max(1.0)
        }
        .max(span / (AXIS_CELLS - 2) as f64);
        let mut grid = Grid {
            cell,
            origin: lo,
            dense: None,
            cells: CellMap::default(),
            sorted: Vec::new(),
            ids: Vec::new(),
        };
        let dims: [i64; 3] = std::array::from_fn(|a| ((hi[a] - lo[a]) / cell).floor() as i64 + 1);
        let count = dims.iter().product::<i64>();
        let order: Vec<u32> = if count <= 16 * points.len() as i64 + 65_536 {
            // A counting sort by dense cell number, in the same (z, y, x)
            // order as packed keys and, within a cell, in index order: the
            // order the sort below gives (`Grid::new` on 32k points: 1.4 →
            // 1.0 ms).
            let cells: Vec<u32> = points
                .par_iter()
                .map(|p| {
                    let [x, y, z] = grid.coords_of(&[p.x, p.y, p.z]).map(|v| v.max(0));
                    ((z * dims[1] + y) * dims[0] + x) as u32
                })
                .collect();
            let mut starts = vec![0u32; count as usize + 1];
            for &c in &cells {
                starts[c as usize + 1] += 1;
            }
            for c in 1..starts.len() {
                starts[c] += starts[c - 1];
            }
            let mut order = vec![0u32; points.len()];
            for (i, &c) in cells.iter().enumerate() {
                order[starts[c as usize] as usize] = i as u32;
                starts[c as usize] += 1;
            }
            // Each cell's start moved to its end, the next cell's start.
            starts.rotate_right(1);
            starts[0] = 0;
            grid.dense = Some(DenseCells { dims, starts });
            order
        } else {
            let mut keyed: Vec<(u64, u32)> = points
                .iter()
                .enumerate()
                .map(|(i, p)| (grid.key_of(&[p.x, p.y, p.z]), i as u32))
                .collect();
            keyed.par_sort_unstable();
            let mut start = 0;
            for k in 1..=keyed.len() {
                if k == keyed.len() || keyed[k].0 != keyed[start].0 {
                    grid.cells.insert(keyed[start].0, (start as u32, k as u32));
                    start = k;
                }
            }
            keyed.into_iter().map(|(_, i)| i).collect()
        };
        grid.sorted = order
            .iter()
            .map(|&i| {
                let p = points[i as usize];
                [p.x, p.y, p.z]
            })
            .collect();
        grid.ids = order;
        grid
    }

    /// Whether the grid answers queries that want up to `max_nn` neighbours
    /// more cheaply than a k-d tree: not when a radius wide against the
    /// cloud puts most of it in every block.
    pub fn suits(&self, max_nn: usize) -> bool {
        self.mean_candidates() <= 8.0 * max_nn as f64 + 256.0
    }

    /// How many candidates a query at a point of the grid scans, on average.
    fn mean_candidates(&self) -> f64 {
        if self.sorted.is_empty() {
            return 0.0;
        }
        let mut total = 0usize;
        let mut k = 0;
        while k < self.sorted.len() {
            let c = self.coords_of(&self.sorted[k]);
            let (_, end) = self.row(c[0], c[0], c[1], c[2]).unwrap_or((k, k + 1));
            let mut block = 0;
            self.block(c, |s, e| block += e - s);
            total += block * (end - k);
            k = end.max(k + 1);
        }
        total as f64 / self.sorted.len() as f64
    }

    /// The side of a cell: queries may use any radius up to it.
    pub fn cell(&self) -> f64 {
        self.cell
    }

    fn coords_of(&self, p: &[f64; 3]) -> [i64; 3] {
        // Non-finite points land in cell 0; validation rejects them upstream.
        std::array::from_fn(|a| {
            let c = (p[a] - self.origin[a]) / self.cell;
            if c.is_finite() {
                floor_to_int(c).clamp(-1, AXIS_CELLS - 2)
            } else {
                0
            }
        })
    }

    fn pack(c: [i64; 3]) -> Option<u64> {
        c.iter()
            .all(|&v| (0..AXIS_CELLS).contains(&v))
            .then(|| c[0] as u64 | (c[1] as u64) << AXIS_BITS | (c[2] as u64) << (2 * AXIS_BITS))
    }

    fn key_of(&self, p: &[f64; 3]) -> u64 {
        Self::pack(self.coords_of(p).map(|v| v.max(0))).unwrap_or(0)
    }

    /// Calls `visit` with the range of points of each of the 9 rows of the
    /// block around `centre` (the cells x−1, x, x+1 of a row are next to each
    /// other in cell order).
    fn block(&self, centre: [i64; 3], mut visit: impl FnMut(usize, usize)) {
        for dz in -1..=1 {
            for dy in -1..=1 {
                let (y, z) = (centre[1] + dy, centre[2] + dz);
                if let Some((s, e)) = self.row(centre[0] - 1, centre[0] + 1, y, z) {
                    visit(s, e);
                }
            }
        }
    }

    /// The points of cells `x0..=x1` of row (`y`, `z`), if any.
    fn row(&self, x0: i64, x1: i64, y: i64, z: i64) -> Option<(usize, usize)> {
        let (s, e) = match &self.dense {
            Some(d) => {
                let (x0, x1) = (x0.max(0), x1.min(d.dims[0] - 1));
                if !(0..d.dims[1]).contains(&y) || !(0..d.dims[2]).contains(&z) || x0 > x1 {
                    return None;
                }
                let base = (z * d.dims[1] + y) * d.dims[0];
                (
                    d.starts[(base + x0) as usize],
                    d.starts[(base + x1) as usize + 1],
                )
            }
            None => (x0..=x1)
                .filter_map(|x| Self::pack([x, y, z]).and_then(|k| self.cells.get(&k)))
                .fold((u32::MAX, 0), |(s, e), &(cs, ce)| (s.min(cs), e.max(ce))),
        };
        (s < e).then_some((s as usize, e as usize))
    }

    /// The points of `centre`'s block, one column per axis (each
    /// coordinate as `to(axis, value)`), and their indices.
    fn gather_columns<V>(
        &self,
        centre: [i64; 3],
        mut columns: [&mut Vec<V>; 3],
        ids: &mut Vec<u32>,
        to: impl Fn(usize, f64) -> V,
    ) {
        columns.iter_mut().for_each(|c| c.clear());
        ids.clear();
        self.block(centre, |s, e| {
            for (a, column) in columns.iter_mut().enumerate() {
                column.extend(self.sorted[s..e].iter().map(|p| to(a, p[a])));
            }
            ids.extend_from_slice(&self.ids[s..e]);
        });
    }

    /// How far `p` (in the cell `c`) is from the outside of `c`'s block:
    /// nothing nearer than this lies outside it.
    fn block_reach(&self, c: [i64; 3], p: &[f64; 3]) -> f64 {
        (0..3)
            .map(|a| {
                let low = self.origin[a] + (c[a] - 1) as f64 * self.cell;
                let high = self.origin[a] + (c[a] + 2) as f64 * self.cell;
                (p[a] - low).min(high - p[a])
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// Runs `per_point(index, position, candidates, reach, scratch)` for
    /// every point of the grid, the points of one cell sharing that cell's
    /// candidates (gathered once, measured by `per_point`), and returns the
    /// results by the points' original index. `reach`: nothing nearer than
    /// it lies outside the block. Each result is cloned once: share large
    /// ones (FPFH's neighbour lists are `Arc`s).
    fn each_point<B: Block, T: Send + Sync + Clone>(
        &self,
        per_point: impl Fn(usize, &[f64; 3], &mut B, f64, &mut Scratch) -> T + Sync,
    ) -> Vec<T> {
        // The points are in cell order: a run of one cell's points shares
        // its candidates. Results are collected in that order and then
        // cloned into point order, each written once where it ends up.
        // Collecting per cell, concatenating, and scattering through a
        // vector of options wrote every result four times, into fresh
        // pages each time.
        let cells: Vec<[i64; 3]> = self.sorted.iter().map(|p| self.coords_of(p)).collect();
        let query = |cand: &mut B, scratch: &mut Scratch, k: usize| {
            let p = &self.sorted[k];
            let reach = self.block_reach(cells[k], p);
            per_point(self.ids[k] as usize, p, cand, reach, scratch)
        };
        let by_cell: Vec<T> = (0..self.sorted.len())
            .into_par_iter()
            .map_init(
                || (B::default(), Scratch::default(), None),
                |(cand, scratch, cell), k| {
                    if *cell != Some(cells[k]) {
                        cand.gather(self, cells[k]);
                        *cell = Some(cells[k]);
                        // A query may start from what the one before it in
                        // its cell found (`knn_map`'s guess), and that guess
                        // decides the order its neighbours come out in: a
                        // cell's first query starts afresh, and a job that
                        // begins inside a cell repeats the query before it,
                        // so the results do not depend on where the work
                        // was split.
                        scratch.last_kth = 0.0;
                        if k > 0 && cells[k - 1] == cells[k] {
                            drop(query(cand, scratch, k - 1));
                        }
                    }
                    query(cand, scratch, k)
                },
            )
            .collect();
        let mut position = vec![0u32; self.ids.len()];
        for (k, &i) in self.ids.iter().enumerate() {
            position[i as usize] = k as u32;
        }
        position
            .par_iter()
            .map(|&k| by_cell[k as usize].clone())
            .collect()
    }

    /// For every point `i`, `f(i, neighbours)` with the at most `max_nn`
    /// nearest points within `radius`, as (index, squared distance): Open3D's
    /// hybrid search, for the whole cloud at once. The point itself comes
    /// first, the others in no particular order (but the same on every run).
    /// `radius` must not exceed [`Grid::cell`] (it is clamped to it).
    pub fn hybrid_map<T: Send + Sync + Clone>(
        &self,
        radius: f64,
        max_nn: usize,
        f: impl Fn(usize, &[(usize, f64)]) -> T + Sync,
    ) -> Vec<T> {
        let r2 = radius.min(self.cell).powi(2);
        self.each_point(|i, p, cand: &mut Candidates, _, scratch| {
            cand.measure(p);
            let found = &mut scratch.found;
            cand.within(r2, found);
            keep_nearest(found, max_nn);
            if let Some(own) = found.iter().position(|x| x.0 == i) {
                found.swap(0, own);
            }
            f(i, found)
        })
    }

    /// For every point `i`, `f(i, nearest)` with its `k` nearest points
    /// (itself included, in no particular order), as far as the grid is
    /// sure of them: where fewer than `k` lie within the block's reach,
    /// every point within it (see [`Nearest`]); ask a k-d tree for more.
    pub fn knn_map<T: Send + Sync + Clone>(
        &self,
        k: usize,
        f: impl Fn(usize, Nearest<'_>) -> T + Sync,
    ) -> Vec<T> {
        self.each_point(|i, p, cand: &mut Candidates, reach, scratch| {
            cand.measure(p);
            let found = &mut scratch.found;
            // Neighbouring queries (one cell's, in turn in one job) have
            // about the same k-th distance: the candidates within a little
            // more than the last one's hold this query's k nearest if there
            // are k of them, and are far fewer to select from than all
            // those within reach. The guess changes the speed and the order
            // the neighbours come out in, not which they are.
            let guess = scratch.last_kth * 1.25;
            if guess < reach {
                cand.within(guess * guess, found);
            }
            if guess >= reach || found.len() < k {
                // Only points within reach can be among a certain answer.
                cand.within(reach * reach, found);
            }
            // Selected, not sorted: the callers need only sets.
            keep_nearest(found, k);
            // Set even without k found (to no guess): a query that
            // `each_point` repeats must leave the guess it left the first
            // time.
            scratch.last_kth = match found.len() == k && k > 0 {
                true => found.iter().fold(0.0f64, |m, x| m.max(x.1)).sqrt(),
                false => 0.0,
            };
            f(
                i,
                Nearest {
                    points: found,
                    asked: k,
                    reach,
                },
            )
        })
    }

    /// For every point `i`, `f(i, list, reach)`: `list` (in no particular
    /// order; `i` among it unless `k` others lie at distance 0) holds every
    /// point nearer than `reach` to `i`, at most `k` of them: `i`'s `k`
    /// nearest by f32 distance (ties to the lower index), and `reach` a
    /// little less than the farthest of them; or, where fewer than `k` lie
    /// within the block's reach, all of those, and that reach.
    ///
    /// This is ICP's neighbour graph ([`crate::icp`]), which needs lists
    /// that hold every point within their reach, not exact nearest sets.
    /// Distances in f32, with `reach` short by a bound on their rounding,
    /// measured four to a vector instruction and then compacted, and the
    /// selection split at the last query's k-th distance first: faster
    /// than [`Grid::knn_map`]'s exact f64 answer (docs/results.md).
    pub fn knn_lists<T: Send + Sync + Clone>(
        &self,
        k: usize,
        f: impl Fn(usize, &[u32], f64) -> T + Sync,
    ) -> Vec<T> {
        // Coordinates relative to the origin are at most `scale`; rounding
        // them and a distance `d` to f32 errs by less than 2⁻²⁰·(scale + d)
        // (about 2⁻²²·(scale + d) at worst: both ends' rounding, the
        // subtractions, the sum).
        let scale = self
            .sorted
            .iter()
            .flat_map(|p| (0..3).map(move |a| (p[a] - self.origin[a]).abs()))
            .fold(0.0f64, f64::max);
        let error = |d: f64| (scale + d) * 2f64.powi(-20);
        self.each_point(|i, p, cand: &mut CandidatesF32, reach, scratch| {
            let q: [f32; 3] = std::array::from_fn(|a| (p[a] - self.origin[a]) as f32);
            cand.measure(q);
            let keys = &mut scratch.keys;
            // As in `knn_map`: the previous query's k-th distance, a little
            // more, usually holds k candidates and far fewer than the reach.
            // Any guess gives the same lists.
            let guess = scratch.last_kth * 1.25;
            if guess < reach {
                cand.keys_within((guess * guess) as f32, keys);
            }
            if guess >= reach || keys.len() < k {
                // Every point within reach, and a few just beyond.
                let beyond = reach + error(reach);
                cand.keys_within((beyond * beyond) as f32, keys);
            }
            let covers = if keys.len() >= k && k > 0 {
                if keys.len() > k {
                    keep_least(keys, k, scratch.last_kth, &mut scratch.split);
                }
                let kth = f32::from_bits((keys.iter().max().copied().unwrap_or(0) >> 32) as u32);
                let kth = (kth as f64).sqrt();
                scratch.last_kth = kth;
                // Every other candidate is no nearer than the k-th in f32.
                (kth - error(kth)).min(reach).max(0.0)
            } else {
                scratch.last_kth = 0.0;
                reach
            };
            scratch.list.clear();
            scratch.list.extend(keys.iter().map(|&key| key as u32));
            f(i, &scratch.list, covers)
        })
    }

    /// The nearest and second-nearest points to `q` within `radius` (at most
    /// [`Grid::cell`]): (index, squared distance) of the nearest, if any, and
    /// the second's squared distance (infinite if none). Only the cells the
    /// ball reaches are read: a small radius reads a few of the 27.
    pub fn nearest_two(&self, q: &Point3<f64>, radius: f64) -> (Option<(usize, f64)>, f64) {
        let p = [q.x, q.y, q.z];
        let r = radius.min(self.cell);
        let centre = self.coords_of(&p);
        let low = self.coords_of(&p.map(|v| v - r));
        let high = self.coords_of(&p.map(|v| v + r));
        let low: [i64; 3] = std::array::from_fn(|a| low[a].max(centre[a] - 1));
        let high: [i64; 3] = std::array::from_fn(|a| high[a].min(centre[a] + 1));
        let mut two = NearestTwo::default();
        for z in low[2]..=high[2] {
            for y in low[1]..=high[1] {
                if let Some((s, e)) = self.row(low[0], high[0], y, z) {
                    for k in s..e {
                        two.offer(distance2(&p, &self.sorted[k]), self.ids[k] as usize);
                    }
                }
            }
        }
        two.within(r * r)
    }
}

/// Open3D's hybrid search (at most `max_nn` nearest within `radius`) for
/// every point of `points`: `f(i, neighbours)`, the point itself first. On a
/// grid where that is cheap, else (a radius wide against the cloud puts most
/// of it in every block) on a k-d tree, nearest first.
pub fn hybrid_search<T: Send + Sync + Clone>(
    points: &[Point3<f64>],
    radius: f64,
    max_nn: usize,
    f: impl Fn(usize, &[(usize, f64)]) -> T + Sync,
) -> Vec<T> {
    let grid = Grid::new(points, radius);
    if grid.suits(max_nn) {
        return grid.hybrid_map(radius, max_nn, f);
    }
    let tree = crate::neighbors::Neighbors::new(points);
    points
        .par_iter()
        .enumerate()
        .map(|(i, p)| f(i, &tree.hybrid(p, radius, max_nn)))
        .collect()
}

/// The nearest (ties to the lower index) and second-nearest of the
/// squared distances offered to it.
///
/// Offers take no branch: which offer improves on the nearest is as good as
/// random, and a branch on it was mispredicted two or three times a query
/// that measures a few dozen candidates (docs/results.md).
struct NearestTwo {
    /// The nearest's index, `usize::MAX` before any offer.
    best: usize,
    d1: f64,
    d2: f64,
}

impl Default for NearestTwo {
    fn default() -> Self {
        NearestTwo {
            best: usize::MAX,
            d1: f64::INFINITY,
            d2: f64::INFINITY,
        }
    }
}

impl NearestTwo {
    fn offer(&mut self, d: f64, id: usize) {
        // (d, id) before (d1, best); an infinite first offer still wins,
        // against no nearest.
        let better = (d < self.d1) | ((d == self.d1) & (id < self.best));
        // In every case the second is the lesser of the old second and the
        // greater of the old nearest and the offer (a NaN offer changes
        // nothing).
        let greater = if d < self.d1 { self.d1 } else { d };
        self.d2 = if greater < self.d2 { greater } else { self.d2 };
        self.d1 = if d < self.d1 { d } else { self.d1 };
        let mask = (better as usize).wrapping_neg();
        self.best ^= (self.best ^ id) & mask;
    }

    /// (index, squared distance) of the nearest within `r2`, if any, and the
    /// second's squared distance (infinite if not within `r2`).
    fn within(self, r2: f64) -> (Option<(usize, f64)>, f64) {
        match self.best {
            i if i != usize::MAX && self.d1 <= r2 => (
                Some((i, self.d1)),
                if self.d2 <= r2 {
                    self.d2
                } else {
                    f64::INFINITY
                },
            ),
            _ => (None, f64::INFINITY),
        }
    }
}

/// Keeps the `k` least of `keys` (more than `k`), in no particular order,
/// given a distance `near` that about `k` of them are within (0 for none).
///
/// Splitting at `near` first, without branches, leaves a far smaller
/// selection, often none: a quickselect of all the keys was a third of the
/// neighbour graph's time, most of it mispredicted branches.
fn keep_least(keys: &mut Vec<u64>, k: usize, near: f64, split: &mut Vec<u64>) {
    let n = keys.len();
    let bound = ((near * near) as f32).to_bits() as u64;
    let inside = if near > 0.0 {
        // Those within `near` to the front of `split`, the others to its
        // back, each written to both ends' next slots.
        split.resize(n + 1, 0);
        let (mut front, mut back) = (0, n);
        for &key in keys.iter() {
            let within = (key >> 32 <= bound) as usize;
            split[front] = key;
            split[back] = key;
            front += within;
            back -= 1 - within;
        }
        // The others are at `back + 1..=n`, and `back` is now `front`.
        keys[..front].copy_from_slice(&split[..front]);
        keys[front..].copy_from_slice(&split[front + 1..]);
        front
    } else {
        0
    };
    match inside.cmp(&k) {
        std::cmp::Ordering::Equal => {}
        std::cmp::Ordering::Greater => {
            keys[..inside].select_nth_unstable(k - 1);
        }
        std::cmp::Ordering::Less => {
            keys[inside..].select_nth_unstable(k - inside - 1);
        }
    }
    keys.truncate(k);
}

fn by_distance(a: &(usize, f64), b: &(usize, f64)) -> std::cmp::Ordering {
    a.1.total_cmp(&b.1).then(a.0.cmp(&b.0))
}

/// Keeps the `k` nearest of `found` (ties by index, so the result does not
/// depend on the order the candidates came in), in no particular order.
fn keep_nearest(found: &mut Vec<(usize, f64)>, k: usize) {
    keep_nearest_in(found, k);
    found.truncate(k);
}

/// Moves the `k` nearest (ties to the lower index) to the front.
fn keep_nearest_in(found: &mut [(usize, f64)], k: usize) {
    if found.len() > k && k > 0 {
        found.select_nth_unstable_by(k - 1, by_distance);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn cloud(n: usize, seed: u64) -> Vec<Point3<f64>> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        // A curved sheet with a dense blob, so cells hold very different counts.
        (0..n)
            .map(|i| {
                if i % 5 == 0 {
                    Point3::new(
                        0.3 + rng.random_range(-0.02..0.02),
                        0.1 + rng.random_range(-0.02..0.02),
                        rng.random_range(-0.02..0.02),
                    )
                } else {
                    let (u, v): (f64, f64) =
                        (rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
                    Point3::new(u, v, 0.3 * (2.0 * u).sin() * v)
                }
            })
            .collect()
    }

    #[test]
    fn coherent_order_is_a_permutation_that_keeps_neighbours_together() {
        // Random order (as splat centres after densification), a duplicated
        // point, and a point off the cloud's scale.
        let mut points = cloud(5000, 4);
        points.push(points[17]);
        points.push(Point3::new(40.0, -3.0, 2.0));
        let order = coherent_order(&points);
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert!(sorted.iter().enumerate().all(|(i, &o)| o as usize == i));
        // Deterministic, and ties in index order.
        assert_eq!(order, coherent_order(&points));
        let at = |i: u32| order.iter().position(|&o| o == i).unwrap();
        assert!(at(17) < at(5000));
        // Consecutive points lie far closer together than in the input.
        let points = &points[..5000];
        let order = coherent_order(points);
        let step = |ids: &mut dyn Iterator<Item = usize>| {
            let ids: Vec<usize> = ids.collect();
            let total: f64 = ids
                .windows(2)
                .map(|w| (points[w[0]] - points[w[1]]).norm())
                .sum();
            total / (ids.len() - 1) as f64
        };
        let given = step(&mut (0..5000));
        let coherent = step(&mut order.iter().map(|&o| o as usize));
        assert!(coherent < given / 10.0, "{coherent} against {given}");
        // Nothing to order, and a cloud of one point.
        assert!(coherent_order(&[]).is_empty());
        assert_eq!(coherent_order(&[Point3::new(1.0, 2.0, 3.0)]), vec![0]);
    }

    #[test]
    fn floor_to_int_is_the_floor() {
        let values = [
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            2.999_999,
            -2.000_001,
            1e15 + 0.5,
            -1e15 - 0.5,
            4.5e15,
            -4.5e15,
            1e300,
            -1e300,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
        ];
        for v in values {
            assert_eq!(floor_to_int(v), v.floor() as i64, "{v}");
        }
    }

    fn brute(points: &[Point3<f64>], q: &Point3<f64>) -> Vec<(usize, f64)> {
        let mut all: Vec<(usize, f64)> = points
            .iter()
            .enumerate()
            .map(|(i, p)| (i, (p - q).norm_squared()))
            .collect();
        all.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
        all
    }

    #[test]
    fn batched_queries_equal_brute_force() {
        let points = cloud(3000, 1);
        let grid = Grid::new(&points, 0.08);
        let hybrid = grid.hybrid_map(0.07, 12, |_, n| n.to_vec());
        let knn = grid.knn_map(9, |_, mut n| {
            n.first(9).map(|found| {
                let mut found = found.to_vec();
                found.sort_by(by_distance);
                found
            })
        });
        let mut sure = 0;
        for (i, p) in points.iter().enumerate() {
            let all = brute(&points, p);
            let expect: Vec<(usize, f64)> = all
                .iter()
                .copied()
                .filter(|x| x.1 <= 0.07 * 0.07)
                .take(12)
                .collect();
            assert_eq!(
                hybrid[i][0].0, i,
                "point {i} comes first in its own neighbourhood"
            );
            let mut found = hybrid[i].clone();
            found.sort_by(by_distance);
            assert_eq!(found, expect, "hybrid search of point {i}");
            if let Some(found) = &knn[i] {
                sure += 1;
                assert_eq!(found[..], all[..9], "9 nearest of point {i}");
            }
        }
        // Most points are answered by the grid; the rest fall back.
        assert!(sure > 2000, "only {sure} of 3000 answered");
    }

    #[test]
    fn knn_lists_hold_every_point_within_their_reach() {
        // The sheet and blob; the same with an outlier 2.5 km away that puts
        // the grid's origin there, so that coordinates from it keep only
        // about 0.2 mm in f32 (the rounding bound must cover that); and 40
        // copies each of a few points (ties everywhere).
        let points = cloud(2000, 4);
        let mut far = points.clone();
        far.push(Point3::new(-2500.0, 0.0, 0.0));
        let copies: Vec<Point3<f64>> = (0..400)
            .map(|i| Point3::new(0.01 * (i % 10) as f64, 0.0, 0.0))
            .collect();
        let k = 9;
        for (name, points, cell) in [
            ("sheet", &points, 0.08),
            ("far", &far, 0.08),
            ("copies", &copies, 0.02),
        ] {
            let grid = Grid::new(points, cell);
            let lists = grid.knn_lists(k, |_, list, reach| (list.to_vec(), reach));
            let mut full = 0;
            for (i, p) in points.iter().enumerate() {
                let (list, reach) = &lists[i];
                assert!(list.len() <= k, "{name}: point {i} lists {}", list.len());
                let mut sorted = list.clone();
                sorted.sort_unstable();
                sorted.dedup();
                assert_eq!(
                    sorted.len(),
                    list.len(),
                    "{name}: point {i} lists a point twice"
                );
                let all = brute(points, p);
                for &(j, d2) in &all {
                    if d2.sqrt() >= *reach {
                        break;
                    }
                    assert!(
                        list.contains(&(j as u32)),
                        "{name}: point {j} is within point {i}'s reach and not listed"
                    );
                }
                if list.len() == k {
                    full += 1;
                    // No more than the rounding bound short of the k-th
                    // nearest distance.
                    let kth = all[k - 1].1.sqrt();
                    let bound = (kth + 2.5e3) * 2f64.powi(-20);
                    assert!(
                        *reach <= kth + bound && *reach >= kth - 2.0 * bound,
                        "{name}: point {i} reach {reach} against {kth}"
                    );
                }
            }
            assert!(full > points.len() / 2, "{name}: only {full} full lists");
        }
    }

    #[test]
    fn keep_least_keeps_the_least_keys_whatever_the_split() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        let mut split = Vec::new();
        for _ in 0..2000 {
            let n = rng.random_range(2..60);
            let k = rng.random_range(1..n);
            // Few distinct distances, so ties between keys' distances are common.
            let keys: Vec<u64> = (0..n)
                .map(|id| {
                    ((rng.random_range(0..20) as f32 * 0.01).to_bits() as u64) << 32 | id as u64
                })
                .collect();
            let mut expected = keys.clone();
            expected.sort_unstable();
            expected.truncate(k);
            for near in [0.0, 0.05, 0.1, 0.19, 1.0, rng.random_range(0.0..0.2)] {
                let mut kept = keys.clone();
                keep_least(&mut kept, k, near, &mut split);
                kept.sort_unstable();
                assert_eq!(kept, expected, "{k} of {n} split at {near}");
            }
        }
    }

    #[test]
    fn nearest_two_equals_brute_force_for_outside_queries() {
        let points = cloud(2000, 2);
        let grid = Grid::new(&points, 0.05);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let queries: Vec<Point3<f64>> = (0..500)
            .map(|_| {
                Point3::new(
                    rng.random_range(-1.2..1.2),
                    rng.random_range(-1.2..1.2),
                    rng.random_range(-0.4..0.4),
                )
            })
            .chain([Point3::new(50.0, -80.0, 3.0), Point3::new(-1.02, 0.0, 0.0)])
            .collect();
        // The whole block, and balls that reach only some of its cells.
        for radius in [0.05, 0.035, 0.02, 0.004] {
            let r2 = radius * radius;
            for (trial, q) in queries.iter().enumerate() {
                let all = brute(&points, q);
                let (first, second) = grid.nearest_two(q, radius);
                if all[0].1 <= r2 {
                    assert_eq!(first, Some(all[0]), "query {trial} within {radius}");
                    let s = if all[1].1 <= r2 {
                        all[1].1
                    } else {
                        f64::INFINITY
                    };
                    assert_eq!(second, s, "query {trial} within {radius}");
                } else {
                    assert_eq!(first, None, "query {trial} within {radius}");
                }
            }
        }
    }

    #[test]
    fn empty_and_degenerate_inputs() {
        let grid = Grid::new(&[], 0.1);
        assert!(grid.hybrid_map(0.1, 5, |_, n| n.len()).is_empty());
        assert_eq!(
            grid.nearest_two(&Point3::origin(), 0.1),
            (None, f64::INFINITY)
        );
        // One point, a zero cell size and a huge extent still work.
        let one = Grid::new(&[Point3::new(1.0, 2.0, 3.0)], 0.0);
        assert_eq!(
            one.hybrid_map(1.0, 5, |_, n| n.to_vec()),
            vec![vec![(0, 0.0)]]
        );
        let far = [Point3::new(-1e9, 0.0, 0.0), Point3::new(1e9, 0.0, 0.0)];
        let grid = Grid::new(&far, 1e-6);
        assert!(grid.cell() > 1e-6);
        assert_eq!(
            grid.knn_map(1, |_, mut n| n.first(1).map(<[_]>::to_vec))[1],
            Some(vec![(1, 0.0)])
        );
    }
}
