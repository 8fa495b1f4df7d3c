//! From pairwise evidence to a verdict.
//!
//! A difference between two copies says that one of them is odd there, not
//! which. With three or more copies it can be told: a spot belongs to model
//! M when M differs there from every other copy while no two of the other
//! copies differ there. Each kind of evidence (geometric from point
//! differencing, visual from pixel differencing) is attributed that way,
//! attributed points are clustered (DBSCAN) into regions, and regions
//! smaller than a minimum area, or not twice the largest region of their
//! kind on the other copies (the noise floor: what good copies differ by,
//! measured on the copies at hand), are dropped as noise. The defective model is
//! the one whose clearest significant region stands out most: its area over
//! the larger of its noise floor and its kind's minimum area. Comparing
//! areas instead let the larger kind of noise win: on three copies of a
//! fuzzy 130k-splat scene, point differencing left 41-84 mm² regions on
//! every copy, and a copy with a 261 mm² one (3.1 times its floor) was
//! named over the copy with tape (115 mm², 4.6 times its floor). None is
//! named when no model has a significant region. Visual regions inside a geometric region of the
//! same model are part of it (a dent also shades differently). The paper's
//! rule (the pair with the smallest mean pixel distance is the good pair)
//! is reported beside the verdict, and only breaks exact ties.

use nalgebra::Point3;
use serde::Serialize;

use omniscan_register::PointCloud;
use omniscan_register::neighbors::Neighbors;
use omniscan_register::preprocess::dbscan;

use crate::differencing::{Evidence, PixelComparison};

/// Evidence of one pair of models.
#[derive(Debug, Clone, Default)]
pub struct PairEvidence {
    pub a: usize,
    pub b: usize,
    pub geometric: Evidence,
    pub visual: Evidence,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    Geometric,
    Visual,
}

/// A cluster of defect evidence on one model.
#[derive(Debug, Clone, Serialize)]
pub struct Region {
    /// The model's index among those inspected (`model_index` in files,
    /// beside the model's name).
    #[serde(rename = "model_index")]
    pub model: usize,
    pub kind: Kind,
    /// Centre in the reference model's frame and units.
    pub centroid: [f64; 3],
    /// Largest distance between two of its points, millimetres.
    pub extent_mm: f64,
    /// Surface area covered, square millimetres.
    pub area_mm2: f64,
    pub points: usize,
    /// Mean distance to the other copies' surfaces (mm) for geometric
    /// regions, mean RGB distance for visual ones.
    pub mean_difference: f64,
    /// The other copies' largest region of this kind, mm²: what twins of
    /// good copies differ by here (see [`noise_floors`]).
    pub noise_floor_mm2: f64,
    /// Whether the region is over the minimum area for its kind and stands
    /// [`NOISE_RATIO`] times above the noise floor.
    pub significant: bool,
    /// Its area over the larger of its noise floor and its kind's minimum
    /// area: how clearly it stands out against what good copies differ by.
    pub standing_out: f64,
    /// Found by a close look ([`crate::closeup`]) rather than the first pass.
    pub close_up: bool,
}

impl Region {
    /// Whether `other` lies on the same model within this region's extent
    /// or its own (`units_per_metre` of the centroids).
    pub fn overlaps(&self, other: &Region, units_per_metre: f64) -> bool {
        let mm = 1000.0 / units_per_metre;
        self.model == other.model
            && (Point3::from(self.centroid) - Point3::from(other.centroid)).norm() * mm
                <= 0.5 * self.extent_mm + 0.5 * other.extent_mm
    }
}

/// Thresholds of the verdict.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VerdictSettings {
    /// Surface sample spacing (model units).
    pub spacing: f64,
    pub units_per_metre: f64,
    /// Attributed points must have the other pairs' evidence within this (model units).
    pub match_radius: f64,
    pub min_geometric_area_mm2: f64,
    pub min_visual_area_mm2: f64,
}

impl VerdictSettings {
    /// The smallest region of `kind` that counts, mm².
    pub fn minimum_area(&self, kind: Kind) -> f64 {
        match kind {
            Kind::Geometric => self.min_geometric_area_mm2,
            Kind::Visual => self.min_visual_area_mm2,
        }
    }
}

