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

/// The model file formats omniscan reads and writes, told by extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelFormat {
    /// The 3DGS PLY (`.ply`): every parameter, lossless. PlayCanvas'
    /// compressed PLY is read from a `.ply` too, told by its content.
    Ply,
    /// PlayCanvas' compressed PLY (`.compressed.ply`), read only.
    CompressedPly,
    /// The web viewers' `.splat`: 32 bytes a splat, base colour only.
    DotSplat,
    /// Niantic's SPZ (`.spz`), written as version 4.
    Spz,
    /// Binary glTF with `KHR_gaussian_splatting` (`.glb`).
    Glb,
}

fn compressed_ply_not_written(path: &Path) -> SplatError {
    SplatError::file(
        path,
        "omniscan reads PlayCanvas' compressed PLY but does not write it: write .spz for a compressed model",
    )
}

/// What `omniscan` lists when an extension is unknown.
const SUPPORTED: &str = ".ply (3DGS PLY), .compressed.ply (PlayCanvas, read only), .spz (Niantic SPZ), .glb (glTF KHR_gaussian_splatting) and .splat (web viewers)";

impl ModelFormat {
    /// The format `path` names, refused unless omniscan writes it: what a
    /// stage checks before its work, so a typo does not cost a training.
    pub fn writable(path: &Path) -> Result<ModelFormat, SplatError> {
        match ModelFormat::of(path)? {
            ModelFormat::CompressedPly => Err(compressed_ply_not_written(path)),
            format => Ok(format),
        }
    }

    /// The format's name for messages.
    pub fn name(self) -> &'static str {
        match self {
            ModelFormat::Ply => "3DGS PLY",
            ModelFormat::CompressedPly => "compressed PLY",
            ModelFormat::DotSplat => ".splat",
            ModelFormat::Spz => "SPZ",
            ModelFormat::Glb => "glTF (KHR_gaussian_splatting)",
        }
    }

    /// The format `path`'s extension names; an unknown one is an error
    /// listing those there are.
    pub fn of(path: &Path) -> Result<ModelFormat, SplatError> {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        if name.ends_with(".compressed.ply") {
            return Ok(ModelFormat::CompressedPly);
        }
        let extension = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase());
        match extension.as_deref() {
            Some("ply") => Ok(ModelFormat::Ply),
            Some("splat") => Ok(ModelFormat::DotSplat),
            Some("spz") => Ok(ModelFormat::Spz),
            Some("glb") => Ok(ModelFormat::Glb),
            other => Err(SplatError::file(
                path,
                format!(
                    "unknown model format {}: omniscan reads {SUPPORTED}",
                    other.map_or("(no extension)".to_string(), |e| format!("`.{e}`"))
                ),
            )),
        }
    }
}

