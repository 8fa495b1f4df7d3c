//! The inspection pipeline as one call: align, render, compare, decide.

use std::time::Instant;

use nalgebra::Point3;
use rayon::prelude::*;
use serde::Serialize;

use omniscan_register::PointCloud;
use omniscan_splat::Splats;
use omniscan_splat::orbit::robust_bounds;

use crate::InspectError;
use crate::align::{AlignSettings, Alignment, align_model, model_points};
use crate::closeup::{CloseUp, CloseUpSettings, look_closer};
use crate::differencing::{
    PixelComparison, compare_pixels, depth_evidence, geometric_evidence, merge, visual_evidence,
};
use crate::photometric::{ColourCorrection, match_colours};
use crate::verdict::{
    Kind, PairEvidence, Region, Verdict, VerdictSettings, apply_noise_floors, candidate_regions,
    name_defective,
};
use crate::views::{
    CameraSet, View, ViewRender, render_views, render_views_on, sphere_views, surface_points,
};
use omniscan_splat::backend::{Backend, Renderer};

/// Settings of an inspection. Lengths in millimetres are converted to the
/// models' units with `units_per_metre`.
#[derive(Debug, Clone, PartialEq)]
pub struct InspectSettings {
    /// Model units per metre (1 for omniscan's own models; about 18 for the
    /// original Omni-Scan models).
    pub units_per_metre: f64,
    /// Point differencing threshold, millimetres (paper: 4.5).
    pub threshold_mm: f64,
    /// Views rendered of every model (paper: 100).
    pub views: usize,
    /// Where the views are: `None` spreads them over a sphere around the
    /// first model; a camera set (its scan's cameras, as the paper) gives
    /// `views` of its cameras, each zoomed onto the part.
    pub cameras: Option<CameraSet>,
    pub width: u32,
    pub height: u32,
    /// RGB L2 distance (0-1 channels) above which a pixel differs.
    pub colour_threshold: f64,
    /// Spacing of the surface samples, millimetres.
    pub spacing_mm: f64,
    /// Smallest geometric region that counts, square millimetres; `None`:
    /// a disc as wide as the threshold is deep (π·(threshold/2)², 15.9 mm²
    /// at 4.5 mm), since a defect that deep is at least that wide. Between
    /// good copies of the Omni-Scan models regions reach 8-17 mm² (16 good
    /// triplets measured with `omniscan bench inspect --seed 1`).
    pub min_geometric_area_mm2: Option<f64>,
    pub min_visual_area_mm2: f64,
    /// Radius over which a model's surface colours are matched to the
    /// reference's before visual differencing, millimetres; `None`: raw
    /// colours (see [`crate::photometric`]). Twice the largest visual
    /// defect the inspection should still see at full contrast.
    pub photometric_radius_mm: Option<f64>,
    /// Indices of models known to be good; `None` = any model may be defective.
    pub references: Option<Vec<usize>>,
    pub align: AlignSettings,
    /// A second, close look at small geometric differences; `None`: none.
    /// Off by default: it finds more true defects and more differences
    /// between good copies alike (see [`crate::closeup`]).
    pub close_up: Option<CloseUpSettings>,
    /// Where the views are rendered (`auto`: a real GPU when there is one).
    pub backend: Backend,
}

impl Default for InspectSettings {
    fn default() -> Self {
        InspectSettings {
            units_per_metre: 1.0,
            threshold_mm: 4.5,
            views: 100,
            cameras: None,
            width: 160,
            height: 120,
            colour_threshold: 0.3,
            spacing_mm: 1.0,
            min_geometric_area_mm2: None,
            min_visual_area_mm2: 8.0,
            photometric_radius_mm: Some(15.0),
            references: None,
            align: AlignSettings::default(),
            close_up: None,
            backend: Backend::Auto,
        }
    }
}

/// Seconds spent per stage.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Timings {
    pub align: f64,
    pub render: f64,
    pub compare: f64,
    pub close_up: f64,
    pub total: f64,
}

/// Everything an inspection found, for the verdict file and the report.
#[derive(Debug, Clone)]
pub struct Inspection {
    pub alignments: Vec<Alignment>,
    pub views: Vec<View>,
    /// Per model, its renders of every view (after alignment).
    pub renders: Vec<Vec<ViewRender>>,
    /// Per model, its visible surface in the reference frame, colours
    /// matched to the reference's.
    pub surfaces: Vec<PointCloud>,
    /// Per model, how its colours were matched to the reference's.
    pub colour_corrections: Vec<ColourCorrection>,
    pub pixels: Vec<PixelComparison>,
    pub pairs: Vec<PairEvidence>,
    /// Places of small geometric differences looked at again.
    pub close_ups: Vec<CloseUp>,
    pub verdict: Verdict,
    pub timings: Timings,
}

