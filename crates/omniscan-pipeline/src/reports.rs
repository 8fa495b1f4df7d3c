//! The `report.html` pages of [`crate::twin::twin`] and [`crate::demo::demo`]:
//! self-contained pages with the stages and their times, the merge's
//! alignment (and its error against the simulator's truth when the capture
//! has it), PSNR and SSIM per held-out view as a plot, photo | render |
//! difference strips for the best, the median and the worst view, and the
//! twin in the viewer ([`omniscan_view`]). Every picture is inside the page.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Result;
use base64::Engine;
use omniscan_core::image_io::{RgbImage, rgb_png_bytes};
use omniscan_splat::evaluation::{Evaluation, ViewFigures};
use omniscan_splat::view::View;
use omniscan_splat::views::ViewSource;
use omniscan_view::escape_html;

use crate::align::PoseError;
use crate::train::TrainReport;
use crate::twin::{Stage, StageStatus, TwinReport, TwinSettings};
use crate::views::{ArmSet, read_transform, view_source};

/// Writes `out/report.html` for `report`; returns its path.
pub fn write_twin_report(
    out: &Path,
    report: &TwinReport,
    settings: &TwinSettings,
) -> Result<PathBuf> {
    let twin = omniscan_splat::ply::read_splats(&report.twin)?;
    let mut body = format!(
        "<h1>Twin of {}</h1>",
        escape_html(&report.capture.display().to_string())
    );
    body.push_str(&stages_table(report));
    body.push_str(&alignment_section(report));
    let evaluation = &report.stages.twin.report.test;
    body.push_str(&per_view_plot(evaluation));
    let right_to_left = read_transform(&report.right_to_left)?;
    let (source, _) = view_source(
        &report.capture,
        ArmSet::Both,
        Some(right_to_left),
        settings.downscale,
        true,
    )?;
    body.push_str(&strips(evaluation, &source, &twin)?);
    write_page(
        out,
        &format!("omniscan twin: {}", name_of(&report.capture)),
        body,
        &twin,
    )
}

/// Writes `out/report.html` for the demo; returns its path.
pub fn write_demo_report(out: &Path, report: &crate::demo::DemoReport) -> Result<PathBuf> {
    let twin = omniscan_splat::ply::read_splats(&report.twin.model)?;
    let s = &report.summary;
    let m = &report.masks;
    let f = |v: Option<f64>| figure(v, 4);
    let mut body = format!(
        "<h1>omniscan demo</h1><p>A simulated bimanual scan ({} left, {} right frames at {}x{}, {:.1} s), \
         masked, merged and trained into a first twin ({} steps; <code>omniscan twin</code> trains the full one).</p>\
         <h2>Masks against the simulator's truth</h2><table><tr><th>mIoU</th><th>left</th><th>right</th></tr>\
         <tr><td>object</td><td>{}</td><td>{}</td></tr><tr><td>gripper</td><td>{}</td><td>{}</td></tr></table>",
        s.left_frames,
        s.right_frames,
        s.width,
        s.height,
        report.seconds,
        report.twin.steps,
        f(m.object_miou.left),
        f(m.object_miou.right),
        f(m.gripper_miou.left),
        f(m.gripper_miou.right)
    );
    let merge = &report.merge;
    let _ = write!(
        body,
        "<h2>Merging the arms</h2><p>{}: fitness {:.3}.</p>",
        escape_html(&merge.method),
        merge.fitness
    );
    if let (Some(before), Some(after)) = (&merge.handover_error, &merge.refined_error) {
        let _ = write!(
            body,
            "<table><tr><th>against the simulator's truth</th><th>rotation °</th><th>translation mm</th></tr>\
             <tr><td>handover estimate</td><td>{:.3}</td><td>{:.2}</td></tr>\
             <tr><td>refined (used)</td><td>{:.3}</td><td>{:.2}</td></tr></table>",
            before.deg, before.mm, after.deg, after.mm
        );
    }
    let t = &report.twin.test;
    let _ = write!(
        body,
        "<h2>The first twin</h2><p>{} splats; held-out PSNR {} dB (masked {}), SSIM {} (masked {}).</p>",
        report.twin.splats,
        figure(t.psnr, 2),
        figure(t.psnr_masked, 2),
        figure(t.ssim, 4),
        figure(t.ssim_masked, 4)
    );
    body.push_str(&per_view_plot(t));
    let right_to_left = omniscan_core::geometry::pose_from_rows(&merge.right_to_left)?;
    let (source, _) = view_source(
        &report.capture,
        ArmSet::Both,
        Some(right_to_left),
        crate::demo::DEMO_DOWNSCALE,
        false,
    )?;
    body.push_str(&strips(t, &source, &twin)?);
    write_page(out, "omniscan demo", body, &twin)
}

