//! What an inspection leaves on disk, every file written atomically:
//! `verdict.json`, colourised difference renders (`diff_*.png`: the two
//! renders and their per-pixel difference), the defect point cloud
//! (`defects.ply`, red = defect, green = agreed) with a picture of it, and
//! `report.html`, which shows all of it from relative paths and opens in a
//! browser from the folder, no server needed.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::Serialize;

use omniscan_core::image_io::{RgbImage, write_rgb};
use omniscan_core::io::{write_atomic, write_json_atomic};
use omniscan_register::PointCloud;
use omniscan_register::cloud::write_ply;
use omniscan_register::neighbors::Neighbors;
use omniscan_splat::Splats;

use crate::InspectError;
use crate::differencing::difference_map;
use crate::inspect::{InspectSettings, Inspection, Timings};
use crate::photometric::RenderCorrection;
use crate::verdict::Region;
use crate::views::ViewRender;

#[derive(Serialize)]
struct AlignmentEntry<'a> {
    model: String,
    #[serde(flatten)]
    alignment: &'a crate::align::Alignment,
}

#[derive(Serialize)]
struct RegionEntry<'a> {
    model: String,
    #[serde(flatten)]
    region: &'a Region,
}

#[derive(Serialize)]
struct PixelEntry {
    a: String,
    b: String,
    mean_l2: f64,
    mean_l2_object: f64,
}

#[derive(Serialize)]
struct PointEntry {
    a: String,
    b: String,
    defect_points: usize,
    visual_points: usize,
    surface_points_a: usize,
    surface_points_b: usize,
}

/// The verdict file's content.
#[derive(Serialize)]
pub struct VerdictFile<'a> {
    /// Path of the defective model, or null.
    defective: Option<String>,
    defective_index: Option<usize>,
    #[serde(rename = "type")]
    defect_type: &'a str,
    /// How far the defective model's clearest significant region stands
    /// out: its area over the larger of its noise floor and its kind's
    /// minimum area (0 with none named).
    score: f64,
    /// Significant defect area of the defective model, mm² (0 with none).
    defect_area_mm2: f64,
    models: Vec<String>,
    references: Option<Vec<String>>,
    regions: Vec<RegionEntry<'a>>,
    alignment: Vec<AlignmentEntry<'a>>,
    pixel_differencing: serde_json::Value,
    point_differencing: serde_json::Value,
    /// How each model's colours were matched to the first's before the
    /// visual comparison (gains per channel, reference over model).
    colour_matching: serde_json::Value,
    combination: &'static str,
    units_per_metre: f64,
    threshold_mm: f64,
    views: usize,
    /// Where the views are: spread over a sphere around the first model, or
    /// the given cameras (each zoomed onto the part).
    views_from: String,
    timings_s: &'a Timings,
}

const COMBINATION: &str = "Both differencing methods locate evidence on the surface: point \
differencing gives surface points farther than the threshold from the other model, pixel \
differencing gives pixels that differ in colour (depth agreeing) back-projected and kept where \
most views agree. A spot counts against a model when it differs there from every other model \
and the others agree there; such spots are clustered into regions. With --close-up, where a \
little geometric evidence (too little for a region) points at one model, that place is rendered \
again from up to 16 of the views that see it, zoomed to 0.4 mm pixels, and judged by the same \
rules (its regions have close_up true). A region is significant when it is over the minimum area \
of its kind and at least twice its noise floor: the largest region of the same kind on the other \
models (twins of good copies differ a little everywhere). The defective model is the one whose \
clearest significant region stands out most: its area over the larger of its noise floor and its \
kind's minimum area (standing_out; the verdict's score), the larger significant area breaking ties \
(none when no region is significant). Before colours are compared, each \
model's surface colours are matched to the first model's by a gain that varies slowly over the \
surface (colour_matching: lighting is baked into each scan). The paper's rule (the pair with the \
smallest mean pixel distance is the good pair, on raw renders) is reported and breaks exact ties.";