/// The outcome.
#[derive(Debug, Clone, Serialize)]
pub struct Verdict {
    pub defective: Option<usize>,
    /// `geometric`, `visual` or `both`; `none` with no defective model.
    pub defect_type: String,
    /// The verdict's score: how far the defective model's clearest
    /// significant region stands out ([`Region::standing_out`]); 0 with
    /// none named.
    pub score: f64,
    /// Significant area per model (mm²), geometric and visual.
    pub geometric_area_mm2: Vec<f64>,
    pub visual_area_mm2: Vec<f64>,
    pub regions: Vec<Region>,
    /// The model left out of the pair with the smallest mean pixel distance (paper's rule).
    pub pixel_rule_odd_one: Option<usize>,
}

fn evidence_of(pairs: &[PairEvidence], kind: Kind, i: usize) -> &Evidence {
    match kind {
        Kind::Geometric => &pairs[i].geometric,
        Kind::Visual => &pairs[i].visual,
    }
}

/// Points of `model`'s pairs that every other pair with `model` confirms
/// and no pair without it shows.
pub(crate) fn attributed(
    pairs: &[PairEvidence],
    model: usize,
    kind: Kind,
    radius: f64,
) -> Evidence {
    let with: Vec<usize> = (0..pairs.len())
        .filter(|&i| pairs[i].a == model || pairs[i].b == model)
        .collect();
    let without: Vec<usize> = (0..pairs.len()).filter(|i| !with.contains(i)).collect();
    let trees: Vec<Option<Neighbors>> = (0..pairs.len())
        .map(|i| {
            let e = evidence_of(pairs, kind, i);
            (!e.is_empty()).then(|| Neighbors::new(&e.points))
        })
        .collect();
    let near = |i: usize, p: &Point3<f64>| {
        trees[i]
            .as_ref()
            .and_then(|t| t.nearest_within(p, radius))
            .is_some()
    };
    let mut out = Evidence::default();
    for &i in &with {
        let e = evidence_of(pairs, kind, i);
        for (p, m) in e.points.iter().zip(&e.magnitude) {
            let confirmed = with.iter().all(|&j| j == i || near(j, p));
            let contradicted = without.iter().any(|&j| near(j, p));
            if confirmed && !contradicted {
                out.points.push(*p);
                out.magnitude.push(*m);
            }
        }
        // One pair's points are enough: the others would only repeat them.
        if !out.is_empty() {
            break;
        }
    }
    out
}

fn cluster(
    evidence: &Evidence,
    model: usize,
    kind: Kind,
    settings: &VerdictSettings,
) -> Vec<Region> {
    if evidence.is_empty() {
        return Vec::new();
    }
    let cloud = PointCloud {
        points: evidence.points.clone(),
        ..Default::default()
    };
    let labels = dbscan(&cloud, 2.5 * settings.spacing, 3);
    let clusters = labels.iter().copied().max().unwrap_or(-1) + 1;
    let mm = 1000.0 / settings.units_per_metre;
    let point_area = (settings.spacing * mm).powi(2);
    (0..clusters)
        .filter_map(|c| {
            let members: Vec<usize> = (0..labels.len()).filter(|&i| labels[i] == c).collect();
            if members.is_empty() {
                return None;
            }
            let centroid = members.iter().fold(nalgebra::Vector3::zeros(), |s, &i| {
                s + evidence.points[i].coords
            }) / members.len() as f64;
            let mut extent: f64 = 0.0;
            for (k, &i) in members.iter().enumerate() {
                for &j in &members[k + 1..] {
                    extent = extent.max((evidence.points[i] - evidence.points[j]).norm());
                }
            }
            let mean =
                members.iter().map(|&i| evidence.magnitude[i]).sum::<f64>() / members.len() as f64;
            let area = members.len() as f64 * point_area;
            let minimum = settings.minimum_area(kind);
            Some(Region {
                model,
                kind,
                centroid: [centroid.x, centroid.y, centroid.z],
                extent_mm: extent * mm,
                area_mm2: area,
                points: members.len(),
                mean_difference: match kind {
                    Kind::Geometric => mean * mm,
                    Kind::Visual => mean,
                },
                noise_floor_mm2: 0.0,
                significant: area >= minimum,
                standing_out: area / minimum.max(f64::MIN_POSITIVE),
                close_up: false,
            })
        })
        .collect()
}

/// How many times a region must exceed the other copies' largest region of
/// its kind to count.
pub const NOISE_RATIO: f64 = 2.0;

fn kind_index(kind: Kind) -> usize {
    match kind {
        Kind::Geometric => 0,
        Kind::Visual => 1,
    }
}

