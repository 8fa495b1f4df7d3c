//! Aligning each model to the reference (paper, "Defect Inspection": TEASER++
//! global registration on the splat point clouds, refined by ICP).
//!
//! The points are the splat centres that pass an opacity and size filter,
//! cleaned by statistical outlier removal. Global registration
//! ([`omniscan_register::global`]) proposes hypotheses and ranks them by
//! fitness; a part that is nearly symmetric (a bracket, a marker) has
//! twins, poses that fit its geometry almost as well as the right one. Such
//! near-ties are settled here by appearance: the hypothesis whose renders
//! look most like the reference's wins. An alignment whose fitness stays
//! under `min_fitness` is an error, not a guess.

use rayon::prelude::*;
use serde::Serialize;

use omniscan_core::Pose;
use omniscan_register::PointCloud;
use omniscan_register::cloud::{SplatFilter, splat_centres};
use omniscan_register::global::{GlobalSettings, global_registration};
use omniscan_register::preprocess::statistical_inliers;
use omniscan_splat::Splats;
use omniscan_splat::ply::splats_to_ply;

use crate::InspectError;
use crate::views::{View, render_views};

/// Splat centres that pass `filter` (the same filter `omniscan align` uses
/// on splat files), with their DC colour, outliers removed.
pub fn model_points(model: &Splats, filter: &SplatFilter) -> PointCloud {
    let mut cloud = splat_centres(&splats_to_ply(model), filter).unwrap_or_default();
    if cloud.len() > 30 {
        let keep = statistical_inliers(&cloud, 20, 2.0);
        cloud = cloud.select(&keep);
    }
    cloud
}

/// How one model was aligned to the reference.
#[derive(Debug, Clone, Serialize)]
pub struct Alignment {
    /// Maps the model's frame into the reference's.
    #[serde(serialize_with = "rows")]
    pub transform: Pose,
    /// Share of the model's points with a reference point within `max_distance`.
    pub fitness: f64,
    pub inlier_rmse: f64,
    /// Correspondence distance of the final ICP (model units).
    pub max_distance: f64,
    /// The hypothesis that won (`identity` for the reference itself).
    pub method: String,
    /// Hypotheses within 0.03 fitness of the best that appearance had to decide between.
    pub near_ties: usize,
}

fn rows<S: serde::Serializer>(pose: &Pose, s: S) -> Result<S::Ok, S::Error> {
    serde::Serialize::serialize(&omniscan_core::geometry::pose_to_rows(pose), s)
}

impl Alignment {
    pub fn identity() -> Alignment {
        Alignment {
            transform: Pose::identity(),
            fitness: 1.0,
            inlier_rmse: 0.0,
            max_distance: 0.0,
            method: "identity".into(),
            near_ties: 0,
        }
    }
}

/// Settings of the alignment.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlignSettings {
    pub filter: SplatFilter,
    /// Below this final fitness the model counts as not aligned.
    pub min_fitness: f64,
    pub seed: u64,
}

impl Default for AlignSettings {
    fn default() -> Self {
        AlignSettings {
            filter: SplatFilter::default(),
            min_fitness: 0.5,
            seed: 0,
        }
    }
}

/// A global registration whose best fitness is below this is tried again.
const RETRY_BELOW_FITNESS: f64 = 0.95;

/// Mean per-pixel RGB distance between renders of `model` moved by `pose` and
/// the reference's renders, over pixels either covers.
fn appearance_distance(
    model: &Splats,
    pose: &Pose,
    views: &[View],
    reference: &[crate::views::ViewRender],
) -> Result<f64, InspectError> {
    let moved = model.transformed(pose, 1.0)?;
    let renders = render_views(&moved, views);
    let (mut sum, mut count) = (0.0, 0usize);
    for (a, b) in renders.iter().zip(reference) {
        for i in 0..a.alpha.len() {
            if a.alpha[i] < 0.5 && b.alpha[i] < 0.5 {
                continue;
            }
            sum += (0..3)
                .map(|k| (a.rgb[i][k] - b.rgb[i][k]).powi(2) as f64)
                .sum::<f64>()
                .sqrt();
            count += 1;
        }
    }
    Ok(if count == 0 {
        f64::INFINITY
    } else {
        sum / count as f64
    })
}

