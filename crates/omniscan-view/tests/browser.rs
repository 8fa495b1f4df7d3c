//! The viewer in a real browser: Debian's Chromium, headless, driven by
//! `web/tests/screenshot.mjs` through playwright-core, rendering with
//! SwiftShader's WebGL2. `.ci/run` installs both and runs these with the
//! other ignored tests.
//!
//! What is checked: no console or page errors, no request leaving the page,
//! a canvas that is not blank, the model's silhouette where the CPU
//! renderer puts it from the same camera (IoU ≥ 0.9; a model turned or
//! mirrored by an axis mistake scores far lower), and markers drawn.

use std::path::Path;

use omniscan_splat::Splats;
use omniscan_splat::orbit::orbit_cameras;
use omniscan_view::{Marker, ViewerModel};

/// A model with no symmetry an axis mistake could hide behind: an L of
/// splats (long along x, short up z) with a ball off one end along y, in
/// three colours.
pub fn asymmetric_model() -> Splats {
    let mut s = Splats::default();
    let mut add = |p: [f32; 3], colour: [f32; 3]| {
        s.means.push(p);
        s.log_scales.push([(0.004f32).ln(); 3]);
        s.quats.push([1.0, 0.0, 0.0, 0.0]);
        s.opacity_logits.push(4.0);
        s.sh.push(colour.map(|c| (c - 0.5) / omniscan_splat::sh::C0 as f32));
    };
    let step = 0.005;
    for i in 0..40 {
        for j in 0..6 {
            add([i as f32 * step, j as f32 * step, 0.0], [0.9, 0.8, 0.2]);
        }
    }
    for k in 0..20 {
        for j in 0..6 {
            add([0.0, j as f32 * step, k as f32 * step], [0.2, 0.7, 0.9]);
        }
    }
    for i in 0..12 {
        for j in 0..12 {
            let (a, b) = (
                i as f32 / 11.0 * std::f32::consts::PI,
                j as f32 / 12.0 * std::f32::consts::TAU,
            );
            let r = 0.025;
            add(
                [
                    0.19 + r * a.sin() * b.cos(),
                    0.08 + r * a.sin() * b.sin(),
                    r * a.cos(),
                ],
                [0.9, 0.2, 0.3],
            );
        }
    }
    s
}

/// Screenshots `page` with `options` into `out`, asserting a clean load.
fn screenshot(page: &Path, out: &Path, options: &[&str]) -> image::RgbImage {
    let shot = omniscan_view::browser::screenshot(page, out, options).unwrap();
    shot.clean().unwrap();
    assert!(shot.frames_drawn > 0);
    image::open(out).unwrap().to_rgb8()
}

const MAGENTA: [f32; 3] = [1.0, 0.0, 1.0];

/// Pixels further than a third of the way from magenta to anything: the
/// same rule for both images, whatever the model's colours.
fn silhouette(pixels: impl Iterator<Item = [f32; 3]>) -> Vec<bool> {
    pixels
        .map(|p| {
            let d: f32 = p.iter().zip(MAGENTA).map(|(a, b)| (a - b).powi(2)).sum();
            d.sqrt() > 0.35
        })
        .collect()
}

fn iou(a: &[bool], b: &[bool]) -> f64 {
    let both = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
    let either = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
    both as f64 / either.max(1) as f64
}

