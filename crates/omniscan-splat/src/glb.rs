//! Binary glTF 2.0 (`.glb`) with Khronos' `KHR_gaussian_splatting`: one
//! point primitive whose attributes are the splats, in the extension's
//! conventions: `POSITION`, `KHR_gaussian_splatting:ROTATION` as an `xyzw`
//! unit quaternion, `:SCALE` linear (not the log), `:OPACITY` after the
//! sigmoid, `:SH_DEGREE_ℓ_COEF_n` the SH coefficients (RGB), and `COLOR_0`
//! the base colour for viewers without the extension.
//!
//! glTF's axes are +Y up, +Z forward and +X left of a viewer facing the
//! model; the 3DGS PLY is taken to be in COLMAP's RDF axes (as for SPZ,
//! [`crate::spz`]), so the writer turns the model a half turn about z, as
//! PlayCanvas' `splat-transform` does, and the reader turns it back.
//!
//! The reader takes float accessors, which is what this writer and
//! `splat-transform` write; a file with quantized accessors or a node
//! transform is refused by name rather than read wrongly.

use serde_json::{Value, json};

use crate::Splats;
use crate::sh::coefficients;

const MAGIC: u32 = 0x4654_6c67; // "glTF"
const CHUNK_JSON: u32 = 0x4e4f_534a;
const CHUNK_BIN: u32 = 0x004e_4942;
const FLOAT: u64 = 5126;
const UNSIGNED_BYTE: u64 = 5121;
const EXTENSION: &str = "KHR_gaussian_splatting";

/// The sign each SH coefficient `k ≥ 1` takes when the axes turn half a
/// turn about z (x → −x, y → −y).
fn half_turn_z_signs(degree: usize) -> Vec<f32> {
    let d = [0.267f64, 0.534, 0.801];
    let turned = [-d[0], -d[1], d[2]];
    let (b, t) = (
        crate::sh::basis(degree, d),
        crate::sh::basis(degree, turned),
    );
    b.iter()
        .zip(&t)
        .skip(1)
        .map(|(a, c)| if a * c < 0.0 { -1.0 } else { 1.0 })
        .collect()
}

/// One attribute's data, before it is laid out in the buffer.
struct Attribute {
    name: String,
    kind: &'static str,
    component: u64,
    normalized: bool,
    bytes: Vec<u8>,
    bounds: Option<([f32; 3], [f32; 3])>,
}

fn float_attribute(name: impl Into<String>, kind: &'static str, values: &[f32]) -> Attribute {
    Attribute {
        name: name.into(),
        kind,
        component: FLOAT,
        normalized: false,
        bytes: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        bounds: None,
    }
}

/// The model as a `.glb`. Fixed-rig models keep their base colour only, as
/// in SPZ.
pub fn to_glb(s: &Splats) -> Vec<u8> {
    let attributes = attributes(s);
    let count = s.len();
    let mut buffer = Vec::new();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    let mut names = serde_json::Map::new();
    for (index, a) in attributes.iter().enumerate() {
        views.push(json!({"buffer": 0, "byteOffset": buffer.len(), "byteLength": a.bytes.len(), "target": 34962}));
        buffer.extend_from_slice(&a.bytes);
        buffer.resize(buffer.len().next_multiple_of(4), 0);
        let mut accessor = json!({"bufferView": index, "componentType": a.component, "count": count, "type": a.kind});
        if a.normalized {
            accessor["normalized"] = json!(true);
        }
        if let Some((min, max)) = a.bounds {
            accessor["min"] = json!(min);
            accessor["max"] = json!(max);
        }
        accessors.push(accessor);
        names.insert(a.name.clone(), json!(index));
    }
    let document = json!({
        "asset": {"version": "2.0", "generator": concat!("omniscan ", env!("CARGO_PKG_VERSION"))},
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{
            "attributes": names,
            "mode": 0,
            "extensions": {EXTENSION: {
                "kernel": "ellipse",
                "colorSpace": "srgb_rec709_display",
                "sortingMethod": "cameraDistance",
                "projection": "perspective"
            }}
        }]}],
        "buffers": [{"byteLength": buffer.len()}],
        "bufferViews": views,
        "accessors": accessors,
    });
    pack_glb(&document, &buffer)
}