/// Views that fit the reference's robust box tightly in each image, so an
/// elongated part is not drawn small in the middle of a square of background.
/// Views on the sphere look at the part's centre and are only zoomed in;
/// given cameras (a scan's, where the part sits anywhere in a wide view)
/// are zoomed and re-centred onto it, as a crop of their image would be.
fn framed_views(
    reference: &Splats,
    centre: &nalgebra::Point3<f64>,
    radius: f64,
    settings: &InspectSettings,
) -> Vec<View> {
    let mut views = match &settings.cameras {
        Some(cameras) => cameras.views(settings.views, settings.width, settings.height),
        None => sphere_views(
            centre,
            1.15 * radius,
            settings.views,
            settings.width,
            settings.height,
        ),
    };
    let sigmoid = |x: f32| 1.0 / (1.0 + (-x).exp());
    let opaque: Vec<nalgebra::Point3<f64>> = reference
        .means
        .iter()
        .zip(&reference.opacity_logits)
        .filter(|(_, o)| sigmoid(**o) > 0.3)
        .map(|(m, _)| nalgebra::Point3::from(m.map(|v| v as f64)))
        .step_by(7)
        .collect();
    for view in &mut views {
        let world_to_camera = view.camera_to_world.inverse();
        let spans: Vec<(f64, f64)> = opaque
            .iter()
            .filter_map(|p| {
                let q = world_to_camera * p;
                (q.z > 0.0).then(|| (q.x / q.z, q.y / q.z))
            })
            .collect();
        if spans.len() < 10 {
            continue;
        }
        // The 2nd and 98th percentiles: stray floaters must not shrink the part.
        let percentile = |v: &[f64], p: usize| v[(v.len() * p / 100).min(v.len() - 1)];
        let sorted = |coordinate: fn(&(f64, f64)) -> f64| {
            let mut v: Vec<f64> = spans.iter().map(coordinate).collect();
            v.sort_by(f64::total_cmp);
            v
        };
        let k = &mut view.intrinsics;
        if settings.cameras.is_some() {
            let (xs, ys) = (sorted(|s| s.0), sorted(|s| s.1));
            let middle = |v: &[f64]| 0.5 * (percentile(v, 2) + percentile(v, 98));
            let half = |v: &[f64]| 0.5 * (percentile(v, 98) - percentile(v, 2));
            let (half_width, half_height) = (0.5 * k.width as f64, 0.5 * k.height as f64);
            let focal = (0.85 * half_width / half(&xs).max(1e-9))
                .min(0.85 * half_height / half(&ys).max(1e-9));
            if focal.is_finite() {
                k.fx = focal;
                k.fy = focal;
                k.cx = half_width - focal * middle(&xs);
                k.cy = half_height - focal * middle(&ys);
            }
        } else {
            let sx = percentile(&sorted(|s| s.0.abs()), 98);
            let sy = percentile(&sorted(|s| s.1.abs()), 98);
            let focal = (0.85 * k.cx / sx.max(1e-9)).min(0.85 * k.cy / sy.max(1e-9));
            if focal.is_finite() && focal > k.fx {
                k.fx = focal;
                k.fy = focal;
            }
        }
    }
    views
}

/// Bounds on the rendered views: count, and pixels a side.
const MAX_VIEWS: usize = 1000;
const MAX_SIDE: u32 = 4096;