fn name(paths: &[PathBuf], i: usize) -> String {
    paths
        .get(i)
        .map(|p| p.display().to_string())
        .unwrap_or_else(|| format!("model {i}"))
}

/// Builds the verdict file's content.
pub fn verdict_file<'a>(
    inspection: &'a Inspection,
    paths: &[PathBuf],
    settings: &InspectSettings,
) -> VerdictFile<'a> {
    let v = &inspection.verdict;
    VerdictFile {
        defective: v.defective.map(|d| name(paths, d)),
        defective_index: v.defective,
        defect_type: &v.defect_type,
        score: v.score,
        defect_area_mm2: v
            .defective
            .map_or(0.0, |d| v.geometric_area_mm2[d] + v.visual_area_mm2[d]),
        models: (0..inspection.renders.len())
            .map(|i| name(paths, i))
            .collect(),
        references: settings
            .references
            .as_ref()
            .map(|r| r.iter().map(|&i| name(paths, i)).collect()),
        regions: v
            .regions
            .iter()
            .map(|r| RegionEntry {
                model: name(paths, r.model),
                region: r,
            })
            .collect(),
        alignment: inspection
            .alignments
            .iter()
            .enumerate()
            .map(|(i, a)| AlignmentEntry {
                model: name(paths, i),
                alignment: a,
            })
            .collect(),
        pixel_differencing: serde_json::json!({
            "pairs": inspection.pixels.iter().map(|p| PixelEntry {
                a: name(paths, p.a),
                b: name(paths, p.b),
                mean_l2: p.mean_l2,
                mean_l2_object: p.mean_l2_object,
            }).collect::<Vec<_>>(),
            "odd_one_out": v.pixel_rule_odd_one.map(|i| name(paths, i)),
        }),
        point_differencing: serde_json::json!({
            "threshold_mm": settings.threshold_mm,
            "pairs": inspection.pairs.iter().map(|p| PointEntry {
                a: name(paths, p.a),
                b: name(paths, p.b),
                defect_points: p.geometric.len(),
                visual_points: p.visual.len(),
                surface_points_a: inspection.surfaces[p.a].len(),
                surface_points_b: inspection.surfaces[p.b].len(),
            }).collect::<Vec<_>>(),
            "close_ups": inspection.close_ups.iter().map(|c| serde_json::json!({
                "model": name(paths, c.model),
                "centre": [c.centre.x, c.centre.y, c.centre.z],
                "radius_mm": c.radius * 1000.0 / settings.units_per_metre,
                "views": c.views.len(),
                "significant_regions": c.regions.iter().filter(|r| r.significant).count(),
            })).collect::<Vec<_>>(),
        }),
        colour_matching: serde_json::json!({
            "radius_mm": settings.photometric_radius_mm,
            "models": inspection.colour_corrections.iter().map(|c| serde_json::json!({
                "model": name(paths, c.model),
                "samples": c.samples,
                "median_gain": c.median_gain,
                "luminance_gain_p05_p95": c.gain_range,
            })).collect::<Vec<_>>(),
        }),
        combination: COMBINATION,
        units_per_metre: settings.units_per_metre,
        threshold_mm: settings.threshold_mm,
        views: inspection.views.len(),
        views_from: settings.cameras.as_ref().map_or_else(
            || "sphere around the first model".to_string(),
            |c| format!("cameras of {}", c.source),
        ),
        timings_s: &inspection.timings,
    }
}

fn to_bytes(c: [f32; 3]) -> [u8; 3] {
    c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
}

/// Black → red → yellow → white as the difference grows to `full`.
pub fn heat(value: f32, full: f32) -> [u8; 3] {
    let t = (value / full).clamp(0.0, 1.0) * 3.0;
    let c = [
        t.min(1.0),
        (t - 1.0).clamp(0.0, 1.0),
        (t - 2.0).clamp(0.0, 1.0),
    ];
    to_bytes(c)
}