/// A glTF binary container: the JSON `document` and one binary chunk.
pub fn pack_glb(document: &Value, buffer: &[u8]) -> Vec<u8> {
    let mut text = serde_json::to_vec(&document).expect("a JSON value serialises");
    text.resize(text.len().next_multiple_of(4), b' ');
    let padded = buffer.len().next_multiple_of(4);
    let total = 12 + 8 + text.len() + 8 + padded;
    let mut out = Vec::with_capacity(total);
    out.extend(MAGIC.to_le_bytes());
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((text.len() as u32).to_le_bytes());
    out.extend(CHUNK_JSON.to_le_bytes());
    out.extend(text);
    out.extend((padded as u32).to_le_bytes());
    out.extend(CHUNK_BIN.to_le_bytes());
    out.extend_from_slice(buffer);
    out.resize(out.len().next_multiple_of(4), 0);
    out
}

fn attributes(s: &Splats) -> Vec<Attribute> {
    let n = s.len();
    let k = s.sh_coefficients();
    let degree = if s.appearance == crate::raster::Appearance::ViewDirection {
        s.sh_degree
    } else {
        0
    };
    let sigmoid = |x: f32| 1.0 / (1.0 + (-x).exp());
    let turn = |m: [f32; 3]| [-m[0], -m[1], m[2]];
    let positions: Vec<f32> = s.means.iter().flat_map(|m| turn(*m)).collect();
    let mut min = [f32::INFINITY; 3];
    let mut max = [f32::NEG_INFINITY; 3];
    for p in positions.chunks_exact(3) {
        for a in 0..3 {
            min[a] = min[a].min(p[a]);
            max[a] = max[a].max(p[a]);
        }
    }
    let mut position = float_attribute("POSITION", "VEC3", &positions);
    position.bounds = Some((min, max));
    let rotations: Vec<f32> = s
        .quats
        .iter()
        .flat_map(|q| {
            let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            [-q[1] / norm, -q[2] / norm, q[3] / norm, q[0] / norm]
        })
        .collect();
    let scales: Vec<f32> = s.log_scales.iter().flat_map(|l| l.map(f32::exp)).collect();
    let opacities: Vec<f32> = s.opacity_logits.iter().map(|&l| sigmoid(l)).collect();
    let to_byte = |v: f32| (v * 255.0).round().clamp(0.0, 255.0) as u8;
    let colours: Vec<u8> = (0..n)
        .flat_map(|i| {
            let dc = s.sh[i * k];
            let rgb = dc.map(|c| to_byte(c * crate::sh::C0 as f32 + 0.5));
            [rgb[0], rgb[1], rgb[2], to_byte(opacities[i])]
        })
        .collect();
    let mut out = vec![
        position,
        Attribute {
            name: "COLOR_0".into(),
            kind: "VEC4",
            component: UNSIGNED_BYTE,
            normalized: true,
            bytes: colours,
            bounds: None,
        },
        float_attribute(format!("{EXTENSION}:ROTATION"), "VEC4", &rotations),
        float_attribute(format!("{EXTENSION}:SCALE"), "VEC3", &scales),
        float_attribute(format!("{EXTENSION}:OPACITY"), "SCALAR", &opacities),
    ];
    let signs = half_turn_z_signs(degree);
    for kk in 0..coefficients(degree) {
        let (band, index) = band_of(kk);
        let sign = if kk == 0 { 1.0 } else { signs[kk - 1] };
        let values: Vec<f32> = (0..n)
            .flat_map(|i| s.sh[i * k + kk].map(|c| sign * c))
            .collect();
        out.push(float_attribute(
            format!("{EXTENSION}:SH_DEGREE_{band}_COEF_{index}"),
            "VEC3",
            &values,
        ));
    }
    out
}

