//! The standard 3DGS PLY (INRIA / gsplat layout): `x y z` [`nx ny nz`]
//! `f_dc_0..2` `f_rest_*` `opacity` `scale_0..2` `rot_0..3`, all float,
//! properties found by name in any order, ASCII or binary; `f_rest` is
//! channel-major (index = channel·(K−1) + k−1) and its count gives the SH
//! degree. A `comment SplatRenderMode: mip` header line marks antialiased
//! models, and `comment SplatAppearance: fixed-rig` models whose SH are a
//! function of the splat's normal in the camera's frame
//! ([`crate::raster::Appearance::FixedRig`]; other readers take them for
//! ordinary models, right in their base colour). Also the headerless
//! `.splat` format of web viewers.

use std::path::Path;

/// The header comment naming a model's [`crate::raster::Appearance`],
/// written for the fixed-rig one only (other models keep 3DGS's header).
const APPEARANCE_COMMENT: &str = "SplatAppearance:";

use crate::sh::{C0, coefficients};
use crate::{SplatError, Splats};
use omniscan_core::ply::{Column, Element, Format, PlyFile, Property, ScalarType};

/// Reads a 3DGS PLY file.
pub fn read_splats(path: &Path) -> Result<Splats, SplatError> {
    let ply = omniscan_core::ply::read(path)?;
    splats_from_ply(&ply).map_err(|m| SplatError::file(path, m))
}

/// Interprets a parsed PLY as a splat model.
pub fn splats_from_ply(ply: &PlyFile) -> Result<Splats, String> {
    let v = ply.element("vertex").ok_or("PLY has no `vertex` element")?;
    let col = |name: &str| {
        v.scalar(name)
            .ok_or_else(|| format!("not a 3DGS PLY: no `{name}` property"))
    };
    let n = v.count;
    if n == 0 {
        return Err("the model has no splats (`element vertex 0`)".into());
    }
    let rest: Vec<&[f64]> = (0..)
        .map_while(|i| v.scalar(&format!("f_rest_{i}")))
        .collect();
    let degree = match rest.len() {
        0 => 0,
        9 => 1,
        24 => 2,
        45 => 3,
        other => {
            return Err(format!(
                "{other} f_rest properties fit no SH degree (expected 0, 9, 24 or 45)"
            ));
        }
    };
    let k = coefficients(degree);
    let (x, y, z) = (col("x")?, col("y")?, col("z")?);
    let dc = [col("f_dc_0")?, col("f_dc_1")?, col("f_dc_2")?];
    let opacity = col("opacity")?;
    let scale = [col("scale_0")?, col("scale_1")?, col("scale_2")?];
    let rot = [col("rot_0")?, col("rot_1")?, col("rot_2")?, col("rot_3")?];
    let mut s = Splats {
        sh_degree: degree,
        ..Default::default()
    };
    s.antialiased = ply
        .comments
        .iter()
        .any(|c| c.trim().eq_ignore_ascii_case("SplatRenderMode: mip"));
    for comment in &ply.comments {
        if let Some(name) = comment.trim().strip_prefix(APPEARANCE_COMMENT) {
            s.appearance = crate::raster::Appearance::from_name(name.trim()).ok_or_else(|| {
                format!("unknown splat appearance `{}` in the header", name.trim())
            })?;
        }
    }
    for i in 0..n {
        s.means.push([x[i], y[i], z[i]].map(|v| v as f32));
        s.log_scales
            .push([scale[0][i], scale[1][i], scale[2][i]].map(|v| v as f32));
        s.quats
            .push([rot[0][i], rot[1][i], rot[2][i], rot[3][i]].map(|v| v as f32));
        s.opacity_logits.push(opacity[i] as f32);
        s.sh.push([dc[0][i], dc[1][i], dc[2][i]].map(|v| v as f32));
        for kk in 1..k {
            s.sh.push([0, 1, 2].map(|ch| rest[ch * (k - 1) + kk - 1][i] as f32));
        }
    }
    s.validate().map_err(|e| e.to_string())?;
    Ok(s)
}

