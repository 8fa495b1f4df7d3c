//! Binning items into image tiles on every thread, for the tiled
//! rasterizers of the simulator (triangles) and the splat renderer
//! (Gaussians).
//!
//! Runs of items list the tiles they cover on their own threads; each tile
//! then joins its runs' lists in run order, so every tile lists its items in
//! item order, as one serial pass would. (Filled on one thread, the lists
//! took a second of a 3000-step splat training run and a few percent of a
//! simulated capture while the other threads waited.)

use rayon::prelude::*;

/// For each of `tile_count` tiles, the indices of the items that cover it,
/// in increasing order. `tiles_of(i)` gives the tiles item `i` covers, each
/// at most once; runs of `run` items are the units of parallel work.
pub fn bin_in_order<T: IntoIterator<Item = usize>>(
    items: usize,
    tile_count: usize,
    run: usize,
    tiles_of: impl Fn(usize) -> T + Sync,
) -> Vec<Vec<u32>> {
    let run = run.max(1);
    let runs: Vec<Vec<Vec<u32>>> = (0..items.div_ceil(run))
        .into_par_iter()
        .map(|r| {
            let mut lists: Vec<Vec<u32>> = vec![Vec::new(); tile_count];
            for i in r * run..((r + 1) * run).min(items) {
                for tile in tiles_of(i) {
                    lists[tile].push(i as u32);
                }
            }
            lists
        })
        .collect();
    (0..tile_count)
        .into_par_iter()
        .map(|t| {
            runs.iter()
                .flat_map(|lists| lists[t].iter().copied())
                .collect()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_tile_lists_its_items_in_order_whatever_the_runs() {
        // Items covering tiles i % 5 and (i * 3) % 7 of 7 (once when equal).
        let tiles_of = |i: usize| {
            let (a, b) = (i % 5, (i * 3) % 7);
            std::iter::once(a).chain((b != a).then_some(b))
        };
        let mut expected = vec![Vec::new(); 7];
        for i in 0..100 {
            for t in tiles_of(i) {
                expected[t].push(i as u32);
            }
        }
        for run in [1, 3, 64, 100, 1000] {
            assert_eq!(bin_in_order(100, 7, run, tiles_of), expected, "run {run}");
        }
        assert_eq!(bin_in_order(0, 3, 4, tiles_of), vec![Vec::<u32>::new(); 3]);
    }
}