/// The degree ℓ and index n of flat coefficient `k` (k = ℓ² + n).
fn band_of(k: usize) -> (usize, usize) {
    let band = (k as f64).sqrt().floor() as usize;
    (band, k - band * band)
}

/// Reads the first `KHR_gaussian_splatting` primitive of a `.glb`.
pub fn from_glb(bytes: &[u8]) -> Result<Splats, String> {
    let (document, bin) = split_glb(bytes)?;
    let primitive = document["meshes"]
        .as_array()
        .into_iter()
        .flatten()
        .flat_map(|m| m["primitives"].as_array().into_iter().flatten())
        .find(|p| p["extensions"][EXTENSION].is_object())
        .ok_or("the glTF has no primitive with KHR_gaussian_splatting")?;
    refuse_node_transforms(&document)?;
    let attributes = &primitive["attributes"];
    let read = |name: &str, width: usize| -> Result<Vec<f32>, String> {
        let index = attributes[name]
            .as_u64()
            .ok_or_else(|| format!("the splat primitive has no `{name}` attribute"))?;
        read_float_accessor(&document, bin, index as usize, width)
            .map_err(|e| format!("`{name}`: {e}"))
    };
    let positions = read("POSITION", 3)?;
    let n = positions.len() / 3;
    if n == 0 {
        return Err("the model has no splats (an empty POSITION accessor)".into());
    }
    let rotations = read(&format!("{EXTENSION}:ROTATION"), 4)?;
    let scales = read(&format!("{EXTENSION}:SCALE"), 3)?;
    let opacities = read(&format!("{EXTENSION}:OPACITY"), 1)?;
    let mut bands = Vec::new();
    for kk in 0..16 {
        let (band, index) = band_of(kk);
        let name = format!("{EXTENSION}:SH_DEGREE_{band}_COEF_{index}");
        if attributes[&name].is_null() {
            break;
        }
        bands.push(read(&name, 3)?);
    }
    let degree = match bands.len() {
        1 => 0,
        4 => 1,
        9 => 2,
        16 => 3,
        0 => return Err(format!("no `{EXTENSION}:SH_DEGREE_0_COEF_0` attribute")),
        other => {
            return Err(format!(
                "{other} SH coefficients are not a whole number of degrees"
            ));
        }
    };
    for (name, len) in [
        ("ROTATION", rotations.len() / 4),
        ("SCALE", scales.len() / 3),
        ("OPACITY", opacities.len()),
    ]
    .into_iter()
    .chain(bands.iter().map(|b| ("SH", b.len() / 3)))
    {
        if len != n {
            return Err(format!("{name} has {len} values for {n} splats"));
        }
    }
    let signs = half_turn_z_signs(degree);
    let mut s = Splats {
        sh_degree: degree,
        ..Default::default()
    };
    for i in 0..n {
        let p = &positions[3 * i..3 * i + 3];
        s.means.push([-p[0], -p[1], p[2]]);
        let q = &rotations[4 * i..4 * i + 4];
        s.quats.push([q[3], -q[0], -q[1], q[2]]);
        let scale = &scales[3 * i..3 * i + 3];
        if !scale.iter().all(|v| v.is_finite() && *v > 0.0) {
            return Err(format!(
                "splat {i}: SCALE must be positive (linear), got {scale:?}"
            ));
        }
        s.log_scales
            .push([scale[0].ln(), scale[1].ln(), scale[2].ln()]);
        let alpha = opacities[i];
        if !(0.0..=1.0).contains(&alpha) {
            return Err(format!("splat {i}: OPACITY {alpha} is outside [0, 1]"));
        }
        let alpha = alpha.clamp(0.5 / 255.0, 254.5 / 255.0);
        s.opacity_logits.push((alpha / (1.0 - alpha)).ln());
        for (kk, band) in bands.iter().enumerate() {
            let sign = if kk == 0 { 1.0 } else { signs[kk - 1] };
            s.sh.push([0, 1, 2].map(|ch| sign * band[3 * i + ch]));
        }
    }
    s.validate().map_err(|e| e.to_string())?;
    Ok(s)
}

