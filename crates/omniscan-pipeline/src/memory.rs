//! Memory checks before the work that needs it: a view too large for the
//! machine is refused up front with a size that fits, rather than ending in
//! an allocation failure (a SIGABRT after taking ~8 GB, for a 16384² render
//! or a capture whose camera asks for 20000²), and views that fit one at a
//! time but not one per thread are worked on by fewer threads. Results do
//! not depend on the thread count, so fewer threads change only the time.

use anyhow::{Result, bail};

/// Bytes a CPU render holds per pixel: the render's colour, alpha, depth,
/// median depth and contributor count (28), the rasterizer's per-pixel
/// scratch, and the 8-bit image with its PNG encoding. Measured at 73
/// (docs/results.md, "Memory per pixel"), rounded up.
pub const RENDER_BYTES_PER_PIXEL: u64 = 96;

/// Bytes reading a view holds per pixel of its image files' size: the
/// decoded photo, masks and depth before they are shrunk. Measured at
/// about 40, rounded up.
pub const READ_BYTES_PER_PIXEL: u64 = 48;

/// Bytes scoring a view holds per pixel at the compared size: the render,
/// the view, the metrics' target and masks, and SSIM's blurred planes.
/// Measured at about 100 beside [`READ_BYTES_PER_PIXEL`], rounded up.
pub const EVAL_BYTES_PER_PIXEL: u64 = 128;

/// The memory the system can give without swapping, where it says
/// (Linux's /proc/meminfo).
pub fn available() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Gigabytes, for messages.
pub fn gb(bytes: u64) -> f64 {
    bytes as f64 / 1e9
}

/// How many views of `largest` bytes each may be worked on at once, at
/// most `wanted`, with `available` bytes (`None`: the system does not
/// say, and `wanted` it is). Refuses when not even one fits, with
/// `what` (the work, "rendering a 16384x16384 view") and `fits` (what
/// would fit) in the message.
pub fn views_at_once(
    what: &str,
    largest: u64,
    wanted: usize,
    available: Option<u64>,
    fits: impl FnOnce(u64) -> String,
) -> Result<usize> {
    let Some(available) = available else {
        return Ok(wanted.max(1));
    };
    if largest > available {
        bail!(
            "{what} needs about {:.2} GB of memory and {:.2} GB is available: {}",
            gb(largest),
            gb(available),
            fits(available)
        );
    }
    let at_once = (available / largest.max(1)).min(wanted as u64).max(1) as usize;
    if at_once < wanted {
        tracing::info!(
            "{what}: {at_once} views at a time, as {:.2} GB of memory holds no more",
            gb(available)
        );
    }
    Ok(at_once)
}

/// Runs `work` on at most `threads` threads: in a pool of that size when
/// it is fewer than the current pool's.
pub fn with_threads<T: Send>(threads: usize, work: impl FnOnce() -> T + Send) -> Result<T> {
    if threads >= rayon::current_num_threads() {
        return Ok(work());
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    Ok(pool.install(work))
}

/// The largest `width`x`height` with the same aspect that `available`
/// bytes render at `bytes_per_pixel`.
pub fn side_that_fits(width: u32, height: u32, bytes_per_pixel: u64, available: u64) -> (u32, u32) {
    let pixels = (available / bytes_per_pixel) as f64;
    let scale = (pixels / (f64::from(width) * f64::from(height)))
        .sqrt()
        .min(1.0);
    let shrink = |side: u32| ((f64::from(side) * scale).floor() as u32).max(1);
    (shrink(width), shrink(height))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_run_as_many_at_once_as_fit_and_none_that_do_not() {
        let gib = 1u64 << 30;
        assert_eq!(
            views_at_once("x", gib, 8, Some(20 * gib), |_| unreachable!()).unwrap(),
            8
        );
        assert_eq!(
            views_at_once("x", gib, 8, Some(3 * gib), |_| unreachable!()).unwrap(),
            3
        );
        assert_eq!(
            views_at_once("x", gib, 8, None, |_| unreachable!()).unwrap(),
            8
        );
        let error = views_at_once("rendering a big view", 3 * gib, 8, Some(gib), |a| {
            format!("try {a}")
        })
        .unwrap_err()
        .to_string();
        assert!(
            error.starts_with("rendering a big view needs about 3.22 GB"),
            "{error}"
        );
        assert!(error.ends_with(&format!("try {gib}")), "{error}");
    }

    #[test]
    fn the_size_that_fits_keeps_the_aspect_and_fits() {
        let (w, h) = side_that_fits(16384, 8192, 96, 1 << 30);
        assert!(u64::from(w) * u64::from(h) * 96 <= 1 << 30);
        assert!((f64::from(w) / f64::from(h) - 2.0).abs() < 1e-3);
        assert_eq!(side_that_fits(640, 480, 96, 1 << 40), (640, 480));
    }

    #[test]
    fn a_smaller_pool_gives_the_same_result() {
        use rayon::prelude::*;
        let sum = |_: ()| (0..1000u64).into_par_iter().map(|v| v * v).sum::<u64>();
        assert_eq!(with_threads(1, || sum(())).unwrap(), sum(()));
    }
}
