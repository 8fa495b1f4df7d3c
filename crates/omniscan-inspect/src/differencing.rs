//! The paper's two comparisons of a pair of aligned models.
//!
//! Pixel differencing: the same views rendered from both, per-pixel L2
//! distance of RGB, averaged over every pixel of every view (the paper's
//! number; the pair with the smallest is the two good copies), and also over
//! the pixels either model covers. For locating a visual defect each pixel's
//! difference tolerates a one-pixel shift (the smaller distance to the other
//! render's 3x3 neighbourhood, taken both ways), pixels where the two depths
//! disagree are left to the geometric test. To locate a visual defect the
//! renders' colours are carried onto the surface samples (each the average
//! of every pixel that landed on it, over all views) and compared there with
//! the same kind of tolerance: a surface point differs when no point of the
//! other model near it has a similar colour.
//!
//! Point differencing: for each surface point of one model the distance to
//! the nearest surface point of the other; points farther than the
//! threshold (4.5 mm by default, paper) are defect points, both ways.

use nalgebra::Point3;
use rayon::prelude::*;
use serde::Serialize;

use omniscan_register::PointCloud;
use omniscan_register::neighbors::Neighbors;

use crate::views::ViewRender;

/// The paper's pixel comparison of one pair.
#[derive(Debug, Clone, Serialize)]
pub struct PixelComparison {
    pub a: usize,
    pub b: usize,
    /// Mean per-pixel RGB L2 distance over every pixel of every view (paper).
    pub mean_l2: f64,
    /// The same over the pixels either model covers.
    pub mean_l2_object: f64,
    /// Per view, the mean over covered pixels.
    pub per_view: Vec<f64>,
}

fn rgb_distance(a: [f32; 3], b: [f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Compares two models' renders of the same views.
pub fn compare_pixels(
    a: usize,
    b: usize,
    renders_a: &[ViewRender],
    renders_b: &[ViewRender],
) -> PixelComparison {
    let per: Vec<(f64, usize, f64, usize)> = renders_a
        .par_iter()
        .zip(renders_b)
        .map(|(ra, rb)| {
            let (mut all, mut object, mut covered) = (0.0, 0.0, 0usize);
            for i in 0..ra.rgb.len() {
                let d = rgb_distance(ra.rgb[i], rb.rgb[i]) as f64;
                all += d;
                if ra.alpha[i] >= 0.5 || rb.alpha[i] >= 0.5 {
                    object += d;
                    covered += 1;
                }
            }
            (all, ra.rgb.len(), object, covered)
        })
        .collect();
    let total_pixels: usize = per.iter().map(|p| p.1).sum();
    let covered: usize = per.iter().map(|p| p.3).sum();
    PixelComparison {
        a,
        b,
        mean_l2: per.iter().map(|p| p.0).sum::<f64>() / total_pixels.max(1) as f64,
        mean_l2_object: per.iter().map(|p| p.2).sum::<f64>() / covered.max(1) as f64,
        per_view: per
            .iter()
            .map(|p| if p.3 == 0 { 0.0 } else { p.2 / p.3 as f64 })
            .collect(),
    }
}

/// Per-pixel colour difference that tolerates a one-pixel shift.
pub fn difference_map(a: &ViewRender, b: &ViewRender) -> Vec<f32> {
    let (w, h) = (a.width as i64, a.height as i64);
    let nearest = |from: &ViewRender, to: &ViewRender, x: i64, y: i64| {
        let c = from.rgb[(y * w + x) as usize];
        let mut best = f32::INFINITY;
        for dy in -1..=1 {
            for dx in -1..=1 {
                let (u, v) = (x + dx, y + dy);
                if u < 0 || v < 0 || u >= w || v >= h {
                    continue;
                }
                best = best.min(rgb_distance(c, to.rgb[(v * w + u) as usize]));
            }
        }
        best
    };
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            nearest(a, b, x, y).max(nearest(b, a, x, y))
        })
        .collect()
}

/// Located differences between two models: points on the surface (model
/// units, reference frame) with how much they differ there (distance in
/// model units for geometric evidence, RGB distance for visual).
#[derive(Debug, Clone, Default)]
pub struct Evidence {
    pub points: Vec<Point3<f64>>,
    pub magnitude: Vec<f64>,
}

impl Evidence {
    pub fn len(&self) -> usize {
        self.points.len()
    }
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }
}

/// Visual differences between two models' coloured surfaces: a surface
/// point of one differs when its colour is farther than `colour_threshold`
/// (RGB L2, 0-1 channels) from the colour of every surface point of the
/// other within `radius`; points with no such neighbour are the geometric
/// test's business. Each surface point's colour is the average of every
/// rendered pixel that landed on it, so one view's artefact is diluted, and
/// the tolerance of `radius` forgives texture edges shifted by resampling.
pub fn visual_evidence(
    a: &PointCloud,
    b: &PointCloud,
    radius: f64,
    colour_threshold: f64,
) -> Evidence {
    let mut evidence = Evidence::default();
    for (from, to) in [(a, b), (b, a)] {
        if from.is_empty() || to.is_empty() || !from.has_colors() || !to.has_colors() {
            continue;
        }
        let tree = Neighbors::new(&to.points);
        let flagged: Vec<Option<f64>> = from
            .points
            .par_iter()
            .zip(&from.colors)
            .map(|(p, c)| {
                let near = tree.within(p, radius);
                if near.is_empty() {
                    return None;
                }
                let best = near
                    .iter()
                    .map(|&(j, _)| rgb_distance(*c, to.colors[j]) as f64)
                    .fold(f64::INFINITY, f64::min);
                (best > colour_threshold).then_some(best)
            })
            .collect();
        for (p, f) in from.points.iter().zip(flagged) {
            if let Some(d) = f {
                evidence.points.push(*p);
                evidence.magnitude.push(d);
            }
        }
    }
    evidence
}

