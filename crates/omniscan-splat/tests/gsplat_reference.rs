//! Conformance with gsplat 1.5.3's float64 reference vectors
//! (`shared/data/reference/gsplat`): projection, SH colour and rendered
//! images, run in f64. Needs `../shared` (or `OMNISCAN_SHARED`).

use std::path::PathBuf;

use serde_json::Value;

use omniscan_splat::raster::{Camera, Colors, Gaussians, Mode, Settings, render};
use omniscan_splat::sh;

fn reference(name: &str) -> Value {
    let dir = std::env::var_os("OMNISCAN_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"));
    let path = dir.join("data/reference/gsplat").join(name);
    serde_json::from_str(
        &std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())),
    )
    .unwrap()
}

fn v3(v: &Value) -> Vec<[f64; 3]> {
    serde_json::from_value(v.clone()).unwrap()
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol * (1.0 + b.abs())
}

const CASES: [&str; 7] = [
    "tiny.json",
    "small.json",
    "medium.json",
    "sh3.json",
    "clipping.json",
    "antialiased.json",
    "opaque_stack.json",
];

#[test]
#[ignore = "needs ../shared"]
fn forward_matches_gsplat_reference_vectors() {
    for case in CASES {
        let d = reference(case);
        let fwd = &d["forward"];
        let (g, camera, settings) = case_inputs(&d);
        let (p, r) = render(&g, &camera, &settings);

        let radii: Vec<[i32; 2]> = serde_json::from_value(fwd["radii"].clone()).unwrap();
        let means2d: Vec<[f64; 2]> = serde_json::from_value(fwd["means2d"].clone()).unwrap();
        let conics = v3(&fwd["conics"]);
        let depths: Vec<f64> = serde_json::from_value(fwd["depths"].clone()).unwrap();
        let opacities: Vec<f64> = serde_json::from_value(fwd["opacities_view"].clone()).unwrap();
        let visible = radii.iter().filter(|r| r[0] > 0 && r[1] > 0).count();
        assert_eq!(
            visible as u64,
            d["diagnostics"]["n_visible"].as_u64().unwrap(),
            "{case}: visible count"
        );
        for i in 0..radii.len() {
            assert_eq!(p.radii[i], radii[i], "{case}: radii of {i}");
            if radii[i][0] == 0 {
                continue;
            }
            for (got, want) in p.means2d[i].iter().zip(&means2d[i]) {
                assert!(close(*got, *want, 1e-12), "{case}: means2d {i}");
            }
            for a in 0..3 {
                assert!(
                    close(p.conics[i][a], conics[i][a], 1e-10),
                    "{case}: conic {i}: {:?} vs {:?}",
                    p.conics[i],
                    conics[i]
                );
            }
            assert!(close(p.depths[i], depths[i], 1e-12));
            assert!(
                close(p.opacities[i], opacities[i], 1e-10),
                "{case}: opacity {i}"
            );
        }
        if let Some(cv) = fwd.get("colors_view") {
            let cv = v3(cv);
            for i in (0..cv.len()).filter(|&i| radii[i][0] > 0) {
                for (got, want) in p.colors[i].iter().zip(&cv[i]) {
                    assert!(close(*got, *want, 1e-10), "{case}: colour {i}");
                }
            }
        }
        let rgb: Vec<Vec<[f64; 3]>> = serde_json::from_value(fwd["render_rgb"].clone()).unwrap();
        let alpha: Vec<Vec<f64>> = serde_json::from_value(fwd["render_alpha"].clone()).unwrap();
        let contrib: Vec<Vec<u32>> =
            serde_json::from_value(d["diagnostics"]["n_contrib"].clone()).unwrap();
        let w = camera.width as usize;
        for (y, row) in rgb.iter().enumerate() {
            for (x, want) in row.iter().enumerate() {
                let i = y * w + x;
                for ch in 0..3 {
                    assert!(
                        (r.rgb[i][ch] - want[ch]).abs() < 1e-10,
                        "{case}: rgb at ({x},{y}): {:?} vs {:?}",
                        r.rgb[i],
                        want
                    );
                }
                assert!(
                    (r.alpha[i] - alpha[y][x]).abs() < 1e-10,
                    "{case}: alpha at ({x},{y})"
                );
                assert_eq!(
                    r.contributors[i], contrib[y][x],
                    "{case}: contributors at ({x},{y})"
                );
            }
        }
    }
}