/// Inspects `models` (at least three copies of one part); the first is the
/// reference frame everything is aligned to.
pub fn inspect(models: &[Splats], settings: &InspectSettings) -> Result<Inspection, InspectError> {
    let start = Instant::now();
    let candidates = check_inputs(models, settings)?;
    let unit = settings.units_per_metre / 1000.0;
    let (centre, radius) = robust_bounds(&models[0]);
    let size_m = 2.0 * radius / settings.units_per_metre;
    if !(0.005..=1.0).contains(&size_m) {
        tracing::warn!(
            "the reference model spans about {size_m:.3} m at {} units per metre: \
             is --units-per-metre right?",
            settings.units_per_metre
        );
    }
    let views = framed_views(&models[0], &centre, radius, settings);
    let alignments = align_all(models, settings, &centre, radius)?;
    let align_done = Instant::now();

    let aligned: Vec<Splats> = models
        .iter()
        .zip(&alignments)
        .map(|(m, a)| {
            if a.method == "identity" {
                Ok(m.clone())
            } else {
                m.transformed(&a.transform, 1.0)
            }
        })
        .collect::<Result<_, _>>()?;
    let renderer = Renderer::new(settings.backend)?;
    let renders: Vec<Vec<ViewRender>> = aligned
        .iter()
        .map(|m| render_views_on(&renderer, m, &views))
        .collect::<Result<_, _>>()?;
    let spacing = settings.spacing_mm * unit;
    let (surfaces, colour_corrections) = sample_surfaces(&renders, &views, spacing, settings);
    let render_done = Instant::now();

    let threshold = settings.threshold_mm * unit;
    let (pixels, pairs) = compare_all(&renders, &surfaces, &views, spacing, settings);
    let verdict_settings = VerdictSettings {
        spacing,
        units_per_metre: settings.units_per_metre,
        match_radius: 3.0 * spacing,
        min_geometric_area_mm2: settings
            .min_geometric_area_mm2
            .unwrap_or(std::f64::consts::PI * (0.5 * settings.threshold_mm).powi(2)),
        min_visual_area_mm2: settings.min_visual_area_mm2,
    };
    let (mut regions, floors) =
        candidate_regions(models.len(), &candidates, &pairs, &verdict_settings);
    let compare_done = Instant::now();
    let close_ups = match &settings.close_up {
        Some(close_up) => look_closer(
            &renderer,
            &aligned,
            &candidates,
            &pairs,
            &regions,
            &views,
            &renders,
            threshold,
            &verdict_settings,
            close_up,
        )?,
        None => Vec::new(),
    };
    add_close_up_regions(
        &mut regions,
        &close_ups,
        &floors,
        &verdict_settings,
        settings,
    );
    let verdict = name_defective(
        models.len(),
        &candidates,
        regions,
        &pixels,
        settings.units_per_metre,
    );
    let end = Instant::now();
    Ok(Inspection {
        alignments,
        views,
        renders,
        surfaces,
        colour_corrections,
        pixels,
        pairs,
        close_ups,
        verdict,
        timings: Timings {
            align: (align_done - start).as_secs_f64(),
            render: (render_done - align_done).as_secs_f64(),
            compare: (compare_done - render_done).as_secs_f64(),
            close_up: (end - compare_done).as_secs_f64(),
            total: (end - start).as_secs_f64(),
        },
    })
}

/// Refuses inputs no inspection can use, naming the problem; returns the
/// models that may be defective (all but the references).
fn check_inputs(models: &[Splats], settings: &InspectSettings) -> Result<Vec<usize>, InspectError> {
    if models.len() < 3 {
        return Err(InspectError::Invalid(format!(
            "inspection needs at least three models (two good copies and one to check), got {}",
            models.len()
        )));
    }
    if !(settings.units_per_metre.is_finite() && settings.units_per_metre > 0.0) {
        return Err(InspectError::Invalid(format!(
            "units per metre must be positive, got {}",
            settings.units_per_metre
        )));
    }
    if !(settings.threshold_mm.is_finite() && settings.threshold_mm > 0.0) {
        return Err(InspectError::Invalid(format!(
            "the threshold must be positive, got {} mm",
            settings.threshold_mm
        )));
    }
    if settings.views == 0 || settings.width < 16 || settings.height < 16 {
        return Err(InspectError::Invalid(
            "need at least one view of at least 16x16 pixels".into(),
        ));
    }
    // Every view is rendered for every model: 10⁵ views ran for hours, and
    // 10⁶-pixel sides ran out of memory.
    if settings.views > MAX_VIEWS || settings.width > MAX_SIDE || settings.height > MAX_SIDE {
        return Err(InspectError::Invalid(format!(
            "at most {MAX_VIEWS} views of at most {MAX_SIDE}x{MAX_SIDE} pixels, got {} of {}x{}",
            settings.views, settings.width, settings.height
        )));
    }
    if !(settings.colour_threshold.is_finite() && settings.colour_threshold > 0.0) {
        return Err(InspectError::Invalid(format!(
            "the colour threshold must be positive, got {}",
            settings.colour_threshold
        )));
    }
    if let Some(r) = settings.photometric_radius_mm
        && !(r.is_finite() && r > 0.0)
    {
        return Err(InspectError::Invalid(format!(
            "the photometric radius must be positive, got {r} mm"
        )));
    }
    let candidates: Vec<usize> = match &settings.references {
        None => (0..models.len()).collect(),
        Some(refs) => {
            if refs.iter().any(|&r| r >= models.len()) || refs.len() < 2 {
                return Err(InspectError::Invalid(
                    "references must name at least two of the given models".into(),
                ));
            }
            (0..models.len()).filter(|m| !refs.contains(m)).collect()
        }
    };
    if candidates.is_empty() {
        return Err(InspectError::Invalid(
            "every model is a reference: nothing to inspect".into(),
        ));
    }
    for (i, m) in models.iter().enumerate() {
        m.validate()
            .map_err(|e| InspectError::Invalid(format!("model {i}: {e}")))?;
        if m.len() < 50 {
            return Err(InspectError::Invalid(format!(
                "model {i} has only {} splats",
                m.len()
            )));
        }
    }
    Ok(candidates)
}