fn split_glb(bytes: &[u8]) -> Result<(Value, &[u8]), String> {
    let u32_at = |i: usize| -> Result<u32, String> {
        bytes
            .get(i..i + 4)
            .map(|b| u32::from_le_bytes(b.try_into().unwrap()))
            .ok_or_else(|| "truncated glTF binary".to_string())
    };
    if u32_at(0)? != MAGIC {
        return Err("not a binary glTF (.glb): no `glTF` magic".into());
    }
    if u32_at(4)? != 2 {
        return Err(format!(
            "glTF binary version {} (omniscan reads 2)",
            u32_at(4)?
        ));
    }
    if u32_at(8)? as usize != bytes.len() {
        return Err(format!(
            "truncated or padded glTF binary: the header says {} bytes, the file has {}",
            u32_at(8)?,
            bytes.len()
        ));
    }
    let json_length = u32_at(12)? as usize;
    if u32_at(16)? != CHUNK_JSON {
        return Err("the first glTF chunk is not JSON".into());
    }
    let text = bytes
        .get(20..20 + json_length)
        .ok_or("truncated glTF binary: the JSON chunk is cut off")?;
    let document: Value =
        serde_json::from_slice(text).map_err(|e| format!("the glTF JSON does not parse: {e}"))?;
    let bin_at = 20 + json_length;
    let bin = if bytes.len() > bin_at {
        let length = u32_at(bin_at)? as usize;
        if u32_at(bin_at + 4)? != CHUNK_BIN {
            return Err("the second glTF chunk is not BIN".into());
        }
        bytes
            .get(bin_at + 8..bin_at + 8 + length)
            .ok_or("truncated glTF binary: the BIN chunk is cut off")?
    } else {
        &[]
    };
    Ok((document, bin))
}

fn refuse_node_transforms(document: &Value) -> Result<(), String> {
    for node in document["nodes"].as_array().into_iter().flatten() {
        for key in ["matrix", "translation", "rotation", "scale"] {
            if !node[key].is_null() {
                return Err(format!(
                    "a node has a `{key}`: omniscan reads splats in the file's own frame only"
                ));
            }
        }
    }
    Ok(())
}