/// The two renders side by side with their difference.
pub fn difference_image(a: &ViewRender, b: &ViewRender) -> RgbImage {
    let (w, h) = (a.width as usize, a.height as usize);
    let diff = difference_map(a, b);
    let mut data = vec![0u8; 3 * w * 3 * h];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let row = y * 3 * w;
            let pixels = [to_bytes(a.rgb[i]), to_bytes(b.rgb[i]), heat(diff[i], 0.5)];
            for (panel, rgb) in pixels.iter().enumerate() {
                let o = 3 * (row + panel * w + x);
                data[o..o + 3].copy_from_slice(rgb);
            }
        }
    }
    RgbImage {
        width: 3 * w as u32,
        height: h as u32,
        data,
    }
}

fn significant_regions(inspection: &Inspection, model: usize) -> Vec<&Region> {
    inspection
        .verdict
        .regions
        .iter()
        .filter(|r| r.model == model && r.significant)
        .collect()
}

/// How far from its centroid a region reaches (model units): half its
/// extent and two sample spacings.
fn region_reach(region: &Region, spacing: f64, units_per_metre: f64) -> f64 {
    0.5 * region.extent_mm * units_per_metre / 1000.0 + 2.0 * spacing
}

/// Per view, the area (mm²) of `model`'s significant regions whose centre
/// it sees: in the image and not hidden behind another part of the model.
fn region_views(
    inspection: &Inspection,
    model: usize,
    spacing: f64,
    units_per_metre: f64,
) -> Vec<f64> {
    let regions = significant_regions(inspection, model);
    inspection
        .views
        .iter()
        .zip(&inspection.renders[model])
        .map(|(view, render)| {
            let to_camera = view.camera_to_world.inverse();
            let k = &view.intrinsics;
            regions
                .iter()
                .filter(|r| {
                    let q = to_camera * nalgebra::Point3::from(r.centroid);
                    if q.z <= 0.0 {
                        return false;
                    }
                    let (u, v) = (k.fx * q.x / q.z + k.cx, k.fy * q.y / q.z + k.cy);
                    if u < 0.0 || v < 0.0 || u >= render.width as f64 || v >= render.height as f64 {
                        return false;
                    }
                    let i = v as usize * render.width as usize + u as usize;
                    let reach = region_reach(r, spacing, units_per_metre);
                    render
                        .surface_depth(i, 0.5)
                        .is_some_and(|z| (z as f64 - q.z).abs() <= reach)
                })
                .map(|r| r.area_mm2)
                .sum()
        })
        .collect()
}

/// The defective model's surface (or the reference's), red where it is
/// part of a significant region, green elsewhere.
pub fn defect_cloud(inspection: &Inspection, spacing: f64, units_per_metre: f64) -> PointCloud {
    let model = inspection.verdict.defective.unwrap_or(0);
    let surface = &inspection.surfaces[model];
    let evidence: Vec<nalgebra::Point3<f64>> = inspection
        .pairs
        .iter()
        .filter(|p| p.a == model || p.b == model)
        .flat_map(|p| p.geometric.points.iter().chain(&p.visual.points).copied())
        .collect();
    let regions = significant_regions(inspection, model);
    let tree = (!evidence.is_empty()).then(|| Neighbors::new(&evidence));
    let mut cloud = surface.clone();
    for (i, p) in surface.points.iter().enumerate() {
        let near_evidence = tree
            .as_ref()
            .is_some_and(|t| t.nearest_within(p, 1.5 * spacing).is_some());
        let in_region = regions.iter().any(|r| {
            let c = nalgebra::Point3::from(r.centroid);
            (p - c).norm() <= region_reach(r, spacing, units_per_metre)
        });
        cloud.colors[i] = if near_evidence && in_region {
            [0.9, 0.1, 0.1]
        } else {
            [0.2, 0.75, 0.25]
        };
    }
    cloud
}