/// The model as a binary little-endian 3DGS PLY.
pub fn splats_to_ply(s: &Splats) -> PlyFile {
    let n = s.len();
    let k = s.sh_coefficients();
    let mut properties = Vec::new();
    let mut columns = Vec::new();
    let mut push = |name: String, values: Vec<f64>| {
        properties.push(Property {
            name,
            scalar: ScalarType::F32,
            list_count: None,
        });
        columns.push(Column::Scalar(values));
    };
    for (a, name) in ["x", "y", "z"].iter().enumerate() {
        push(
            name.to_string(),
            s.means.iter().map(|m| m[a] as f64).collect(),
        );
    }
    for name in ["nx", "ny", "nz"] {
        push(name.to_string(), vec![0.0; n]);
    }
    for ch in 0..3 {
        push(
            format!("f_dc_{ch}"),
            (0..n).map(|i| s.sh[i * k][ch] as f64).collect(),
        );
    }
    for ch in 0..3 {
        for kk in 1..k {
            push(
                format!("f_rest_{}", ch * (k - 1) + kk - 1),
                (0..n).map(|i| s.sh[i * k + kk][ch] as f64).collect(),
            );
        }
    }
    push(
        "opacity".into(),
        s.opacity_logits.iter().map(|&v| v as f64).collect(),
    );
    for a in 0..3 {
        push(
            format!("scale_{a}"),
            s.log_scales.iter().map(|v| v[a] as f64).collect(),
        );
    }
    for a in 0..4 {
        push(
            format!("rot_{a}"),
            s.quats.iter().map(|v| v[a] as f64).collect(),
        );
    }
    let mode = if s.antialiased { "mip" } else { "default" };
    let mut comments = vec![format!("SplatRenderMode: {mode}")];
    if s.appearance != crate::raster::Appearance::ViewDirection {
        comments.push(format!("{APPEARANCE_COMMENT} {}", s.appearance.name()));
    }
    comments.push("written by omniscan".into());
    PlyFile {
        format: Format::BinaryLittleEndian,
        comments,
        elements: vec![Element {
            name: "vertex".into(),
            count: n,
            properties,
            columns,
        }],
    }
}

/// Writes a binary 3DGS PLY atomically.
pub fn write_splats(path: &Path, s: &Splats) -> Result<(), SplatError> {
    s.validate()?;
    omniscan_core::io::write_atomic(path, &omniscan_core::ply::to_binary_le(&splats_to_ply(s)))?;
    Ok(())
}

/// The `.splat` web format: 32 bytes per splat (position, scale, RGBA, and
/// the rotation as bytes), most visible splats first; DC colour only.
pub fn to_dot_splat(s: &Splats) -> Vec<u8> {
    let k = s.sh_coefficients();
    let sigmoid = |x: f32| 1.0 / (1.0 + (-x).exp());
    let mut order: Vec<usize> = (0..s.len()).collect();
    let weight =
        |i: usize| -(s.log_scales[i].iter().sum::<f32>()).exp() * sigmoid(s.opacity_logits[i]);
    order.sort_by(|&a, &b| weight(a).total_cmp(&weight(b)).then(a.cmp(&b)));
    let mut out = Vec::with_capacity(32 * s.len());
    for i in order {
        for v in s.means[i] {
            out.extend(v.to_le_bytes());
        }
        for v in s.log_scales[i] {
            out.extend(v.exp().to_le_bytes());
        }
        for v in s.sh[i * k] {
            out.push(((0.5 + C0 as f32 * v) * 255.0).round().clamp(0.0, 255.0) as u8);
        }
        out.push(
            (sigmoid(s.opacity_logits[i]) * 255.0)
                .round()
                .clamp(0.0, 255.0) as u8,
        );
        let q = s.quats[i];
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        for v in q {
            out.push((v / norm * 128.0 + 128.0).round().clamp(0.0, 255.0) as u8);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(degree: usize) -> Splats {
        let k = coefficients(degree);
        let n = 5;
        Splats {
            means: (0..n).map(|i| [i as f32, -0.5 * i as f32, 0.25]).collect(),
            log_scales: (0..n)
                .map(|i| [-3.0, -2.5 + 0.1 * i as f32, -4.0])
                .collect(),
            quats: (0..n).map(|i| [1.0, 0.1 * i as f32, -0.2, 0.3]).collect(),
            opacity_logits: (0..n).map(|i| i as f32 - 2.0).collect(),
            sh_degree: degree,
            sh: (0..n * k)
                .map(|j| [j as f32 * 0.01, -(j as f32) * 0.02, 0.5])
                .collect(),
            antialiased: degree == 2,
            appearance: if degree == 1 {
                crate::raster::Appearance::FixedRig
            } else {
                crate::raster::Appearance::ViewDirection
            },
        }
    }

    #[test]
    fn ply_round_trip_every_degree() {
        let dir = tempfile::tempdir().unwrap();
        for degree in 0..=3 {
            let s = sample(degree);
            let path = dir.path().join(format!("s{degree}.ply"));
            write_splats(&path, &s).unwrap();
            assert_eq!(read_splats(&path).unwrap(), s);
        }
    }

    #[test]
    fn bad_files_are_errors_not_panics() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.ply");
        write_splats(&path, &sample(3)).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(dir.path().join("cut.ply"), &bytes[..bytes.len() - 7]).unwrap();
        assert!(
            read_splats(&dir.path().join("cut.ply"))
                .unwrap_err()
                .to_string()
                .contains("truncated")
        );
        let mut s = sample(1);
        s.means[2][1] = f32::NAN;
        assert!(
            write_splats(&path, &s)
                .unwrap_err()
                .to_string()
                .contains("splat 2")
        );
        let ply = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n";
        std::fs::write(dir.path().join("points.ply"), ply).unwrap();
        assert!(
            read_splats(&dir.path().join("points.ply"))
                .unwrap_err()
                .to_string()
                .contains("f_dc_0")
        );
    }

    #[test]
    fn dot_splat_layout() {
        let s = sample(0);
        let bytes = to_dot_splat(&s);
        assert_eq!(bytes.len(), 32 * s.len());
    }
}