#[test]
#[ignore = "needs ../shared"]
fn spherical_harmonics_match_gsplat() {
    let d = reference("sh_eval.json");
    let dirs = v3(&d["inputs"]["dirs"]);
    let coeffs: Vec<Vec<[f64; 3]>> = serde_json::from_value(d["inputs"]["coeffs"].clone()).unwrap();
    let bases: Vec<Vec<f64>> = serde_json::from_value(d["bases_unit_dirs"].clone()).unwrap();
    for (i, dir) in dirs.iter().enumerate() {
        let n = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
        let unit = dir.map(|v| v / n);
        let b = sh::basis(3, unit);
        for k in 0..16 {
            assert!(
                (b[k] - bases[i][k]).abs() < 1e-12,
                "basis {k} of direction {i}"
            );
        }
        for degree in 0..=3 {
            let out = v3(&d["degrees"][degree.to_string()]["out"]);
            let got = sh::evaluate(degree, unit, &coeffs[i][..sh::coefficients(degree)]);
            for ch in 0..3 {
                assert!(
                    (got[ch] - out[i][ch]).abs() < 1e-12,
                    "degree {degree}, direction {i}"
                );
            }
        }
    }
}

#[test]
#[ignore = "needs ../shared"]
fn every_real_splat_model_loads_and_renders() {
    let dir = std::env::var_os("OMNISCAN_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"));
    let mut n = 0;
    for entry in std::fs::read_dir(dir.join("data/real-splats")).unwrap() {
        let path = entry.unwrap().path();
        let model = omniscan_splat::ply::read_splats(&path).unwrap();
        assert_eq!(model.sh_degree, 0);
        let cameras = omniscan_splat::orbit::orbit_cameras(&model, 2, 96, 72);
        for camera in &cameras {
            let (_, r) = render(&model.gaussians::<f32>(), camera, &Settings::default());
            let covered = r.alpha.iter().filter(|&&a| a > 0.5).count();
            assert!(
                covered > 200,
                "{}: only {covered} covered pixels",
                path.display()
            );
            assert!(r.rgb.iter().flatten().all(|v| v.is_finite()));
        }
        n += 1;
    }
    assert_eq!(n, 14);
}

fn case_inputs(d: &Value) -> (Gaussians<f64>, Camera<f64>, Settings<f64>) {
    let (inp, cfg) = (&d["inputs"], &d["config"]);
    let colors = match cfg["sh_degree"].as_u64() {
        Some(deg) => {
            let coeffs: Vec<Vec<[f64; 3]>> =
                serde_json::from_value(inp["sh_coeffs"].clone()).unwrap();
            Colors::Sh {
                degree: deg as usize,
                coeffs: coeffs.into_iter().flatten().collect(),
            }
        }
        None => Colors::Rgb(v3(&inp["colors"])),
    };
    let g = Gaussians {
        means: v3(&inp["means"]),
        scales: v3(&inp["scales"]),
        quats: serde_json::from_value(inp["quats_wxyz"].clone()).unwrap(),
        opacities: serde_json::from_value(inp["opacities"].clone()).unwrap(),
        colors,
    };
    let k: [[f64; 3]; 3] = serde_json::from_value(inp["K"].clone()).unwrap();
    let camera = Camera {
        viewmat: serde_json::from_value(inp["viewmat"].clone()).unwrap(),
        fx: k[0][0],
        fy: k[1][1],
        cx: k[0][2],
        cy: k[1][2],
        width: cfg["width"].as_u64().unwrap() as u32,
        height: cfg["height"].as_u64().unwrap() as u32,
        near: cfg["near_plane"].as_f64().unwrap(),
        far: cfg["far_plane"].as_f64().unwrap(),
    };
    let mode = if cfg["rasterize_mode"] == "antialiased" {
        Mode::Antialiased
    } else {
        Mode::Classic
    };
    let bg: Vec<f64> = serde_json::from_value(inp["background"].clone()).unwrap();
    (
        g,
        camera,
        Settings {
            eps2d: cfg["eps2d"].as_f64().unwrap(),
            mode,
            background: [bg[0], bg[1], bg[2]],
            ..Settings::default()
        },
    )
}