/// Three orthographic views (along x, y, z) of a coloured cloud.
pub fn cloud_picture(cloud: &PointCloud, size: u32) -> RgbImage {
    let s = size as usize;
    let mut data = vec![255u8; 3 * s * 3 * s];
    if cloud.is_empty() {
        return RgbImage {
            width: 3 * size,
            height: size,
            data,
        };
    }
    let c = cloud.centroid();
    let radius = cloud
        .points
        .iter()
        .map(|p| (p - c).norm())
        .fold(0.0, f64::max)
        .max(1e-12);
    // Draw red last so defects are never hidden behind agreed points.
    let mut order: Vec<usize> = (0..cloud.len()).collect();
    order.sort_by(|&a, &b| cloud.colors[a][0].total_cmp(&cloud.colors[b][0]));
    for (panel, (u, v)) in [(1usize, 2usize), (0, 2), (0, 1)].into_iter().enumerate() {
        for &i in &order {
            let p = cloud.points[i] - c;
            let x = ((p[u] / radius * 0.48 + 0.5) * s as f64) as i64;
            let y = ((0.5 - p[v] / radius * 0.48) * s as f64) as i64;
            for dy in 0..2 {
                for dx in 0..2 {
                    let (x, y) = (x + dx, y + dy);
                    if x < 0 || y < 0 || x >= s as i64 || y >= s as i64 {
                        continue;
                    }
                    let o = 3 * (y as usize * 3 * s + panel * s + x as usize);
                    data[o..o + 3].copy_from_slice(&to_bytes(cloud.colors[i]));
                }
            }
        }
    }
    RgbImage {
        width: 3 * size,
        height: size,
        data,
    }
}

fn escape(text: &str) -> String {
    omniscan_view::escape_html(text)
}

/// The copies in 3D, aligned onto the first, one at a time or side by
/// side, with their significant regions as markers (red: geometric, amber:
/// visual) labelled as in the table below.
fn viewer_section(
    inspection: &Inspection,
    models: &[Splats],
    paths: &[PathBuf],
    settings: &InspectSettings,
) -> Result<String, InspectError> {
    let mut aligned = Vec::with_capacity(models.len());
    for ((model, alignment), path) in models.iter().zip(&inspection.alignments).zip(paths) {
        let model = model
            .transformed(&alignment.transform, 1.0)
            .map_err(|e| InspectError::file(path, e.to_string()))?;
        aligned.push(model);
    }
    let mm = settings.units_per_metre / 1000.0;
    let models: Vec<omniscan_view::ViewerModel> = aligned
        .iter()
        .enumerate()
        .map(|(i, splats)| omniscan_view::ViewerModel {
            name: name(paths, i),
            splats,
            markers: significant_regions(inspection, i)
                .into_iter()
                .enumerate()
                .map(|(k, r)| omniscan_view::Marker {
                    label: format!("{:?} {} ({:.1} mm²)", r.kind, k + 1, r.area_mm2),
                    position: r.centroid.map(|v| v as f32),
                    radius: ((0.5 * r.extent_mm).max(1.0) * mm) as f32,
                    colour: match r.kind {
                        crate::verdict::Kind::Geometric => [230, 40, 40],
                        _ => [255, 176, 0],
                    },
                })
                .collect(),
        })
        .collect();
    let viewer = omniscan_view::viewer_html(&models)
        .map_err(|e| InspectError::file(&paths[0], e.to_string()))?;
    Ok(format!(
        "<h2>The copies in 3D</h2><p>Aligned onto {}; the buttons show one copy or all side by side, \
         the markers the significant regions.</p>{viewer}",
        escape(&name(paths, 0))
    ))
}

