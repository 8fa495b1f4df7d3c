//! Seed corpora: valid files of every format, made by the same writers and
//! in the same shapes as the tests' (a simulated 64x48 capture of the
//! built-in remote, its nerfstudio export, small models and clouds), plus
//! any files kept under `fuzz/corpus/<target>/` (failures found earlier,
//! kept as regression seeds once fixed).

use std::path::Path;

use anyhow::{Context, Result};

use crate::Target;
use omniscan_splat::Splats;

/// Prepares `dir` for `target` (the images a capture or photo set names)
/// and returns the seed inputs.
pub fn write(target: Target, dir: &Path) -> Result<Vec<Vec<u8>>> {
    std::fs::create_dir_all(dir)?;
    let mut seeds = match target {
        Target::PlySplats => splat_models(dir)?,
        Target::DotSplat => [(0, 3), (2, 2)]
            .map(|(degree, n)| omniscan_splat::ply::to_dot_splat(&model(degree, n)))
            .to_vec(),
        Target::Spz => {
            use omniscan_splat::spz::{SpzVersion, to_spz};
            [
                (0, 3, SpzVersion::V4),
                (1, 2, SpzVersion::V3),
                (3, 2, SpzVersion::V2),
                (2, 1, SpzVersion::V4),
            ]
            .map(|(degree, n, version)| to_spz(&model(degree, n), version))
            .to_vec()
        }
        Target::Glb => [(0, 3), (3, 2)]
            .map(|(degree, n)| omniscan_splat::glb::to_glb(&model(degree, n)))
            .to_vec(),
        Target::CompressedPly => vec![compressed_ply()],
        Target::PlyCloud => clouds_ply(dir)?,
        Target::Pcd => pcd(),
        Target::Xyz => vec![
            b"0 0 0\n1 0 0\n0 1 0.5\n".to_vec(),
            b"# a comment\n0.1 0.2 0.3\n\n-1e-3 2 3\n".to_vec(),
        ],
        Target::Capture => {
            simulate(dir)?;
            vec![std::fs::read(dir.join("capture.json"))?]
        }
        Target::TransformsJson => {
            photo_set(dir)?;
            vec![std::fs::read(dir.join("transforms.json"))?]
        }
        Target::CamerasJson => {
            photo_set(dir)?;
            vec![std::fs::read(dir.join("cameras.json"))?]
        }
        Target::Checkpoint => vec![checkpoint(dir)?],
        Target::Png => images(dir)?,
    };
    let kept = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fuzz/corpus")
        .join(target.name());
    if let Ok(entries) = std::fs::read_dir(&kept) {
        for entry in entries {
            seeds.push(std::fs::read(entry?.path())?);
        }
    }
    Ok(seeds)
}

fn model(degree: usize, n: usize) -> Splats {
    let k = (degree + 1) * (degree + 1);
    let f = |i: usize, j: usize| ((i * 7 + j * 3) % 11) as f32 / 11.0 - 0.5;
    Splats {
        means: (0..n).map(|i| [f(i, 0), f(i, 1), f(i, 2)]).collect(),
        log_scales: (0..n).map(|i| [-3.0 + f(i, 3); 3]).collect(),
        quats: (0..n).map(|i| [1.0, f(i, 4), 0.0, f(i, 5)]).collect(),
        opacity_logits: (0..n).map(|i| f(i, 6)).collect(),
        sh_degree: degree,
        sh: (0..n * k).map(|i| [f(i, 7), f(i, 8), f(i, 9)]).collect(),
        ..Default::default()
    }
}

fn splat_models(dir: &Path) -> Result<Vec<Vec<u8>>> {
    let path = dir.join("seed.ply");
    let mut seeds = Vec::new();
    for (degree, n) in [(0, 3), (1, 2), (3, 1)] {
        omniscan_splat::ply::write_splats(&path, &model(degree, n))?;
        seeds.push(std::fs::read(&path)?);
    }
    seeds.push(
        b"ply\nformat ascii 1.0\ncomment SplatRenderMode: mip\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\nproperty float opacity\nproperty float scale_0\nproperty float scale_1\nproperty float scale_2\nproperty float rot_0\nproperty float rot_1\nproperty float rot_2\nproperty float rot_3\nend_header\n0 0 0 0.1 0.2 0.3 0.5 -3 -3 -3 1 0 0 0\n0.1 0.2 0.3 0.3 0.2 0.1 -0.5 -2 -2.5 -3 0.7 0.7 0 0\n"
            .to_vec(),
    );
    Ok(seeds)
}