/// Reads a splat model in the format its extension names ([`ModelFormat`];
/// a file with another extension is read as PLY when it is one).
pub fn read_splats(path: &Path) -> Result<Splats, SplatError> {
    let bytes = std::fs::read(path).map_err(|e| omniscan_core::CoreError::io(path, e))?;
    let format = match ModelFormat::of(path) {
        Ok(format) => format,
        Err(_) if bytes.starts_with(b"ply") => ModelFormat::Ply,
        Err(e) => return Err(e),
    };
    let splats = match format {
        ModelFormat::Ply | ModelFormat::CompressedPly => omniscan_core::ply::parse(&bytes)
            .and_then(|ply| {
                if crate::compressed_ply::is_compressed(&ply) {
                    crate::compressed_ply::splats_from_compressed_ply(&ply)
                } else {
                    splats_from_ply(&ply)
                }
            }),
        ModelFormat::DotSplat => from_dot_splat(&bytes),
        ModelFormat::Spz => crate::spz::from_spz(&bytes),
        ModelFormat::Glb => crate::glb::from_glb(&bytes),
    };
    splats.map_err(|m| SplatError::file(path, m))
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

/// Writes a model atomically in the format `path`'s extension names
/// ([`ModelFormat`]). The lossy formats say what they drop: `.splat` keeps
/// the base colour only; SPZ and glTF keep the SH bands of ordinary models
/// and the base colour of fixed-rig ones (whose bands other viewers would
/// take for view-dependent colour).
pub fn write_splats(path: &Path, s: &Splats) -> Result<(), SplatError> {
    write_splats_as(path, s, crate::spz::SpzVersion::V4)
}

/// [`write_splats`], with the SPZ version to write when `path` is `.spz`.
pub fn write_splats_as(
    path: &Path,
    s: &Splats,
    spz_version: crate::spz::SpzVersion,
) -> Result<(), SplatError> {
    s.validate()?;
    let format = ModelFormat::writable(path)?;
    let keeps_bands = match format {
        ModelFormat::Ply => true,
        ModelFormat::DotSplat => false,
        _ => s.appearance == crate::raster::Appearance::ViewDirection,
    };
    if s.sh_degree > 0 && !keeps_bands {
        tracing::warn!(
            "{}: {} keeps the base colour of this model only; SH bands 1-{} are not written",
            path.display(),
            format.name(),
            s.sh_degree
        );
    }
    let bytes = match format {
        ModelFormat::Ply => omniscan_core::ply::to_binary_le(&splats_to_ply(s)),
        ModelFormat::CompressedPly => return Err(compressed_ply_not_written(path)),
        ModelFormat::DotSplat => to_dot_splat(s),
        ModelFormat::Spz => crate::spz::to_spz(s, spz_version),
        ModelFormat::Glb => crate::glb::to_glb(s),
    };
    omniscan_core::io::write_atomic(path, &bytes)?;
    Ok(())
}

/// Reads the `.splat` web format ([`to_dot_splat`]): linear scales, 8-bit
/// RGBA (colour after the DC band, opacity after the sigmoid) and an 8-bit
/// rotation, all turned back into the model's parameters.
pub fn from_dot_splat(bytes: &[u8]) -> Result<Splats, String> {
    if bytes.is_empty() || !bytes.len().is_multiple_of(32) {
        return Err(format!(
            "not a .splat file: {} bytes is not a whole number of 32-byte splats",
            bytes.len()
        ));
    }
    let f32_at = |b: &[u8], i: usize| f32::from_le_bytes(b[4 * i..4 * i + 4].try_into().unwrap());
    // 8-bit values stay off 0 and 1, where the logit and log are infinite.
    let unit = |byte: u8| (f32::from(byte) / 255.0).clamp(0.5 / 255.0, 254.5 / 255.0);
    let mut s = Splats::default();
    for (index, b) in bytes.chunks_exact(32).enumerate() {
        s.means.push([f32_at(b, 0), f32_at(b, 1), f32_at(b, 2)]);
        let scale = [f32_at(b, 3), f32_at(b, 4), f32_at(b, 5)];
        if !scale.iter().all(|v| v.is_finite() && *v > 0.0) {
            return Err(format!(
                "splat {index}: scales must be positive, got {scale:?}"
            ));
        }
        s.log_scales.push(scale.map(f32::ln));
        s.sh.push([b[24], b[25], b[26]].map(|c| (f32::from(c) / 255.0 - 0.5) / C0 as f32));
        let alpha = unit(b[27]);
        s.opacity_logits.push((alpha / (1.0 - alpha)).ln());
        let q = [b[28], b[29], b[30], b[31]].map(|v| (f32::from(v) - 128.0) / 128.0);
        if q.iter().all(|v| *v == 0.0) {
            return Err(format!("splat {index}: the rotation is zero"));
        }
        s.quats.push(q);
    }
    s.validate().map_err(|e| e.to_string())?;
    Ok(s)
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

    /// `.splat` by extension, read back within its 8-bit quantisation;
    /// an unknown extension names the formats there are.
    #[test]
    fn the_extension_chooses_the_format_and_splat_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let s = sample(0);
        let path = dir.path().join("m.splat");
        write_splats(&path, &s).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), to_dot_splat(&s));
        let back = read_splats(&path).unwrap();
        assert_eq!(back.len(), s.len());
        // Splats come back ordered by visibility: match them by position.
        let sigmoid = |x: f32| 1.0 / (1.0 + (-x).exp());
        for i in 0..s.len() {
            let j = (0..back.len())
                .find(|&j| back.means[j] == s.means[i])
                .unwrap();
            for a in 0..3 {
                assert!((back.log_scales[j][a] - s.log_scales[i][a]).abs() < 1e-5);
                let colour = |sh: &[f32; 3]| 0.5 + C0 as f32 * sh[a];
                assert!(
                    (colour(&back.sh[j]) - colour(&s.sh[i]).clamp(0.0, 1.0)).abs()
                        <= 0.5 / 255.0 + 1e-6
                );
            }
            assert!(
                (sigmoid(back.opacity_logits[j]) - sigmoid(s.opacity_logits[i])).abs()
                    <= 0.5 / 255.0 + 1e-6
            );
        }
        for name in ["m.ksplat", "m"] {
            let error = write_splats(&dir.path().join(name), &s)
                .unwrap_err()
                .to_string();
            assert!(error.contains(SUPPORTED), "{error}");
        }
        let error = write_splats(&dir.path().join("m.compressed.ply"), &s)
            .unwrap_err()
            .to_string();
        assert!(error.contains("does not write it"), "{error}");
        // Every written format reads back by its extension.
        for name in ["m.spz", "m.glb"] {
            write_splats(&dir.path().join(name), &s).unwrap();
            assert_eq!(read_splats(&dir.path().join(name)).unwrap().len(), s.len());
        }
        std::fs::write(dir.path().join("bad.splat"), [0u8; 33]).unwrap();
        let error = read_splats(&dir.path().join("bad.splat"))
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("not a whole number of 32-byte splats"),
            "{error}"
        );
    }
}