/// The page around `body`, the twin's viewer last.
fn write_page(
    out: &Path,
    title: &str,
    mut body: String,
    twin: &omniscan_splat::Splats,
) -> Result<PathBuf> {
    body.push_str("<h2>The twin in 3D</h2>");
    body.push_str(&omniscan_view::viewer_html(&[
        omniscan_view::ViewerModel {
            name: "twin".into(),
            splats: twin,
            markers: Vec::new(),
        },
    ])?);
    let html = format!(
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{}</title>\
         <style>{STYLE}</style></head><body>{body}</body></html>\n",
        escape_html(title)
    );
    let path = out.join("report.html");
    omniscan_core::io::write_atomic(&path, html.as_bytes())?;
    Ok(path)
}

const STYLE: &str = "body{font-family:sans-serif;margin:1.5em auto;max-width:1100px;padding:0 1em;color:#222}\
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}\
th{background:#eee}td:first-child,th:first-child{text-align:left}figure{margin:.5em 0}\
figcaption{font-size:.85em;color:#555}figure img{width:100%;image-rendering:pixelated}#omniscan-viewer{height:520px}";

fn name_of(path: &Path) -> String {
    path.file_name().map_or_else(
        || path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}

fn figure(value: Option<f64>, digits: usize) -> String {
    value.map_or_else(|| "–".into(), |v| format!("{v:.digits$}"))
}

fn status(status: StageStatus) -> &'static str {
    match status {
        StageStatus::Ran => "ran",
        StageStatus::Resumed => "resumed",
        StageStatus::Reused => "reused",
    }
}

fn stages_table(report: &TwinReport) -> String {
    let s = &report.stages;
    let mut html = String::from(
        "<h2>Stages</h2><table><tr><th>stage</th><th>status</th><th>seconds</th><th>splats</th>\
         <th>steps</th><th>held-out PSNR dB (masked)</th><th>held-out SSIM (masked)</th></tr>",
    );
    let train_row = |html: &mut String, label: &str, stage: &Stage<TrainReport>| {
        let r = &stage.report;
        let _ = write!(
            html,
            "<tr><td>{label}</td><td>{}</td><td>{:.1}</td><td>{}</td><td>{}</td><td>{} ({})</td><td>{} ({})</td></tr>",
            status(stage.status),
            r.seconds,
            r.splats,
            r.steps,
            figure(r.test.psnr, 2),
            figure(r.test.psnr_masked, 2),
            figure(r.test.ssim, 4),
            figure(r.test.ssim_masked, 4)
        );
    };
    train_row(&mut html, "left arm", &s.left);
    train_row(&mut html, "right arm", &s.right);
    let _ = write!(
        html,
        "<tr><td>align right to left</td><td>{}</td><td>{:.1}</td><td colspan=\"4\">{}</td></tr>",
        status(s.align.status),
        s.align.report.seconds,
        escape_html(&s.align.report.method)
    );
    train_row(&mut html, "twin (both arms)", &s.twin);
    let total = s.left.report.seconds
        + s.right.report.seconds
        + s.align.report.seconds
        + s.twin.report.seconds;
    let _ = write!(
        html,
        "</table><p>Stage time in all: {total:.1} s (a reused stage shows the time it took when it ran).</p>"
    );
    html
}

fn alignment_section(report: &TwinReport) -> String {
    let a = &report.stages.align.report;
    let mut html = format!(
        "<h2>Alignment of the arms</h2><p>{}: fitness {:.3}, inlier RMSE {:.5} {}, {} correspondences.</p>",
        escape_html(&a.method),
        a.fitness,
        a.inlier_rmse,
        escape_html(&a.units),
        a.correspondences
    );
    if let Some(error) = &report.alignment_error {
        html.push_str("<table><tr><th>against the simulator's truth</th><th>rotation °</th><th>translation mm</th></tr>");
        let row = |html: &mut String, label: &str, e: &PoseError| {
            let _ = write!(
                html,
                "<tr><td>{label}</td><td>{:.3}</td><td>{:.2}</td></tr>",
                e.deg, e.mm
            );
        };
        row(&mut html, "handover estimate", &error.handover_estimate);
        if let Some(points) = &error.points_only {
            row(&mut html, "point registration", points);
        }
        row(&mut html, "refined (used)", &error.refined);
        html.push_str("</table>");
    } else {
        html.push_str("<p>The capture has no ground truth to measure the alignment against.</p>");
    }
    html
}