/// Every model aligned to the first (the first's own: the identity).
fn align_all(
    models: &[Splats],
    settings: &InspectSettings,
    centre: &Point3<f64>,
    radius: f64,
) -> Result<Vec<Alignment>, InspectError> {
    let points: Vec<PointCloud> = models
        .par_iter()
        .map(|m| model_points(m, &settings.align.filter))
        .collect();
    for (i, p) in points.iter().enumerate() {
        if p.len() < 30 {
            return Err(InspectError::Invalid(format!(
                "model {i}: only {} splats pass the opacity/size filter",
                p.len()
            )));
        }
    }
    let twin_views = sphere_views(centre, 1.15 * radius, 16, 96, 72);
    let twin_reference = render_views(&models[0], &twin_views);
    let mut alignments = vec![Alignment::identity()];
    for i in 1..models.len() {
        let a = align_model(
            &models[i],
            &points[i],
            &points[0],
            &twin_views,
            &twin_reference,
            &settings.align,
        )?;
        if a.fitness < settings.align.min_fitness {
            return Err(InspectError::Alignment {
                model: i,
                fitness: a.fitness,
                min_fitness: settings.align.min_fitness,
            });
        }
        alignments.push(a);
    }
    Ok(alignments)
}

/// Each model's visible surface from its renders, colours matched to the
/// first model's where `photometric_radius_mm` asks.
fn sample_surfaces(
    renders: &[Vec<ViewRender>],
    views: &[View],
    spacing: f64,
    settings: &InspectSettings,
) -> (Vec<PointCloud>, Vec<ColourCorrection>) {
    let unit = settings.units_per_metre / 1000.0;
    let mut surfaces: Vec<PointCloud> = renders
        .par_iter()
        .map(|r| surface_points(r, views, spacing))
        .collect();
    let mut colour_corrections = vec![ColourCorrection::identity(0)];
    let (reference_surface, others) = surfaces.split_at_mut(1);
    colour_corrections.extend(others.iter_mut().enumerate().map(|(k, surface)| {
        match settings.photometric_radius_mm {
            Some(radius) if radius > 0.0 => match_colours(
                k + 1,
                &reference_surface[0],
                surface,
                1.5 * spacing,
                radius * unit,
            ),
            _ => ColourCorrection::identity(k + 1),
        }
    }));
    (surfaces, colour_corrections)
}

/// Every pair of models compared both ways: pixels, and geometric and
/// visual evidence on their surfaces.
fn compare_all(
    renders: &[Vec<ViewRender>],
    surfaces: &[PointCloud],
    views: &[View],
    spacing: f64,
    settings: &InspectSettings,
) -> (Vec<PixelComparison>, Vec<PairEvidence>) {
    let threshold = settings.threshold_mm * settings.units_per_metre / 1000.0;
    let mut pixels = Vec::new();
    let mut pairs = Vec::new();
    for a in 0..renders.len() {
        for b in a + 1..renders.len() {
            pixels.push(compare_pixels(a, b, &renders[a], &renders[b]));
            pairs.push(PairEvidence {
                a,
                b,
                geometric: merge(
                    geometric_evidence(&surfaces[a], &surfaces[b], threshold),
                    depth_evidence(&renders[a], &renders[b], views, threshold, spacing),
                ),
                visual: visual_evidence(
                    &surfaces[a],
                    &surfaces[b],
                    1.5 * spacing,
                    settings.colour_threshold,
                ),
            });
        }
    }
    (pixels, pairs)
}

/// What a close look found counts unless a significant region already
/// holds it (places near one another see the same defect).
fn add_close_up_regions(
    regions: &mut Vec<Region>,
    close_ups: &[CloseUp],
    floors: &[[f64; 2]],
    verdict_settings: &VerdictSettings,
    settings: &InspectSettings,
) {
    for region in close_ups.iter().flat_map(|c| &c.regions) {
        let known = regions.iter().any(|r| {
            r.kind == Kind::Geometric
                && r.significant
                && r.overlaps(region, settings.units_per_metre)
        });
        if region.kind == Kind::Geometric && !known {
            let mut region = region.clone();
            apply_noise_floors(std::slice::from_mut(&mut region), floors, verdict_settings);
            regions.push(region);
        }
    }
}