/// Aligns `model` (points `source`) to the reference (points `target`,
/// renders `reference_renders` from `views`).
pub fn align_model(
    model: &Splats,
    source: &PointCloud,
    target: &PointCloud,
    views: &[View],
    reference_renders: &[crate::views::ViewRender],
    settings: &AlignSettings,
) -> Result<Alignment, InspectError> {
    // Feature matching on splat centres sometimes lands on a wrong pose
    // whose fitness still looks fair (0.75-0.82 where the right pose of a
    // good copy scores 0.99-1.0: measured on the Omni-Scan models). Such a
    // result is retried with other seeds and feature scales, keeping the best.
    let mut result = global_registration(
        source,
        target,
        &GlobalSettings {
            seed: settings.seed,
            ..GlobalSettings::default()
        },
    )?;
    let automatic_voxel = result.voxel;
    for (attempt, scale) in [0.75, 1.33, 0.6, 1.6].into_iter().enumerate() {
        if result.best.registration.fitness >= RETRY_BELOW_FITNESS {
            break;
        }
        let retry = global_registration(
            source,
            target,
            &GlobalSettings {
                seed: settings.seed.wrapping_add(attempt as u64 + 1),
                voxel: Some(scale * automatic_voxel),
                ..GlobalSettings::default()
            },
        );
        tracing::debug!(
            "global registration retried at {scale}x the voxel: fitness {:?}",
            retry.as_ref().map(|r| r.best.registration.fitness).ok()
        );
        if let Ok(retry) = retry
            && retry.best.registration.fitness > result.best.registration.fitness
        {
            result = retry;
        }
    }
    let best_fitness = result
        .candidates
        .iter()
        .map(|c| c.registration.fitness)
        .fold(0.0, f64::max);
    // Distinct near-tied poses (twins) go to the appearance test.
    for c in &result.candidates {
        tracing::debug!(
            "candidate {}: fitness {:.4} rmse {:.4} colour {:?} pose {:?}",
            c.method,
            c.registration.fitness,
            c.registration.inlier_rmse,
            c.color_rmse,
            omniscan_core::geometry::pose_to_rows(&c.registration.transformation)
        );
    }
    let mut ties: Vec<&omniscan_register::global::Candidate> = Vec::new();
    let mut by_fitness: Vec<_> = result.candidates.iter().collect();
    by_fitness.sort_by(|a, b| b.registration.fitness.total_cmp(&a.registration.fitness));
    for c in by_fitness {
        if c.registration.fitness < best_fitness - 0.03 {
            break;
        }
        let distinct = ties.iter().all(|t| {
            let (angle, _) = omniscan_core::geometry::pose_difference(
                &t.registration.transformation,
                &c.registration.transformation,
            );
            angle > 5f64.to_radians()
        });
        if distinct {
            ties.push(c);
        }
    }
    let mut method = result.best.method.to_string();
    let mut transform = result.best.registration.transformation;
    if ties.len() > 1 {
        let scores: Vec<Result<f64, InspectError>> = ties
            .par_iter()
            .map(|c| {
                appearance_distance(
                    model,
                    &c.registration.transformation,
                    views,
                    reference_renders,
                )
            })
            .collect();
        let mut best = (f64::INFINITY, 0);
        for (i, s) in scores.into_iter().enumerate() {
            let s = s?;
            tracing::debug!(
                "twin {i}: fitness {:.4}, appearance {s:.4}",
                ties[i].registration.fitness
            );
            if s < best.0 {
                best = (s, i);
            }
        }
        method = ties[best.1].method.to_string();
        transform = ties[best.1].registration.transformation;
    }
    // Final full-resolution ICP from the chosen hypothesis.
    let spacing = omniscan_register::global::median_spacing(target);
    let max_distance = (3.0 * spacing).max(0.4 * result.voxel);
    let tt = omniscan_register::icp::Target::new(target);
    let refined = omniscan_register::icp::icp(
        source,
        &tt,
        max_distance,
        &transform,
        omniscan_register::icp::Estimator::PointToPoint,
        omniscan_register::icp::Kernel::L2,
        &omniscan_register::icp::Criteria {
            max_iteration: 50,
            ..Default::default()
        },
    )?;
    Ok(Alignment {
        transform: refined.transformation,
        fitness: refined.fitness,
        inlier_rmse: refined.inlier_rmse,
        max_distance,
        method,
        near_ties: ties.len(),
    })
}