/// Points of `a` farther than `threshold` from every point of `b`, and the
/// other way round.
pub fn geometric_evidence(a: &PointCloud, b: &PointCloud, threshold: f64) -> Evidence {
    let mut evidence = Evidence::default();
    for (from, to) in [(a, b), (b, a)] {
        if from.is_empty() {
            continue;
        }
        if to.is_empty() {
            evidence.points.extend(&from.points);
            evidence
                .magnitude
                .extend(std::iter::repeat_n(f64::INFINITY, from.len()));
            continue;
        }
        let tree = Neighbors::new(&to.points);
        let distances: Vec<f64> = from
            .points
            .par_iter()
            .map(|p| tree.nearest(p).map_or(f64::INFINITY, |(_, d2)| d2.sqrt()))
            .collect();
        for (p, d) in from.points.iter().zip(distances) {
            if d > threshold {
                evidence.points.push(*p);
                evidence.magnitude.push(d);
            }
        }
    }
    evidence
}

/// Distance from each point of `a` to the nearest point of `b` (for colouring).
pub fn nearest_distances(a: &PointCloud, b: &PointCloud) -> Vec<f64> {
    if b.is_empty() {
        return vec![f64::INFINITY; a.len()];
    }
    let tree = Neighbors::new(&b.points);
    a.points
        .par_iter()
        .map(|p| tree.nearest(p).map_or(f64::INFINITY, |(_, d2)| d2.sqrt()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(colour: [f32; 3], w: u32, h: u32) -> ViewRender {
        ViewRender {
            width: w,
            height: h,
            rgb: vec![colour; (w * h) as usize],
            alpha: vec![1.0; (w * h) as usize],
            depth: vec![1.0; (w * h) as usize],
        }
    }

    #[test]
    fn difference_map_forgives_a_one_pixel_shift_but_not_a_mark() {
        let mut a = flat([0.2; 3], 20, 20);
        let mut b = flat([0.2; 3], 20, 20);
        // An edge at x = 10 in a, x = 11 in b.
        for y in 0..20 {
            for x in 10..20 {
                a.rgb[y * 20 + x] = [0.9; 3];
            }
            for x in 11..20 {
                b.rgb[y * 20 + x] = [0.9; 3];
            }
        }
        let d = difference_map(&a, &b);
        assert!(
            d.iter().all(|&v| v < 1e-6),
            "a shifted edge is no difference"
        );
        // A 3x3 mark in b only.
        for y in 4..7 {
            for x in 2..5 {
                b.rgb[y * 20 + x] = [0.9, 0.1, 0.1];
            }
        }
        let d = difference_map(&a, &b);
        assert!(d[5 * 20 + 3] > 0.5);
    }

    #[test]
    fn pixel_comparison_of_identical_renders_is_zero() {
        let a = vec![flat([0.3; 3], 8, 8)];
        let c = compare_pixels(0, 1, &a, &a);
        assert_eq!(c.mean_l2, 0.0);
        let b = vec![flat([0.3, 0.3, 0.7], 8, 8)];
        let c = compare_pixels(0, 1, &a, &b);
        assert!((c.mean_l2 - 0.4).abs() < 1e-6);
        assert!((c.mean_l2_object - 0.4).abs() < 1e-6);
    }

    #[test]
    fn visual_evidence_finds_a_recoloured_patch_but_forgives_a_shifted_edge() {
        let grid = |shift: f64| -> PointCloud {
            let mut c = PointCloud::default();
            for i in 0..900 {
                let (x, y) = ((i % 30) as f64 * 0.001, (i / 30) as f64 * 0.001);
                c.points.push(Point3::new(x, y, 0.0));
                // A black/white edge at x = 15 mm (+ shift).
                c.colors.push(if x < 0.015 + shift {
                    [0.0; 3]
                } else {
                    [1.0; 3]
                });
            }
            c
        };
        let a = grid(0.0);
        let b = grid(0.001);
        assert!(visual_evidence(&a, &b, 0.0015, 0.3).is_empty());
        let mut marked = b.clone();
        for i in 0..900 {
            let p = marked.points[i];
            if (p.x - 0.005).abs() <= 0.002 && (p.y - 0.005).abs() <= 0.002 {
                marked.colors[i] = [1.0, 0.0, 0.0];
            }
        }
        let e = visual_evidence(&a, &marked, 0.0015, 0.3);
        // The 5x5 patch; its rim is forgiven from one side only.
        assert!(e.len() >= 9 && e.len() <= 50, "{}", e.len());
        assert!(e.points.iter().all(|p| (p.x - 0.005).abs() <= 0.0021));
    }

    #[test]
    fn geometric_evidence_finds_the_moved_points_both_ways() {
        let grid: Vec<Point3<f64>> = (0..400)
            .map(|i| Point3::new((i % 20) as f64 * 0.001, (i / 20) as f64 * 0.001, 0.0))
            .collect();
        let a = PointCloud {
            points: grid.clone(),
            ..Default::default()
        };
        let mut moved = grid;
        for p in moved.iter_mut().take(45).skip(40) {
            p.z += 0.006;
        }
        let b = PointCloud {
            points: moved,
            ..Default::default()
        };
        let e = geometric_evidence(&a, &b, 0.0045);
        // The 5 raised points of b; the places they left are within a
        // millimetre of their unmoved neighbours.
        assert_eq!(e.len(), 5);
        assert!(e.magnitude.iter().all(|&d| d > 0.0045));
        assert!(geometric_evidence(&a, &a, 0.0045).is_empty());
    }
}