/// Per model, per kind (geometric, visual), the area a region of that model
/// must stand out against: the largest region of the kind on the other
/// copies (the upper median of those when there are more than two others,
/// so a second defective copy does not raise the floor). `regions` must hold
/// every model's regions, references included.
///
/// Copies made from one model differ by resampling and noise, and their
/// regions stay under the minimum areas; twins scanned and trained one by
/// one differ everywhere a little (`omniscan bench scans`: regions of
/// 7-54 mm² on good twins, from their own floaters, unseen patches and
/// baked-in highlights). A defect must stand out against that, whatever its
/// absolute size: a copy is only named when it differs from the others
/// clearly more than they differ among themselves.
pub fn noise_floors(models: usize, regions: &[Region]) -> Vec<[f64; 2]> {
    let mut largest = vec![[0.0f64; 2]; models];
    for r in regions {
        let slot = &mut largest[r.model][kind_index(r.kind)];
        *slot = slot.max(r.area_mm2);
    }
    (0..models)
        .map(|m| {
            [0, 1].map(|k| {
                let mut others: Vec<f64> = (0..models)
                    .filter(|&o| o != m)
                    .map(|o| largest[o][k])
                    .collect();
                others.sort_by(f64::total_cmp);
                others.get(others.len() / 2).copied().unwrap_or(0.0)
            })
        })
        .collect()
}

/// Marks regions that do not stand [`NOISE_RATIO`] times above their
/// model's noise floor as not significant, and measures how far each
/// stands out.
pub fn apply_noise_floors(regions: &mut [Region], floors: &[[f64; 2]], settings: &VerdictSettings) {
    for r in regions {
        let floor = floors.get(r.model).map_or(0.0, |f| f[kind_index(r.kind)]);
        let minimum = settings.minimum_area(r.kind);
        r.noise_floor_mm2 = floor;
        r.significant &= r.area_mm2 >= NOISE_RATIO * floor;
        r.standing_out = r.area_mm2 / floor.max(minimum).max(f64::MIN_POSITIVE);
    }
}

/// The candidates' regions with their noise floors applied, and every
/// model's floors. Regions are found for every model, references too:
/// those measure how much good copies differ.
pub fn candidate_regions(
    models: usize,
    candidates: &[usize],
    pairs: &[PairEvidence],
    settings: &VerdictSettings,
) -> (Vec<Region>, Vec<[f64; 2]>) {
    let every: Vec<usize> = (0..models).collect();
    let mut regions = find_regions(&every, pairs, settings);
    let floors = noise_floors(models, &regions);
    regions.retain(|r| candidates.contains(&r.model));
    apply_noise_floors(&mut regions, &floors, settings);
    (regions, floors)
}

/// Decides which of `models` models is defective. `candidates` are the
/// models that may be named (all, or those not given as references).
pub fn decide(
    models: usize,
    candidates: &[usize],
    pairs: &[PairEvidence],
    pixels: &[PixelComparison],
    settings: &VerdictSettings,
) -> Verdict {
    let (regions, _) = candidate_regions(models, candidates, pairs, settings);
    name_defective(
        models,
        candidates,
        regions,
        pixels,
        settings.units_per_metre,
    )
}

/// Every candidate's regions of attributed evidence, significant or not.
pub fn find_regions(
    candidates: &[usize],
    pairs: &[PairEvidence],
    settings: &VerdictSettings,
) -> Vec<Region> {
    let mut regions = Vec::new();
    for &m in candidates {
        for kind in [Kind::Geometric, Kind::Visual] {
            regions.extend(cluster(
                &attributed(pairs, m, kind, settings.match_radius),
                m,
                kind,
                settings,
            ));
        }
    }
    regions
}