/// A PlayCanvas compressed PLY of three splats in one chunk, with SH of
/// degree 1 (omniscan writes none; the layout is the reader's).
fn compressed_ply() -> Vec<u8> {
    use omniscan_core::ply::{Column, Element, Format, PlyFile, Property, ScalarType};
    let element =
        |name: &str, count: usize, columns: Vec<(String, ScalarType, Vec<f64>)>| Element {
            name: name.into(),
            count,
            properties: columns
                .iter()
                .map(|(name, scalar, _)| Property {
                    name: name.clone(),
                    scalar: *scalar,
                    list_count: None,
                })
                .collect(),
            columns: columns
                .into_iter()
                .map(|(_, _, v)| Column::Scalar(v))
                .collect(),
        };
    let chunk_names = [
        "min_x",
        "min_y",
        "min_z",
        "max_x",
        "max_y",
        "max_z",
        "min_scale_x",
        "min_scale_y",
        "min_scale_z",
        "max_scale_x",
        "max_scale_y",
        "max_scale_z",
    ];
    let chunk_values = [
        -0.1, -0.1, -0.1, 0.1, 0.1, 0.1, -6.0, -6.0, -6.0, -3.0, -3.0, -3.0,
    ];
    let chunk = chunk_names
        .iter()
        .zip(chunk_values)
        .map(|(n, v)| (n.to_string(), ScalarType::F32, vec![v]))
        .collect();
    let packed = |values: [f64; 3]| ("".to_string(), ScalarType::U32, values.to_vec());
    let mut vertex = Vec::new();
    for (name, values) in [
        ("packed_position", [0.0, 2_147_483_647.0, 1_234_567_890.0]),
        (
            "packed_rotation",
            [3_221_749_247.0, 523_776.0, 2_684_354_559.0],
        ),
        ("packed_scale", [0.0, 4_294_967_295.0, 2_000_000_000.0]),
        (
            "packed_color",
            [4_286_611_711.0, 2_155_905_279.0, 16_777_215.0],
        ),
    ] {
        let (_, scalar, v) = packed(values);
        vertex.push((name.to_string(), scalar, v));
    }
    let sh = (0..9)
        .map(|i| {
            (
                format!("f_rest_{i}"),
                ScalarType::U8,
                vec![0.0, 128.0, 255.0],
            )
        })
        .collect();
    omniscan_core::ply::to_binary_le(&PlyFile {
        format: Format::BinaryLittleEndian,
        comments: vec![],
        elements: vec![
            element("chunk", 1, chunk),
            element("vertex", 3, vertex),
            element("sh", 3, sh),
        ],
    })
}

fn clouds_ply(dir: &Path) -> Result<Vec<Vec<u8>>> {
    use nalgebra_points::cloud;
    let path = dir.join("seed.ply");
    omniscan_register::cloud::write_ply(&path, &cloud())?;
    Ok(vec![
        std::fs::read(&path)?,
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 255 0 0\n1 0 0 0 255 0\n0 1 0 0 0 255\n3 0 1 2\n"
            .to_vec(),
    ])
}

/// A small coloured cloud with normals, without naming nalgebra here.
mod nalgebra_points {
    use omniscan_register::PointCloud;

    pub fn cloud() -> PointCloud {
        let mut cloud = PointCloud::default();
        for i in 0..5 {
            let t = i as f64 * 0.3;
            cloud.points.push([t.cos(), t.sin(), t * 0.1].into());
            cloud.normals.push([0.0, 0.0, 1.0].into());
            cloud
                .colors
                .push([0.2 * i as f32, 0.5, 1.0 - 0.2 * i as f32]);
        }
        cloud
    }
}

fn pcd() -> Vec<Vec<u8>> {
    let header = |kind: &str| {
        format!(
            "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA {kind}\n"
        )
    };
    let ascii = header("ascii") + "1 2 3 16711680\n4 5 6 255\n";
    let points = [([1f32, 2.0, 3.0], 0xff0000u32), ([4.0, 5.0, 6.0], 0x0000ff)];
    let mut binary = header("binary").into_bytes();
    for (p, c) in points {
        p.iter().for_each(|v| binary.extend(v.to_le_bytes()));
        binary.extend(c.to_le_bytes());
    }
    // Column-major data in one all-literal LZF run.
    let mut raw = Vec::new();
    for axis in 0..3 {
        points
            .iter()
            .for_each(|(p, _)| raw.extend(p[axis].to_le_bytes()));
    }
    points.iter().for_each(|(_, c)| raw.extend(c.to_le_bytes()));
    let mut lzf = vec![(raw.len() - 1) as u8];
    lzf.extend_from_slice(&raw);
    let mut compressed = header("binary_compressed").into_bytes();
    compressed.extend((lzf.len() as u32).to_le_bytes());
    compressed.extend((raw.len() as u32).to_le_bytes());
    compressed.extend(&lzf);
    vec![ascii.into_bytes(), binary, compressed]
}