#[test]
#[ignore = "needs Chromium and web/node_modules (.ci/run installs them)"]
fn the_viewer_draws_the_model_where_the_cpu_renderer_does() {
    let tmp = tempfile::tempdir().unwrap();
    let model = asymmetric_model();
    let page = tmp.path().join("view.html");
    omniscan_view::write_view(
        &page,
        "test",
        &[ViewerModel {
            name: "L".into(),
            splats: &model,
            markers: vec![],
        }],
    )
    .unwrap();
    let shot = screenshot(
        &page,
        &tmp.path().join("shot.png"),
        &["--background", "1,0,1"],
    );
    let (w, h) = shot.dimensions();
    let variance = {
        let values: Vec<f32> = shot
            .pixels()
            .map(|p| p.0.iter().map(|&c| c as f32).sum())
            .collect();
        let mean = values.iter().sum::<f32>() / values.len() as f32;
        values.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / values.len() as f32
    };
    assert!(variance > 100.0, "a blank canvas (variance {variance})");

    let camera = orbit_cameras(&model, 1, w, h)[0];
    let g = model.gaussians::<f32>();
    let settings = model.render_settings(MAGENTA);
    let (_, cpu) = omniscan_splat::raster::render(&g, &camera, &settings);
    let browser = silhouette(shot.pixels().map(|p| p.0.map(|c| c as f32 / 255.0)));
    let reference = silhouette(cpu.rgb.iter().copied());
    let score = iou(&browser, &reference);
    let covered = reference.iter().filter(|x| **x).count() as f64 / reference.len() as f64;
    assert!(
        covered > 0.05,
        "the CPU render barely shows the model ({covered})"
    );
    eprintln!("silhouette IoU {score:.3}, model covers {covered:.3} of the view");
    assert!(
        score >= 0.9,
        "silhouette IoU {score:.3} between Spark and the CPU renderer"
    );

    // The same model turned half a turn about z scores far lower: the
    // comparison can tell an axis mistake.
    let mut turned = model.clone();
    for m in &mut turned.means {
        *m = [-m[0], -m[1], m[2]];
    }
    let (_, turned_render) =
        omniscan_splat::raster::render(&turned.gaussians::<f32>(), &camera, &settings);
    let wrong = iou(&browser, &silhouette(turned_render.rgb.iter().copied()));
    eprintln!("turned half a turn: IoU {wrong:.3}");
    assert!(wrong < 0.7, "a turned model still scores {wrong:.3}");
}

#[test]
#[ignore = "needs Chromium and web/node_modules (.ci/run installs them)"]
fn markers_are_drawn_and_models_toggle() {
    let tmp = tempfile::tempdir().unwrap();
    let model = asymmetric_model();
    let page = tmp.path().join("view.html");
    let marker = Marker {
        label: "defect 1".into(),
        position: [0.19, 0.08, 0.0],
        radius: 0.03,
        colour: [0, 255, 0],
    };
    let other = model.clone();
    omniscan_view::write_view(
        &page,
        "markers",
        &[
            ViewerModel {
                name: "a".into(),
                splats: &model,
                markers: vec![marker],
            },
            ViewerModel {
                name: "b".into(),
                splats: &other,
                markers: vec![],
            },
        ],
    )
    .unwrap();
    let options = |markers: &'static str| vec!["--show", "0", "--markers", markers];
    let on = screenshot(&page, &tmp.path().join("on.png"), &options("on"));
    let off = screenshot(&page, &tmp.path().join("off.png"), &options("off"));
    let green = |img: &image::RgbImage| {
        img.pixels()
            .filter(|p| p.0[1] > 200 && p.0[0] < 80 && p.0[2] < 80)
            .count()
    };
    assert!(
        green(&on) > 50,
        "no marker drawn ({} green pixels)",
        green(&on)
    );
    assert_eq!(green(&off), 0);
    // Side by side, there is a model in the left third and in the right.
    let both = screenshot(
        &page,
        &tmp.path().join("both.png"),
        &["--show", "0,1", "--markers", "off", "--background", "1,0,1"],
    );
    let (w, _) = both.dimensions();
    let mask = silhouette(both.pixels().map(|p| p.0.map(|c| c as f32 / 255.0)));
    let in_columns = |from: u32, to: u32| {
        mask.iter()
            .enumerate()
            .filter(|(i, m)| **m && (from..to).contains(&(*i as u32 % w)))
            .count()
    };
    assert!(in_columns(0, w / 3) > 100, "no model on the left");
    assert!(in_columns(2 * w / 3, w) > 100, "no model on the right");
}
