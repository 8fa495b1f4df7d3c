//! A second, close look at small geometric differences.
//!
//! The inspection's views (100 of 160x120 pixels, paper: 100 views) give a
//! pixel of about 1 mm on a 15 cm part. A defect near the smallest size
//! that matters (a 5 mm bump is a plateau 5 mm across on a 10 mm mound)
//! then covers a handful of pixels, each pixel's median depth blends it
//! with its surroundings, and the evidence falls apart into a few points
//! (measured on `remote_merge` with `omniscan bench inspect`: a 5.3 mm bump
//! left 3 points of depth evidence at 1 mm per pixel, and a 44 mm² region at
//! 0.5 mm per pixel). Rendering every view finer costs four times as much per
//! halving, so instead every place where the first pass attributed any
//! geometric difference to one model, however little, is looked at again:
//! each first-pass view that sees the place becomes a camera at the same
//! pose with a narrow field of view centred on it (a crop, zoomed), every
//! model is rendered through those cameras (16 views, 0.4 mm pixels), and
//! the same depth comparison, attribution and clustering run there. Regions
//! found so count like the first pass's; the thresholds (depth in
//! millimetres, area in square millimetres, votes pooled in voxels of the
//! first pass's spacing) are the same. On that bump: 33 mm², located; with
//! 8 views and votes in 0.4 mm voxels nothing over 1.3 mm² (a fuzzy
//! model's median depth wanders by more than 0.4 mm from view to view, so
//! no voxel gathered three votes).
//!
//! It is off by default (`--close-up` turns it on), because it sharpens the
//! eye for differences between good copies as much as for defects:
//! `omniscan bench inspect` (seed 0, 46 triplets) goes from 41 to 42
//! correct and from 35 to 36 of 40 defects located, at 0.2 s more per
//! triplet (at most 1.3 s), but on 16 triplets of good copies (`--seed 1
//! --triplets 0 --good-triplets 16`) from 14 to 12 correct: two copies
//! that lost a few splats on a thin edge (realsense, 29 mm² at 6 mm) or
//! were aligned to a near-symmetric pose (twin, 16 mm²) now show a region.
//! Stricter voting (three quarters of the views) lost the bump and kept
//! the realsense region.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use omniscan_core::Intrinsics;
use omniscan_register::PointCloud;
use omniscan_register::preprocess::dbscan;
use omniscan_splat::Splats;
use omniscan_splat::backend::Renderer;

use crate::differencing::{Evidence, depth_evidence};
use crate::verdict::{Kind, PairEvidence, Region, VerdictSettings, attributed, find_regions};
use crate::views::{View, ViewRender, render_views_on, surface_pixel_depth};

/// How closely and how often to look again.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CloseUpSettings {
    /// Places looked at again, at most (the most evidence first).
    pub max_places: usize,
    /// Views of each place, at most.
    pub views: usize,
    /// Pixel size at the place, millimetres (larger where the place would
    /// need more than `max_side` pixels).
    pub pixel_mm: f64,
    /// Largest close-up image side, pixels.
    pub max_side: u32,
}

impl Default for CloseUpSettings {
    fn default() -> Self {
        CloseUpSettings {
            max_places: 6,
            views: 16,
            pixel_mm: 0.4,
            max_side: 96,
        }
    }
}

/// One place looked at again and what was found there.
#[derive(Debug, Clone)]
pub struct CloseUp {
    /// The model the first pass attributed the difference to.
    pub model: usize,
    /// Centre of the place (reference frame, model units).
    pub centre: Point3<f64>,
    /// Radius of the place looked at (model units).
    pub radius: f64,
    pub views: Vec<View>,
    /// Geometric regions found there, significant or not.
    pub regions: Vec<Region>,
}

/// A place worth a close look: a cluster of first-pass evidence attributed
/// to `model`.
#[derive(Debug, Clone)]
struct Place {
    model: usize,
    centre: Point3<f64>,
    radius: f64,
    points: usize,
}

/// Clusters of geometric evidence attributed to one candidate, outside the
/// significant regions already found, the largest first; evidence closer
/// than `join` is one cluster.
fn places(
    pairs: &[PairEvidence],
    candidates: &[usize],
    found: &[Region],
    settings: &VerdictSettings,
    join: f64,
    limit: usize,
) -> Vec<Place> {
    let mm = 1000.0 / settings.units_per_metre;
    let mut out = Vec::new();
    for &m in candidates {
        let evidence = attributed(pairs, m, Kind::Geometric, settings.match_radius);
        if evidence.is_empty() {
            continue;
        }
        let cloud = PointCloud {
            points: evidence.points.clone(),
            ..Default::default()
        };
        // One point is enough to look: what a close look finds is judged
        // by the usual thresholds. Points within `join` are one place, so
        // one defect is not looked at (and counted) twice.
        let labels = dbscan(&cloud, join, 1);
        let clusters = labels.iter().copied().max().unwrap_or(-1) + 1;
        for c in 0..clusters {
            let members: Vec<&Point3<f64>> = evidence
                .points
                .iter()
                .zip(&labels)
                .filter(|(_, l)| **l == c)
                .map(|(p, _)| p)
                .collect();
            let centre = Point3::from(
                members.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / members.len() as f64,
            );
            let radius = members
                .iter()
                .map(|p| (*p - centre).norm())
                .fold(0.0, f64::max);
            let known = found.iter().any(|r| {
                r.significant
                    && r.model == m
                    && r.kind == Kind::Geometric
                    && (Point3::from(r.centroid) - centre).norm() * mm <= 0.5 * r.extent_mm
            });
            if !known {
                out.push(Place {
                    model: m,
                    centre,
                    radius,
                    points: members.len(),
                });
            }
        }
    }
    out.sort_by_key(|p| std::cmp::Reverse(p.points));
    out.truncate(limit);
    out
}