/// A 64x48 capture of the built-in remote, 3 wrist angles at 2 latitudes.
fn simulate(dir: &Path) -> Result<()> {
    use omniscan_pipeline::simulate::{SimulateSettings, simulate};
    let mut settings = SimulateSettings {
        object: "builtin:remote".into(),
        width: 64,
        height: 48,
        supersample: 1,
        no_empty_pass: true,
        seed: 5,
        ..SimulateSettings::default()
    };
    settings.plan.wrist_angles = 3;
    settings.plan.latitudes = 2;
    simulate(&settings, dir, &omniscan_pipeline::Silent).context("simulating the seed capture")?;
    Ok(())
}

/// The capture's left arm exported for nerfstudio into `dir`, and the same
/// views as a `cameras.json` (OpenCV axes and pixels).
fn photo_set(dir: &Path) -> Result<()> {
    use omniscan_core::nerfstudio::{ExportOptions, export_nerfstudio};
    let capture_dir = dir.join("capture");
    simulate(&capture_dir)?;
    let capture = omniscan_core::Capture::load(&capture_dir)?;
    let options = ExportOptions {
        views: omniscan_core::poses::ViewSet::Arm(omniscan_core::Arm::Left),
        masks: true,
    };
    export_nerfstudio(&capture, dir, options)?;
    let transforms: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("transforms.json"))?)?;
    let frames: Vec<serde_json::Value> = transforms["frames"]
        .as_array()
        .context("the export has frames")?
        .iter()
        .map(|f| {
            let gl = &f["transform_matrix"];
            // OpenGL's camera axes to OpenCV's: y and z turn over.
            let cv: Vec<Vec<f64>> = (0..4)
                .map(|r| {
                    (0..4)
                        .map(|c| {
                            let v = gl[r][c].as_f64().unwrap_or(0.0);
                            if (c == 1 || c == 2) && r < 3 { -v } else { v }
                        })
                        .collect()
                })
                .collect();
            serde_json::json!({
                "file_path": f["file_path"],
                "mask_path": f["mask_path"],
                "fl_x": transforms["fl_x"],
                "fl_y": transforms["fl_y"],
                "cx": transforms["cx"].as_f64().unwrap_or(32.0) - 0.5,
                "cy": transforms["cy"].as_f64().unwrap_or(24.0) - 0.5,
                "w": transforms["w"],
                "h": transforms["h"],
                "camera_to_world_opencv": cv,
            })
        })
        .collect();
    let cameras = serde_json::json!({ "frames": frames });
    std::fs::write(
        dir.join("cameras.json"),
        serde_json::to_vec_pretty(&cameras)?,
    )?;
    Ok(())
}

fn checkpoint(dir: &Path) -> Result<Vec<u8>> {
    let splats = model(0, 3);
    let n = splats.len();
    // Values per splat of Adam's five groups at SH degree 0.
    let moments = [3, 3, 4, 1, 3].map(|stride| (vec![0.25; n * stride], vec![1e-4; n * stride]));
    let state = omniscan_splat::train::TrainState {
        step: 7,
        splats,
        extent: 1.5,
        moments,
        grad2d_sum: vec![0.0; n],
        grad2d_count: vec![0; n],
        order: vec![1, 0],
        rng_word_pos: 42,
        fingerprint: "fuzz".into(),
        poses: None,
    };
    let path = dir.join("seed.safetensors");
    omniscan_splat::checkpoint::save(&state, &path)?;
    Ok(std::fs::read(path)?)
}

fn images(dir: &Path) -> Result<Vec<Vec<u8>>> {
    use omniscan_core::image_io::{DepthMm, Mask, RgbImage, write_depth, write_mask, write_rgb};
    let (width, height) = (16u32, 12u32);
    let pixels = (width * height) as usize;
    let path = dir.join("seed.png");
    let mut seeds = Vec::new();
    let rgb = RgbImage {
        width,
        height,
        data: (0..pixels * 3).map(|i| (i * 37 % 256) as u8).collect(),
    };
    write_rgb(&path, &rgb)?;
    seeds.push(std::fs::read(&path)?);
    let mut mask = Mask::new(width, height);
    for (i, v) in mask.data.iter_mut().enumerate() {
        *v = if i % 3 == 0 { 255 } else { 0 };
    }
    write_mask(&path, &mask)?;
    seeds.push(std::fs::read(&path)?);
    let depth = DepthMm {
        width,
        height,
        data: (0..pixels).map(|i| (i * 131 % 4000) as u16).collect(),
    };
    write_depth(&path, &depth)?;
    seeds.push(std::fs::read(&path)?);
    Ok(seeds)
}