/// The verdict from the regions found: the candidate with the largest
/// significant area is defective.
pub fn name_defective(
    models: usize,
    candidates: &[usize],
    mut regions: Vec<Region>,
    pixels: &[PixelComparison],
    units_per_metre: f64,
) -> Verdict {
    // A visual difference inside a geometric region of the same model is
    // part of it (a dent also shades differently).
    let geometric: Vec<Region> = regions
        .iter()
        .filter(|g| g.kind == Kind::Geometric && g.significant)
        .cloned()
        .collect();
    regions.retain(|v| {
        v.kind == Kind::Geometric || !geometric.iter().any(|g| g.overlaps(v, units_per_metre))
    });
    let mut geometric_area = vec![0.0; models];
    let mut visual_area = vec![0.0; models];
    let mut standing_out = vec![0.0f64; models];
    for r in regions.iter().filter(|r| r.significant) {
        match r.kind {
            Kind::Geometric => geometric_area[r.model] += r.area_mm2,
            Kind::Visual => visual_area[r.model] += r.area_mm2,
        }
        standing_out[r.model] = standing_out[r.model].max(r.standing_out);
    }
    regions.sort_by(|a, b| {
        b.significant
            .cmp(&a.significant)
            .then(b.area_mm2.total_cmp(&a.area_mm2))
    });
    // Paper's rule: the pair with the smallest mean pixel distance is good.
    let pixel_rule_odd_one = (models == 3)
        .then(|| {
            pixels
                .iter()
                .min_by(|a, b| a.mean_l2.total_cmp(&b.mean_l2))
                .map(|p| 3 - p.a - p.b)
        })
        .flatten();
    // The clearest region first, then the larger significant area, then
    // the paper's rule.
    let total = |m: usize| geometric_area[m] + visual_area[m];
    let rank = |m: usize| (standing_out[m], total(m), pixel_rule_odd_one == Some(m));
    let defective = candidates
        .iter()
        .copied()
        .filter(|&m| standing_out[m] > 0.0)
        .max_by(|&a, &b| {
            let (ra, rb) = (rank(a), rank(b));
            ra.0.total_cmp(&rb.0)
                .then(ra.1.total_cmp(&rb.1))
                .then(ra.2.cmp(&rb.2))
                .then(b.cmp(&a))
        });
    let defect_type = match defective {
        None => "none",
        Some(d) => match (geometric_area[d] > 0.0, visual_area[d] > 0.0) {
            (true, true) => "both",
            (true, false) => "geometric",
            _ => "visual",
        },
    }
    .to_string();
    Verdict {
        defective,
        defect_type,
        score: defective.map_or(0.0, |d| standing_out[d]),
        geometric_area_mm2: geometric_area,
        visual_area_mm2: visual_area,
        regions,
        pixel_rule_odd_one,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::differencing::merge;

    fn patch(centre: [f64; 3], side: usize, spacing: f64) -> Evidence {
        let mut e = Evidence::default();
        for i in 0..side * side {
            e.points.push(Point3::new(
                centre[0] + (i % side) as f64 * spacing,
                centre[1] + (i / side) as f64 * spacing,
                centre[2],
            ));
            e.magnitude.push(0.006);
        }
        e
    }

    fn settings() -> VerdictSettings {
        VerdictSettings {
            spacing: 0.001,
            units_per_metre: 1.0,
            match_radius: 0.003,
            min_geometric_area_mm2: 4.0,
            min_visual_area_mm2: 2.0,
        }
    }

    #[test]
    fn the_model_that_differs_from_both_others_is_defective() {
        // Model 2 has a 6x6 mm bump: pairs (0,2) and (1,2) show it; a small
        // noise spot shows between 0 and 1 only.
        let bump = patch([0.0, 0.0, 0.0], 6, 0.001);
        let pairs = vec![
            PairEvidence {
                a: 0,
                b: 1,
                geometric: patch([0.05, 0.0, 0.0], 2, 0.001),
                ..Default::default()
            },
            PairEvidence {
                a: 0,
                b: 2,
                geometric: bump.clone(),
                ..Default::default()
            },
            PairEvidence {
                a: 1,
                b: 2,
                geometric: bump,
                ..Default::default()
            },
        ];
        let v = decide(3, &[0, 1, 2], &pairs, &[], &settings());
        assert_eq!(v.defective, Some(2));
        assert_eq!(v.defect_type, "geometric");
        // 36 mm² against no floor: nine times the 4 mm² minimum.
        assert!((v.score - 9.0).abs() < 1e-9, "{}", v.score);
        assert!((v.geometric_area_mm2[2] - 36.0).abs() < 1e-9);
        let r = &v.regions[0];
        assert_eq!(r.model, 2);
        assert!(r.significant);
        assert!((r.extent_mm - (50f64).sqrt()).abs() < 1e-6);
    }

    #[test]
    fn a_copy_is_named_only_when_it_stands_out_against_the_others() {
        // Model 2 has a 6x6 mm difference, model 0 one of 5x5 mm elsewhere:
        // both over the minimum area, but neither twice the other's.
        let on_two = patch([0.0, 0.0, 0.0], 6, 0.001);
        let on_zero = patch([0.05, 0.0, 0.0], 5, 0.001);
        let pairs = |zero: &Evidence| {
            vec![
                PairEvidence {
                    a: 0,
                    b: 1,
                    geometric: zero.clone(),
                    ..Default::default()
                },
                PairEvidence {
                    a: 0,
                    b: 2,
                    geometric: merge(zero.clone(), on_two.clone()),
                    ..Default::default()
                },
                PairEvidence {
                    a: 1,
                    b: 2,
                    geometric: on_two.clone(),
                    ..Default::default()
                },
            ]
        };
        let v = decide(3, &[0, 1, 2], &pairs(&on_zero), &[], &settings());
        assert_eq!(v.defective, None, "{:?}", v.regions);
        let floors: Vec<f64> = v.regions.iter().map(|r| r.noise_floor_mm2).collect();
        assert!(
            floors.contains(&25.0) && floors.contains(&36.0),
            "{floors:?}"
        );
        // A 3x3 mm difference on model 0 is noise the 6x6 stands out against.
        let small = patch([0.05, 0.0, 0.0], 3, 0.001);
        let v = decide(3, &[0, 1, 2], &pairs(&small), &[], &settings());
        assert_eq!(v.defective, Some(2));
        // With 0 and 1 as references, model 0's difference still sets the floor.
        let v = decide(3, &[2], &pairs(&on_zero), &[], &settings());
        assert_eq!(v.defective, None);
    }

    #[test]
    fn the_copy_that_stands_out_more_is_named_not_the_larger_area() {
        // Point differencing is noisy here: 5x5 mm geometric differences on
        // models 1 and 2, and one of 8x8 mm on model 0 (64 mm², 2.6 times
        // the others' 25). Model 2 also has a 4x4 mm visual difference
        // where the other copies agree in colour (16 mm², 8 times the
        // 2 mm² minimum): it stands out more, and is named.
        let noise = |x: f64, side: usize| patch([x, 0.0, 0.0], side, 0.001);
        let (g0, g1, g2) = (noise(0.0, 8), noise(0.05, 5), noise(0.1, 5));
        let mark = patch([0.1, 0.05, 0.0], 4, 0.001);
        let pairs = vec![
            PairEvidence {
                a: 0,
                b: 1,
                geometric: merge(g0.clone(), g1.clone()),
                ..Default::default()
            },
            PairEvidence {
                a: 0,
                b: 2,
                geometric: merge(g0, g2.clone()),
                visual: mark.clone(),
            },
            PairEvidence {
                a: 1,
                b: 2,
                geometric: merge(g1, g2),
                visual: mark,
            },
        ];
        let v = decide(3, &[0, 1, 2], &pairs, &[], &settings());
        let significant: Vec<(usize, Kind, f64)> = v
            .regions
            .iter()
            .filter(|r| r.significant)
            .map(|r| (r.model, r.kind, r.area_mm2))
            .collect();
        assert!(
            significant.contains(&(0, Kind::Geometric, 64.0))
                && significant.contains(&(2, Kind::Visual, 16.0)),
            "{significant:?}"
        );
        assert_eq!(v.defective, Some(2), "{:?}", v.regions);
        assert_eq!(v.defect_type, "visual");
        assert!((v.score - 8.0).abs() < 1e-9, "{}", v.score);
    }

    #[test]
    fn agreeing_copies_give_no_defect() {
        let noise = patch([0.0, 0.0, 0.0], 1, 0.001);
        let pairs = vec![
            PairEvidence {
                a: 0,
                b: 1,
                visual: noise.clone(),
                ..Default::default()
            },
            PairEvidence {
                a: 0,
                b: 2,
                ..Default::default()
            },
            PairEvidence {
                a: 1,
                b: 2,
                visual: noise,
                ..Default::default()
            },
        ];
        let v = decide(3, &[0, 1, 2], &pairs, &[], &settings());
        assert_eq!(v.defective, None);
        assert_eq!(v.defect_type, "none");
    }

    #[test]
    fn a_difference_the_good_pair_also_shows_is_not_attributed() {
        let spot = patch([0.0, 0.0, 0.0], 5, 0.001);
        let pairs = vec![
            PairEvidence {
                a: 0,
                b: 1,
                visual: spot.clone(),
                ..Default::default()
            },
            PairEvidence {
                a: 0,
                b: 2,
                visual: spot.clone(),
                ..Default::default()
            },
            PairEvidence {
                a: 1,
                b: 2,
                visual: spot,
                ..Default::default()
            },
        ];
        let v = decide(3, &[0, 1, 2], &pairs, &[], &settings());
        assert_eq!(v.defective, None);
    }
}