/// Up to `count` of `views` that see `place` on the model's surface,
/// spread over the directions they see it from, each made a close-up
/// camera centred on it with pixels of `pixel` (model units) there.
fn close_views(
    place: &Place,
    half_width: f64,
    views: &[View],
    renders: &[ViewRender],
    count: usize,
    pixel: f64,
    max_side: u32,
) -> Vec<View> {
    // Views whose render of the model shows a surface near the place.
    let mut seeing: Vec<(usize, Vector3<f64>)> = Vec::new();
    for (k, (view, render)) in views.iter().zip(renders).enumerate() {
        let local = view.camera_to_world.inverse() * place.centre;
        if local.z <= view.near {
            continue;
        }
        let i = &view.intrinsics;
        let (u, v) = (
            i.fx * local.x / local.z + i.cx,
            i.fy * local.y / local.z + i.cy,
        );
        if u < 0.0 || v < 0.0 || u >= i.width as f64 || v >= i.height as f64 {
            continue;
        }
        let index = v as usize * render.width as usize + u as usize;
        let Some(depth) = surface_pixel_depth(render, view, index) else {
            continue;
        };
        if (depth as f64 - local.z).abs() <= half_width {
            let eye = view.camera_to_world.translation.vector;
            seeing.push((k, (eye - place.centre.coords).normalize()));
        }
    }
    if seeing.is_empty() {
        return Vec::new();
    }
    // Farthest-point choice of directions, from the one nearest their mean.
    let mean = seeing.iter().fold(Vector3::zeros(), |s, (_, d)| s + d);
    let first = (0..seeing.len())
        .max_by(|&a, &b| seeing[a].1.dot(&mean).total_cmp(&seeing[b].1.dot(&mean)))
        .unwrap_or(0);
    let mut chosen = vec![first];
    let mut nearest: Vec<f64> = seeing
        .iter()
        .map(|(_, d)| d.dot(&seeing[first].1))
        .collect();
    while chosen.len() < count.min(seeing.len()) {
        let next = (0..seeing.len())
            .filter(|k| !chosen.contains(k))
            .min_by(|&a, &b| nearest[a].total_cmp(&nearest[b]));
        let Some(next) = next else { break };
        chosen.push(next);
        for (k, (_, d)) in seeing.iter().enumerate() {
            nearest[k] = nearest[k].max(d.dot(&seeing[next].1));
        }
    }
    let side = ((2.0 * half_width / pixel).ceil() as u32).clamp(16, max_side);
    chosen
        .into_iter()
        .map(|k| {
            let view = &views[seeing[k].0];
            let local = view.camera_to_world.inverse() * place.centre;
            let focal = 0.5 * side as f64 * local.z / half_width;
            View {
                camera_to_world: view.camera_to_world,
                intrinsics: Intrinsics {
                    width: side,
                    height: side,
                    fx: focal,
                    fy: focal,
                    cx: 0.5 * side as f64 - focal * local.x / local.z,
                    cy: 0.5 * side as f64 - focal * local.y / local.z,
                },
                near: view.near,
                far: view.far,
            }
        })
        .collect()
}

/// Evidence within `radius` of `centre` only: the crop's edges cut the
/// surfaces, and what lies outside the place was judged by the first pass.
fn within(evidence: Evidence, centre: &Point3<f64>, radius: f64) -> Evidence {
    let mut out = Evidence::default();
    for (p, m) in evidence.points.into_iter().zip(evidence.magnitude) {
        if (p - centre).norm() <= radius {
            out.points.push(p);
            out.magnitude.push(m);
        }
    }
    out
}

