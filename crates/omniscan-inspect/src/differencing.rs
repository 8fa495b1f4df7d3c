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

use crate::views::{SURFACE_ALPHA, View, ViewRender, back_project, surface_pixel_depth};

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

/// Both kinds of evidence of one difference as one set.
pub fn merge(mut a: Evidence, b: Evidence) -> Evidence {
    a.points.extend(b.points);
    a.magnitude.extend(b.magnitude);
    a
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

/// Pixels at most this opaque show nothing: the other model has a hole there.
const EMPTY_ALPHA: f32 = 0.3;

/// Geometric differences seen in the renders: in every view, a surface
/// pixel of one model whose depth differs by more than `threshold` from
/// the other model's depth at that pixel and its eight neighbours (one
/// pixel of alignment is forgiven), or where the other shows no surface at
/// all (a hole). The flagged pixels are back-projected and pooled in voxels
/// of `spacing`; a voxel is evidence when at least three views flag it and
/// they are at least half of the views that see it there.
///
/// This compares the depths the two models show along the same ray, which
/// is what a user sees; the nearest-point test ([`geometric_evidence`])
/// misses a 9 mm dent on a trained model whose faint skin gives surface
/// samples a few millimetres deep, any of which is "near" the dent's floor
/// (measured on `pressure_sensor`: no point over 4.5 mm, while the depths
/// along the rays differ by 5-10 mm in 30 of 100 views).
pub fn depth_evidence(
    renders_a: &[ViewRender],
    renders_b: &[ViewRender],
    views: &[View],
    threshold: f64,
    spacing: f64,
) -> Evidence {
    /// A surface pixel's voxel, whether it differs, by how much (the depth
    /// difference, or the threshold for a hole), and where it is.
    type Sample = ([i64; 3], bool, f64, Point3<f64>);
    let threshold = threshold as f32;
    let samples: Vec<Vec<Sample>> = renders_a
        .par_iter()
        .zip(renders_b)
        .zip(views)
        .flat_map(|((ra, rb), view)| [(ra, rb, view), (rb, ra, view)])
        .map(|(from, to, view)| {
            let (w, h) = (from.width as i64, from.height as i64);
            let mut out = Vec::new();
            for i in 0..from.alpha.len() {
                let Some(z) = surface_pixel_depth(from, view, i) else {
                    continue;
                };
                let (x, y) = (i as i64 % w, i as i64 / w);
                let mut best = f32::INFINITY;
                let mut undecided = false;
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (u, v) = (x + dx, y + dy);
                        if u < 0 || v < 0 || u >= w || v >= h {
                            continue;
                        }
                        let j = (v * w + u) as usize;
                        match to.surface_depth(j, SURFACE_ALPHA) {
                            Some(other) => best = best.min((other - z).abs()),
                            None if to.alpha[j] > EMPTY_ALPHA => undecided = true,
                            None => {}
                        }
                    }
                }
                if best.is_infinite() && undecided {
                    continue;
                }
                let p = back_project(view, x as u32, y as u32, z as f64);
                let key = (p.coords / spacing).map(|c| c.floor() as i64);
                let flagged = best > threshold;
                let magnitude = if best.is_finite() {
                    best as f64
                } else {
                    threshold as f64
                };
                out.push(([key.x, key.y, key.z], flagged, magnitude, p));
            }
            out
        })
        .collect();
    #[derive(Default)]
    struct Voxel {
        seen: usize,
        flagged: usize,
        magnitude: f64,
        point: nalgebra::Vector3<f64>,
    }
    let mut voxels: std::collections::HashMap<[i64; 3], Voxel> = std::collections::HashMap::new();
    for (key, flagged, magnitude, p) in samples.into_iter().flatten() {
        let v = voxels.entry(key).or_default();
        v.seen += 1;
        if flagged {
            v.flagged += 1;
            v.magnitude += magnitude;
            v.point += p.coords;
        }
    }
    let mut keys: Vec<&[i64; 3]> = voxels
        .iter()
        .filter(|(_, v)| v.flagged >= 3 && 2 * v.flagged >= v.seen)
        .map(|(k, _)| k)
        .collect();
    // Deterministic order, whatever the hash map's.
    keys.sort();
    let mut evidence = Evidence::default();
    for key in keys {
        let v = &voxels[key];
        evidence
            .points
            .push(Point3::from(v.point / v.flagged as f64));
        evidence.magnitude.push(v.magnitude / v.flagged as f64);
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
    fn depth_evidence_finds_a_dent_and_a_hole_in_every_view_that_sees_them() {
        use crate::views::sphere_views;
        // Three views from one place of a wall facing the camera.
        let views = vec![sphere_views(&Point3::origin(), 0.5, 1, 40, 30)[0].clone(); 3];
        let wall = |z: f32| ViewRender {
            depth: vec![z; 1200],
            ..flat([0.5; 3], 40, 30)
        };
        let distance = (views[0].camera_to_world.translation.vector).norm() as f32;
        let a: Vec<ViewRender> = (0..3).map(|_| wall(distance)).collect();
        let mut b = a.clone();
        for r in &mut b {
            // A 6x6-pixel dent 0.01 deep, and a 4x4-pixel hole.
            for y in 5..11 {
                for x in 5..11 {
                    r.depth[y * 40 + x] += 0.01;
                }
            }
            for y in 20..24 {
                for x in 25..29 {
                    r.alpha[y * 40 + x] = 0.0;
                    r.depth[y * 40 + x] = 0.0;
                }
            }
        }
        let pixel = distance as f64 / views[0].intrinsics.fx;
        let e = depth_evidence(&a, &b, &views, 0.0045, 2.0 * pixel);
        assert!(!e.is_empty());
        // Nothing of the wall away from the two spots; inner pixels of both.
        let spot = |p: &Point3<f64>, x: f64, y: f64, r: f64, v: &View| {
            let q = v.camera_to_world.inverse() * p;
            let (u, w) = (
                v.intrinsics.fx * q.x / q.z + v.intrinsics.cx,
                v.intrinsics.fy * q.y / q.z + v.intrinsics.cy,
            );
            (u - x).abs() <= r && (w - y).abs() <= r
        };
        let v = &views[0];
        assert!(
            e.points
                .iter()
                .all(|p| spot(p, 8.0, 8.0, 4.5, v) || spot(p, 27.0, 22.0, 3.5, v))
        );
        assert!(
            e.points.iter().any(|p| spot(p, 8.0, 8.0, 2.0, v)),
            "the dent"
        );
        assert!(
            e.points.iter().any(|p| spot(p, 27.0, 22.0, 1.5, v)),
            "the hole"
        );
        assert!(depth_evidence(&a, &a, &views, 0.0045, 2.0 * pixel).is_empty());
        // A dent shallower than the threshold is no evidence.
        let shallow: Vec<ViewRender> = a
            .iter()
            .map(|r| ViewRender {
                depth: r.depth.iter().map(|z| z + 0.003).collect(),
                ..r.clone()
            })
            .collect();
        assert!(depth_evidence(&a, &shallow, &views, 0.0045, 2.0 * pixel).is_empty());
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