#[test]
#[ignore = "needs ../shared"]
fn gradients_match_gsplat_autograd() {
    for case in CASES {
        let d = reference(case);
        let (g, camera, settings) = case_inputs(&d);
        let (p, _) = render(&g, &camera, &settings);
        let w_rgb: Vec<Vec<[f64; 3]>> = serde_json::from_value(d["loss"]["w_rgb"].clone()).unwrap();
        let w_alpha: Vec<Vec<f64>> = serde_json::from_value(d["loss"]["w_alpha"].clone()).unwrap();
        let d_rgb: Vec<[f64; 3]> = w_rgb.into_iter().flatten().collect();
        let d_alpha: Vec<f64> = w_alpha.into_iter().flatten().collect();
        let grads =
            omniscan_splat::backward::backward(&g, &camera, &settings, &p, &d_rgb, &d_alpha);
        let gr = &d["grads"];
        let check = |name: &str, got: Vec<f64>, want: Vec<f64>| {
            assert_eq!(got.len(), want.len(), "{case}: {name} length");
            let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-12);
            for (k, (a, b)) in got.iter().zip(&want).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-7 * scale + 1e-9 * b.abs(),
                    "{case}: {name}[{k}] = {a} vs {b} (scale {scale})"
                );
            }
        };
        let flat = |v: &Value| -> Vec<f64> {
            match v {
                Value::Array(a) => a
                    .iter()
                    .flat_map(|x| match x {
                        Value::Array(_) => flat_inner(x),
                        other => vec![other.as_f64().unwrap()],
                    })
                    .collect(),
                other => vec![other.as_f64().unwrap()],
            }
        };
        check(
            "means2d",
            grads.means2d.iter().flatten().copied().collect(),
            flat(&gr["means2d"]),
        );
        check(
            "conics",
            grads.conics.iter().flatten().copied().collect(),
            flat(&gr["conics"]),
        );
        check(
            "opacities_view",
            grads.opacities_view.clone(),
            flat(&gr["opacities_view"]),
        );
        check("opacities", grads.opacities.clone(), flat(&gr["opacities"]));
        check(
            "opacity_logits",
            grads.opacity_logits(&g),
            flat(&gr["opacity_logits"]),
        );
        check(
            "scales",
            grads.scales.iter().flatten().copied().collect(),
            flat(&gr["scales"]),
        );
        check(
            "log_scales",
            grads.log_scales(&g).iter().flatten().copied().collect(),
            flat(&gr["log_scales"]),
        );
        check(
            "quats",
            grads.quats.iter().flatten().copied().collect(),
            flat(&gr["quats"]),
        );
        let color_key = if gr.get("sh_coeffs").is_some() {
            "sh_coeffs"
        } else {
            "colors"
        };
        check(
            color_key,
            grads.colors.iter().flatten().copied().collect(),
            flat(&gr[color_key]),
        );
        check(
            "means",
            grads.means.iter().flatten().copied().collect(),
            flat(&gr["means"]),
        );
    }
}

fn flat_inner(v: &Value) -> Vec<f64> {
    match v {
        Value::Array(a) => a.iter().flat_map(flat_inner).collect(),
        other => vec![other.as_f64().unwrap()],
    }
}

#[test]
#[ignore = "needs ../shared"]
fn dtu_photo_set_loads_with_masks_and_a_consistent_visual_hull() {
    let dir = std::env::var_os("OMNISCAN_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"));
    let views = omniscan_splat::views::views_from_cameras_json(
        &dir.join("data/dtu_scan37/cameras.json"),
        8,
    )
    .unwrap();
    assert_eq!(views.len(), 49);
    assert!(views.iter().all(|v| v.object.iter().any(|&m| m > 0.5)));
    // The cameras and masks agree on a common object: the visual hull is not empty.
    let init = omniscan_splat::train::initial_splats(&views, 500, 0, 0).unwrap();
    assert!(init.len() >= 100, "{}", init.len());
}