/// PSNR (left axis) and SSIM (right axis) per held-out view, as inline SVG.
fn per_view_plot(evaluation: &Evaluation) -> String {
    let views = &evaluation.per_view;
    let series: [(&str, &str, Vec<Option<f64>>); 2] = [
        (
            "PSNR masked (dB)",
            "#1f5fa8",
            views.iter().map(|v| v.psnr_masked.or(v.psnr)).collect(),
        ),
        (
            "SSIM masked",
            "#c0392b",
            views.iter().map(|v| v.ssim_masked.or(v.ssim)).collect(),
        ),
    ];
    if views.len() < 2 {
        return "<h2>Held-out views</h2><p>Fewer than two held-out views: nothing to plot.</p>"
            .into();
    }
    let (w, h, pad) = (900.0, 260.0, 45.0);
    let mut svg = format!(
        "<h2>Held-out views</h2><svg viewBox=\"0 0 {w} {h}\" width=\"100%\" role=\"img\" \
         aria-label=\"PSNR and SSIM per held-out view\" style=\"max-width:{w}px\">\
         <rect x=\"{pad}\" y=\"10\" width=\"{}\" height=\"{}\" fill=\"#fafafa\" stroke=\"#ccc\"/>",
        w - 2.0 * pad,
        h - 40.0
    );
    for (k, (label, colour, values)) in series.iter().enumerate() {
        let finite: Vec<f64> = values.iter().flatten().copied().collect();
        if finite.is_empty() {
            continue;
        }
        let lo = finite.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = finite
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max)
            .max(lo + 1e-9);
        let x = |i: usize| pad + (w - 2.0 * pad) * i as f64 / (views.len() - 1) as f64;
        let y = |v: f64| 10.0 + (h - 40.0) * (1.0 - (v - lo) / (hi - lo));
        let points: Vec<String> = values
            .iter()
            .enumerate()
            .filter_map(|(i, v)| v.map(|v| format!("{:.1},{:.1}", x(i), y(v))))
            .collect();
        let axis_x = if k == 0 { 4.0 } else { w - pad + 4.0 };
        let _ = write!(
            svg,
            "<polyline fill=\"none\" stroke=\"{colour}\" stroke-width=\"1.5\" points=\"{}\"/>\
             <text x=\"{axis_x}\" y=\"18\" font-size=\"11\" fill=\"{colour}\">{hi:.3}</text>\
             <text x=\"{axis_x}\" y=\"{}\" font-size=\"11\" fill=\"{colour}\">{lo:.3}</text>\
             <text x=\"{}\" y=\"{}\" font-size=\"12\" fill=\"{colour}\">{label}</text>",
            points.join(" "),
            h - 30.0,
            pad + 10.0 + 260.0 * k as f64,
            h - 8.0
        );
    }
    let _ = write!(
        svg,
        "</svg><p>Each point is a held-out view ({} of them, in capture order); masked figures cover the object without the gripper.</p>",
        views.len()
    );
    svg
}

/// Photo | render | difference for the best, median and worst held-out
/// views by masked PSNR.
fn strips(
    evaluation: &Evaluation,
    source: &ViewSource,
    twin: &omniscan_splat::Splats,
) -> Result<String> {
    let mut ranked: Vec<&ViewFigures> = evaluation
        .per_view
        .iter()
        .filter(|v| v.psnr_masked.or(v.psnr).is_some())
        .collect();
    if ranked.is_empty() {
        return Ok(String::new());
    }
    ranked.sort_by(|a, b| {
        let key = |v: &ViewFigures| v.psnr_masked.or(v.psnr).unwrap_or(0.0);
        key(b).total_cmp(&key(a)).then(a.view.cmp(&b.view))
    });
    let mut chosen = vec![("best", ranked[0])];
    if ranked.len() > 2 {
        chosen.push(("median", ranked[ranked.len() / 2]));
    }
    if ranked.len() > 1 {
        chosen.push(("worst", ranked[ranked.len() - 1]));
    }
    let gaussians = twin.gaussians::<f32>();
    let render_settings = twin.render_settings([0.0f32; 3]);
    let mut html = String::from("<h2>Photo | render | difference</h2>");
    for (label, figures) in chosen {
        let view = source.load(figures.view)?;
        let (_, render) =
            omniscan_splat::raster::render(&gaussians, &view.camera, &render_settings);
        let png = rgb_png_bytes(&strip(&view, &render.rgb));
        let _ = write!(
            html,
            "<figure><img alt=\"view {}\" src=\"data:image/png;base64,{}\"><figcaption>{label}: view {}, PSNR {} dB (masked {}), SSIM {}; \
             the difference is |photo − render| × 4, the photo cut to the object.</figcaption></figure>",
            figures.view,
            base64::engine::general_purpose::STANDARD.encode(png),
            figures.view,
            figure(figures.psnr, 2),
            figure(figures.psnr_masked, 2),
            figure(figures.ssim, 4)
        );
    }
    Ok(html)
}

fn strip(view: &View, render: &[[f32; 3]]) -> RgbImage {
    let byte = |x: f32| (x.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    let (w, h) = (view.camera.width as usize, view.camera.height as usize);
    let mut data = Vec::with_capacity(3 * w * h * 3);
    for y in 0..h {
        let row = y * w..(y + 1) * w;
        for p in row.clone() {
            data.extend(view.image[p].map(|c| byte(c * view.object[p])));
        }
        for p in row.clone() {
            data.extend(render[p].map(byte));
        }
        for p in row {
            let photo = view.image[p].map(|c| c * view.object[p]);
            data.extend([0, 1, 2].map(|c| byte(4.0 * (photo[c] - render[p][c]).abs())));
        }
    }
    RgbImage {
        width: 3 * w as u32,
        height: h as u32,
        data,
    }
}