/// Writes every output into `out`; returns the verdict file's path.
/// `verdict.json` is written last, and an earlier one removed first: its
/// presence says the report beside it is whole (a full disk used to leave
/// a verdict without its report).
pub fn write_report(
    out: &Path,
    inspection: &Inspection,
    models: &[Splats],
    paths: &[PathBuf],
    settings: &InspectSettings,
) -> Result<PathBuf, InspectError> {
    std::fs::create_dir_all(out).map_err(|e| InspectError::file(out, e.to_string()))?;
    let verdict_path = out.join("verdict.json");
    match std::fs::remove_file(&verdict_path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            return Err(InspectError::file(&verdict_path, e.to_string()));
        }
        _ => {}
    }

    // Difference renders: for each pair with the defective model (every
    // pair when none), the four views that see most of its significant
    // regions, else where the pair differs most; colours matched as the
    // visual comparison matched them.
    let focus = inspection.verdict.defective;
    let spacing = settings.spacing_mm * settings.units_per_metre / 1000.0;
    let mut images: Vec<(String, String)> = Vec::new();
    let corrections: Vec<RenderCorrection> = inspection
        .surfaces
        .iter()
        .zip(&inspection.colour_corrections)
        .map(|(surface, correction)| RenderCorrection::new(surface, correction))
        .collect();
    for p in &inspection.pixels {
        if focus.is_some_and(|d| p.a != d && p.b != d) {
            continue;
        }
        let seen: Vec<f64> = match focus {
            Some(d) => region_views(inspection, d, spacing, settings.units_per_metre),
            None => vec![0.0; p.per_view.len()],
        };
        let mut order: Vec<usize> = (0..p.per_view.len()).collect();
        order.sort_by(|&x, &y| {
            seen[y]
                .total_cmp(&seen[x])
                .then(p.per_view[y].total_cmp(&p.per_view[x]))
        });
        for &v in order.iter().take(4) {
            let file = format!("diff_{}_{}_view{:03}.png", p.a, p.b, v);
            let matched =
                |m: usize| corrections[m].apply(&inspection.renders[m][v], &inspection.views[v]);
            let image = difference_image(&matched(p.a), &matched(p.b));
            write_rgb(&out.join(&file), &image)?;
            images.push((
                file,
                format!(
                    "{} | {} | difference (view {v}, mean {:.3})",
                    name(paths, p.a),
                    name(paths, p.b),
                    p.per_view[v]
                ),
            ));
        }
    }
    let cloud = defect_cloud(inspection, spacing, settings.units_per_metre);
    write_ply(&out.join("defects.ply"), &cloud)?;
    write_rgb(&out.join("defects.png"), &cloud_picture(&cloud, 360))?;

    let v = &inspection.verdict;
    let mut html = String::new();
    let _ = write!(
        html,
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>omniscan inspection</title>\
         <style>body{{font-family:sans-serif;margin:2em;max-width:1200px}}\
         table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:4px 8px;text-align:right}}\
         th{{background:#eee}}img{{max-width:100%;image-rendering:pixelated}}\
         .verdict{{font-size:1.4em;padding:0.6em;background:{}}}#omniscan-viewer{{height:520px}}</style></head><body>\
         <h1>omniscan inspection</h1><p class=\"verdict\">",
        if v.defective.is_some() {
            "#fdd"
        } else {
            "#dfd"
        }
    );
    match v.defective {
        Some(d) => {
            let _ = write!(
                html,
                "Defective: <b>{}</b> ({} defect, {:.1} mm² of significant regions, the clearest \
                 {:.1} times what the other copies differ by)",
                escape(&name(paths, d)),
                escape(&v.defect_type),
                v.geometric_area_mm2[d] + v.visual_area_mm2[d],
                v.score
            );
        }
        None => {
            html.push_str("No defective model: every copy agrees within the noise of good copies.")
        }
    }
    html.push_str("</p>");
    html.push_str(&viewer_section(inspection, models, paths, settings)?);
    html.push_str("<h2>Regions</h2><table><tr><th>model</th><th>kind</th><th>centroid (model units)</th>\
                   <th>extent mm</th><th>area mm²</th><th>noise floor mm²</th><th>standing out</th><th>mean difference</th><th>significant</th></tr>");
    for r in &v.regions {
        let _ = write!(
            html,
            "<tr><td>{}</td><td>{:?}</td><td>{:.4}, {:.4}, {:.4}</td><td>{:.1}</td><td>{:.1}</td><td>{:.1}</td><td>{:.1}</td><td>{:.3}</td><td>{}</td></tr>",
            escape(&name(paths, r.model)),
            r.kind,
            r.centroid[0],
            r.centroid[1],
            r.centroid[2],
            r.extent_mm,
            r.area_mm2,
            r.noise_floor_mm2,
            r.standing_out,
            r.mean_difference,
            if r.significant { "yes" } else { "no" }
        );
    }
    html.push_str(
        "</table><h2>Alignment to the first model</h2><table><tr><th>model</th><th>fitness</th>\
                   <th>inlier RMSE</th><th>method</th></tr>",
    );
    for (i, a) in inspection.alignments.iter().enumerate() {
        let _ = write!(
            html,
            "<tr><td>{}</td><td>{:.3}</td><td>{:.5}</td><td>{}</td></tr>",
            escape(&name(paths, i)),
            a.fitness,
            a.inlier_rmse,
            escape(&a.method)
        );
    }
    html.push_str("</table><h2>Pixel differencing (paper)</h2><table><tr><th>pair</th><th>mean L2, all pixels</th>\
                   <th>mean L2, object pixels</th></tr>");
    for p in &inspection.pixels {
        let _ = write!(
            html,
            "<tr><td>{} / {}</td><td>{:.4}</td><td>{:.4}</td></tr>",
            escape(&name(paths, p.a)),
            escape(&name(paths, p.b)),
            p.mean_l2,
            p.mean_l2_object
        );
    }
    html.push_str("</table>");
    if let Some(odd) = v.pixel_rule_odd_one {
        let _ = write!(
            html,
            "<p>Paper's rule (smallest pair is good): odd one out is {}.</p>",
            escape(&name(paths, odd))
        );
    }
    html.push_str(
        "<h2>Point differencing</h2><table><tr><th>pair</th><th>points over threshold</th></tr>",
    );
    for p in &inspection.pairs {
        let _ = write!(
            html,
            "<tr><td>{} / {}</td><td>{}</td></tr>",
            escape(&name(paths, p.a)),
            escape(&name(paths, p.b)),
            p.geometric.len()
        );
    }
    let _ = write!(
        html,
        "</table><h2>Defect points</h2><p>Surface of {} seen along x, y and z: red = defect, green = agreed \
         (<a href=\"defects.ply\">defects.ply</a>).</p><img src=\"defects.png\" alt=\"defect points\">\
         <h2>Difference renders</h2>",
        escape(&name(paths, v.defective.unwrap_or(0)))
    );
    for (file, caption) in &images {
        let _ = write!(
            html,
            "<figure><img src=\"{}\" alt=\"difference\"><figcaption>{}</figcaption></figure>",
            escape(file),
            escape(caption)
        );
    }
    let _ = write!(
        html,
        "<h2>How the verdict is reached</h2><p>{}</p><p><a href=\"verdict.json\">verdict.json</a></p></body></html>",
        escape(COMBINATION)
    );
    write_atomic(&out.join("report.html"), html.as_bytes())?;
    write_json_atomic(&verdict_path, &verdict_file(inspection, paths, settings))?;
    Ok(verdict_path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::verdict::Kind;

    #[test]
    fn a_region_names_its_model_once() {
        let region = Region {
            model: 2,
            kind: Kind::Geometric,
            centroid: [0.0; 3],
            extent_mm: 1.0,
            area_mm2: 2.0,
            points: 3,
            mean_difference: 0.5,
            noise_floor_mm2: 0.0,
            significant: true,
            standing_out: 4.0,
            close_up: false,
        };
        let entry = RegionEntry {
            model: "c.ply".into(),
            region: &region,
        };
        let text = serde_json::to_string(&entry).unwrap();
        // JSON readers keep only one of two equal keys: each must be once.
        assert_eq!(text.matches("\"model\":").count(), 1, "{text}");
        let value: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(
            (value["model"].as_str(), value["model_index"].as_u64()),
            (Some("c.ply"), Some(2))
        );
    }
}