fn read_float_accessor(
    document: &Value,
    bin: &[u8],
    index: usize,
    width: usize,
) -> Result<Vec<f32>, String> {
    let accessor = &document["accessors"][index];
    if accessor.is_null() {
        return Err(format!("accessor {index} does not exist"));
    }
    if accessor["componentType"].as_u64() != Some(FLOAT) {
        return Err(format!(
            "accessor {index} is not float (component type {}); quantized splats are not read",
            accessor["componentType"]
        ));
    }
    let count = accessor["count"]
        .as_u64()
        .ok_or("an accessor without `count`")? as usize;
    let view = &document["bufferViews"][accessor["bufferView"]
        .as_u64()
        .ok_or("a sparse or empty accessor")? as usize];
    if view["buffer"].as_u64() != Some(0) {
        return Err("data outside the .glb's own buffer".into());
    }
    let offset = |v: &Value| usize::try_from(v.as_u64().unwrap_or(0)).unwrap_or(usize::MAX);
    let start = offset(&view["byteOffset"]).saturating_add(offset(&accessor["byteOffset"]));
    let element = 4 * width;
    let stride = view["byteStride"].as_u64().map_or(element, |s| s as usize);
    if stride < element {
        return Err(format!(
            "byte stride {stride} is shorter than an element ({element})"
        ));
    }
    let view_end = offset(&view["byteOffset"]).saturating_add(offset(&view["byteLength"]));
    let needed = match count {
        0 => Some(start),
        _ => stride
            .checked_mul(count - 1)
            .and_then(|v| v.checked_add(start))
            .and_then(|v| v.checked_add(element)),
    };
    match needed {
        Some(needed) if needed <= view_end && view_end <= bin.len() => {}
        _ => {
            return Err(format!(
                "accessor {index} ({count} elements) runs past its buffer of {} bytes",
                view_end.min(bin.len())
            ));
        }
    }
    let mut out = Vec::with_capacity(count * width);
    for i in 0..count {
        let at = start + i * stride;
        for c in 0..width {
            let b = &bin[at + 4 * c..at + 4 * c + 4];
            out.push(f32::from_le_bytes(b.try_into().unwrap()));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model(degree: usize, n: usize) -> Splats {
        crate::test_support::random_model(3, degree, n, 0.5)
    }

    #[test]
    fn round_trips_to_single_precision() {
        let s = model(3, 50);
        let back = from_glb(&to_glb(&s)).unwrap();
        assert_eq!(back.sh_degree, 3);
        for i in 0..s.len() {
            for a in 0..3 {
                assert!((back.means[i][a] - s.means[i][a]).abs() < 1e-6);
                assert!((back.log_scales[i][a] - s.log_scales[i][a]).abs() < 1e-5);
            }
            let dot: f32 = back.quats[i]
                .iter()
                .zip(&s.quats[i])
                .map(|(a, b)| a * b)
                .sum();
            assert!((dot.abs() - 1.0).abs() < 1e-5);
            assert!((back.opacity_logits[i] - s.opacity_logits[i]).abs() < 1e-4);
            for kk in 0..16 {
                for ch in 0..3 {
                    assert!((back.sh[i * 16 + kk][ch] - s.sh[i * 16 + kk][ch]).abs() < 1e-6);
                }
            }
        }
    }

    #[test]
    fn attributes_follow_the_extension() {
        let mut s = model(1, 1);
        s.means[0] = [0.1, 0.2, 0.3];
        s.log_scales[0] = [0.0, 1.0, -1.0];
        s.opacity_logits[0] = 0.0;
        s.quats[0] = [1.0, 0.0, 0.0, 0.0];
        let (document, bin) = split_glb(&to_glb(&s))
            .map(|(d, b)| (d, b.to_vec()))
            .unwrap();
        let read = |name: &str, width| {
            let index = document["meshes"][0]["primitives"][0]["attributes"][name]
                .as_u64()
                .unwrap();
            read_float_accessor(&document, &bin, index as usize, width).unwrap()
        };
        // glTF's axes: a half turn about z from the PLY's.
        assert_eq!(read("POSITION", 3), vec![-0.1, -0.2, 0.3]);
        let scale = read("KHR_gaussian_splatting:SCALE", 3);
        assert!(
            (scale[1] - std::f32::consts::E).abs() < 1e-6,
            "linear scales"
        );
        assert_eq!(read("KHR_gaussian_splatting:OPACITY", 1), vec![0.5]);
        assert_eq!(
            read("KHR_gaussian_splatting:ROTATION", 4),
            vec![0.0, 0.0, 0.0, 1.0]
        );
        assert_eq!(document["extensionsUsed"][0], EXTENSION);
        assert_eq!(document["meshes"][0]["primitives"][0]["mode"], 0);
    }

    #[test]
    fn bad_files_are_refused() {
        let glb = to_glb(&model(0, 4));
        assert!(
            from_glb(&glb[..glb.len() - 4])
                .unwrap_err()
                .contains("truncated")
        );
        assert!(
            from_glb(b"ply\n")
                .unwrap_err()
                .contains("not a binary glTF")
        );
    }
}