/// Looks again, closely, at every place where the first pass attributed a
/// little geometric difference to one of `candidates` outside the regions
/// it already found significant. `models` are the aligned models,
/// `views`/`renders` the first pass's, `threshold` the depth threshold and
/// `verdict` the first pass's verdict settings (model units).
#[allow(clippy::too_many_arguments)]
pub fn look_closer(
    renderer: &Renderer,
    models: &[Splats],
    candidates: &[usize],
    pairs: &[PairEvidence],
    found: &[Region],
    views: &[View],
    renders: &[Vec<ViewRender>],
    threshold: f64,
    verdict: &VerdictSettings,
    settings: &CloseUpSettings,
) -> Result<Vec<CloseUp>, omniscan_splat::SplatError> {
    let unit = verdict.units_per_metre / 1000.0;
    let pixel = settings.pixel_mm * unit;
    let mut out = Vec::new();
    for place in places(
        pairs,
        candidates,
        found,
        verdict,
        threshold,
        settings.max_places,
    ) {
        // The place, and room around it for the surface it stands out from.
        let half_width = place.radius + 2.0 * threshold;
        let close = close_views(
            &place,
            half_width,
            views,
            &renders[place.model],
            settings.views,
            pixel,
            settings.max_side,
        );
        if close.len() < 3 {
            continue;
        }
        // Votes are pooled in voxels of the first pass's spacing: finer
        // voxels split one surface's samples from different views by
        // their depth noise, and fewer than three views agree in any.
        let spacing = verdict.spacing;
        let close_renders: Vec<Vec<ViewRender>> = models
            .iter()
            .map(|m| render_views_on(renderer, m, &close))
            .collect::<Result<_, _>>()?;
        let close_pairs: Vec<PairEvidence> = pairs
            .par_iter()
            .map(|&PairEvidence { a, b, .. }| PairEvidence {
                a,
                b,
                geometric: within(
                    depth_evidence(
                        &close_renders[a],
                        &close_renders[b],
                        &close,
                        threshold,
                        spacing,
                    ),
                    &place.centre,
                    half_width,
                ),
                visual: Evidence::default(),
            })
            .collect();
        let mut regions = find_regions(
            candidates,
            &close_pairs,
            &VerdictSettings {
                spacing,
                match_radius: 3.0 * spacing,
                ..*verdict
            },
        );
        regions.iter_mut().for_each(|r| r.close_up = true);
        out.push(CloseUp {
            model: place.model,
            centre: place.centre,
            radius: half_width,
            views: close,
            regions,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::views::sphere_views;

    /// A render of a flat, opaque surface through the place at its depth.
    fn flat_render(view: &View, place: &Point3<f64>) -> ViewRender {
        let depth = (view.camera_to_world.inverse() * place).z as f32;
        let n = (view.intrinsics.width * view.intrinsics.height) as usize;
        ViewRender {
            width: view.intrinsics.width,
            height: view.intrinsics.height,
            rgb: vec![[0.5; 3]; n],
            alpha: vec![1.0; n],
            depth: vec![depth; n],
        }
    }

    #[test]
    fn close_views_centre_the_place_at_the_asked_pixel_size() {
        let centre = Point3::new(0.0, 0.0, 0.0);
        let views = sphere_views(&centre, 0.05, 30, 64, 48);
        let place = Place {
            model: 0,
            centre: Point3::new(0.01, -0.005, 0.02),
            radius: 0.002,
            points: 4,
        };
        let renders: Vec<ViewRender> = views
            .iter()
            .map(|v| flat_render(v, &place.centre))
            .collect();
        let close = close_views(&place, 0.01, &views, &renders, 8, 0.0004, 96);
        assert_eq!(close.len(), 8);
        for v in &close {
            let local = v.camera_to_world.inverse() * place.centre;
            let k = &v.intrinsics;
            assert_eq!((k.width, k.height), (50, 50));
            assert!((k.fx * local.x / local.z + k.cx - 25.0).abs() < 1e-9);
            assert!((k.fy * local.y / local.z + k.cy - 25.0).abs() < 1e-9);
            // 0.4 mm per pixel at the place.
            assert!((local.z / k.fx - 0.0004).abs() < 1e-12);
        }
        // Spread: no two chosen views look from the same direction.
        let directions: Vec<Vector3<f64>> = close
            .iter()
            .map(|v| (v.camera_to_world.translation.vector - place.centre.coords).normalize())
            .collect();
        for (i, a) in directions.iter().enumerate() {
            for b in &directions[i + 1..] {
                assert!(a.dot(b) < 0.999);
            }
        }
    }

    #[test]
    fn a_place_hidden_in_every_view_gets_no_close_view() {
        let views = sphere_views(&Point3::origin(), 0.05, 10, 32, 24);
        let place = Place {
            model: 0,
            centre: Point3::origin(),
            radius: 0.0,
            points: 1,
        };
        // Every render shows a surface 3 cm in front of the place.
        let renders: Vec<ViewRender> = views
            .iter()
            .map(|v| {
                let mut r = flat_render(v, &place.centre);
                r.depth.iter_mut().for_each(|d| *d -= 0.03);
                r
            })
            .collect();
        assert!(close_views(&place, 0.01, &views, &renders, 8, 0.0004, 96).is_empty());
    }
}
