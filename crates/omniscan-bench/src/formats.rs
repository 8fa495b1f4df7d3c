//! `omniscan bench formats`: what each model format keeps. Every model is
//! written in each format and read back; its renders from an orbit are
//! compared with the original's (PSNR over all pixels, on black), and the
//! file's size with the 3DGS PLY's. With `--splat-transform`, the same for
//! files written by PlayCanvas' tool (an independent implementation: SPZ
//! through Niantic's reference library, compressed PLY, glb) and read by
//! omniscan.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde_json::json;

use omniscan_splat::Splats;
use omniscan_splat::orbit::orbit_cameras;
use omniscan_splat::ply::{read_splats, write_splats};
use omniscan_splat::spz::{SpzVersion, to_spz};

#[derive(clap::Args)]
pub struct BenchArgs {
    /// The models to convert (any format omniscan reads).
    #[arg(required = true)]
    models: Vec<PathBuf>,
    /// Orbit views each model is rendered from.
    #[arg(long, default_value_t = 8)]
    views: usize,
    /// Render width, pixels.
    #[arg(long, default_value_t = 320)]
    width: u32,
    /// Render height, pixels.
    #[arg(long, default_value_t = 240)]
    height: u32,
    /// PlayCanvas' splat-transform command (web/node_modules/.bin/splat-transform
    /// after `npm ci` in web/), to compare with the files it writes.
    #[arg(long)]
    splat_transform: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

/// One format's figures on one model.
struct Row {
    model: String,
    writer: &'static str,
    format: &'static str,
    bytes: u64,
    size_ratio: f64,
    psnr_mean_db: f64,
    psnr_min_db: f64,
    write_s: f64,
    read_s: f64,
}

fn renders(model: &Splats, args: &BenchArgs) -> Vec<Vec<[f32; 3]>> {
    let g = model.gaussians::<f32>();
    let settings = model.render_settings([0.0f32; 3]);
    orbit_cameras(model, args.views, args.width, args.height)
        .iter()
        .map(|c| omniscan_splat::raster::render(&g, c, &settings).1.rgb)
        .collect()
}

/// PSNR (dB) of `b` against `a`, over every pixel and channel; infinite
/// when they are equal.
fn psnr(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let squared: f64 = a
        .iter()
        .zip(b)
        .flat_map(|(x, y)| {
            (0..3).map(move |c| {
                (f64::from(x[c].clamp(0.0, 1.0)) - f64::from(y[c].clamp(0.0, 1.0))).powi(2)
            })
        })
        .sum();
    let mse = squared / (3 * a.len()) as f64;
    if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

pub fn bench(args: BenchArgs) -> Result<()> {
    let tmp = tempfile::tempdir()?;
    let mut rows = Vec::new();
    for path in &args.models {
        let model = read_splats(path)?;
        let name = path.file_name().map_or_else(
            || path.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        let ply = tmp.path().join("original.ply");
        write_splats(&ply, &model)?;
        let ply_bytes = std::fs::metadata(&ply)?.len();
        // Cameras and renders of the original, the reference for every format.
        let reference = renders(&model, &args);
        let mut measure =
            |writer: &'static str, format: &'static str, file: &Path, write_s: f64| -> Result<()> {
                let start = Instant::now();
                let back = read_splats(file).with_context(|| format!("{writer} {format}"))?;
                let read_s = start.elapsed().as_secs_f64();
                // The original's cameras, so both are seen from the same place.
                let g = back.gaussians::<f32>();
                let settings = back.render_settings([0.0f32; 3]);
                let scores: Vec<f64> = orbit_cameras(&model, args.views, args.width, args.height)
                    .iter()
                    .zip(&reference)
                    .map(|(c, r)| psnr(r, &omniscan_splat::raster::render(&g, c, &settings).1.rgb))
                    .collect();
                let bytes = std::fs::metadata(file)?.len();
                rows.push(Row {
                    model: name.clone(),
                    writer,
                    format,
                    bytes,
                    size_ratio: bytes as f64 / ply_bytes as f64,
                    psnr_mean_db: scores.iter().sum::<f64>() / scores.len() as f64,
                    psnr_min_db: scores.iter().copied().fold(f64::INFINITY, f64::min),
                    write_s,
                    read_s,
                });
                Ok(())
            };
        for (format, file) in [
            ("ply", "m.ply"),
            ("spz v4", "m.spz"),
            ("spz v3", "m3.spz"),
            ("spz v2", "m2.spz"),
            ("glb", "m.glb"),
            (".splat", "m.splat"),
        ] {
            let file = tmp.path().join(file);
            let start = Instant::now();
            match format {
                "spz v3" => {
                    omniscan_core::io::write_atomic(&file, &to_spz(&model, SpzVersion::V3))?
                }
                "spz v2" => {
                    omniscan_core::io::write_atomic(&file, &to_spz(&model, SpzVersion::V2))?
                }
                _ => write_splats(&file, &model)?,
            }
            measure("omniscan", format, &file, start.elapsed().as_secs_f64())?;
        }
        if let Some(tool) = &args.splat_transform {
            for (format, file, flags) in [
                ("spz v4", "st.spz", &[][..]),
                ("spz v3", "st3.spz", &["--spz-version", "3"][..]),
                ("compressed ply", "st.compressed.ply", &[][..]),
                ("glb", "st.glb", &[][..]),
            ] {
                let file = tmp.path().join(file);
                let start = Instant::now();
                let out = Command::new(tool)
                    .arg("-w")
                    .arg(&ply)
                    .args(flags)
                    .arg(&file)
                    .output()
                    .with_context(|| format!("running {}", tool.display()))?;
                if !out.status.success() {
                    bail!(
                        "splat-transform {format}: {}",
                        String::from_utf8_lossy(&out.stderr)
                    );
                }
                measure(
                    "splat-transform",
                    format,
                    &file,
                    start.elapsed().as_secs_f64(),
                )?;
            }
        }
    }
    if args.json {
        let list: Vec<_> = rows.iter().map(|r| json!({
            "model": r.model, "writer": r.writer, "format": r.format, "bytes": r.bytes,
            "size_ratio": r.size_ratio, "psnr_mean_db": r.psnr_mean_db, "psnr_min_db": r.psnr_min_db,
            "write_s": r.write_s, "read_s": r.read_s,
        })).collect();
        println!(
            "{}",
            serde_json::to_string_pretty(
                &json!({"views": args.views, "width": args.width, "height": args.height, "rows": list})
            )?
        );
        return Ok(());
    }
    println!(
        "{} orbit views of {}x{} per model; PSNR of the read-back model's renders against the original's",
        args.views, args.width, args.height
    );
    println!(
        "{:<22} {:<16} {:<15} {:>10} {:>7} {:>10} {:>9} {:>8} {:>8}",
        "model",
        "written by",
        "format",
        "bytes",
        "size",
        "PSNR mean",
        "PSNR min",
        "write s",
        "read s"
    );
    for r in &rows {
        println!(
            "{:<22} {:<16} {:<15} {:>10} {:>6.3}x {:>10.2} {:>9.2} {:>8.3} {:>8.3}",
            r.model,
            r.writer,
            r.format,
            r.bytes,
            r.size_ratio,
            r.psnr_mean_db,
            r.psnr_min_db,
            r.write_s,
            r.read_s
        );
    }
    Ok(())
}
