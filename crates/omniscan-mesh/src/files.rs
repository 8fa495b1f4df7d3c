//! Mesh files: Wavefront OBJ + MTL + PNG texture, binary PLY with vertex
//! colours, and glTF binary (`.glb`) with the texture inside. Every file is
//! written atomically (`omniscan_core::io`).
//!
//! Positions are metres in the twin's frame. The GLB alone is turned half a
//! turn about z, as `omniscan_splat::glb` turns splat models into glTF's
//! axes, so a mesh and a splat `.glb` of one twin line up in a viewer.

use std::path::{Path, PathBuf};

use image::ImageEncoder;
use serde_json::json;

use omniscan_core::io::write_atomic;
use omniscan_core::ply::{Column, Element, Format, PlyFile, Property, ScalarType};

use crate::texture::Texture;
use crate::{MeshError, TriMesh};

/// The files [`write_all`] wrote.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MeshFiles {
    pub obj: PathBuf,
    pub mtl: PathBuf,
    pub texture: PathBuf,
    pub ply: PathBuf,
    pub glb: PathBuf,
}

/// Writes `NAME.obj` (+ `.mtl`, `.png`), `NAME.ply` and `NAME.glb` in `dir`.
pub fn write_all(
    dir: &Path,
    name: &str,
    mesh: &TriMesh,
    texture: &Texture,
) -> Result<MeshFiles, MeshError> {
    let files = MeshFiles {
        obj: dir.join(format!("{name}.obj")),
        mtl: dir.join(format!("{name}.mtl")),
        texture: dir.join(format!("{name}.png")),
        ply: dir.join(format!("{name}.ply")),
        glb: dir.join(format!("{name}.glb")),
    };
    let png = encode_png(texture, &files.texture)?;
    write_atomic(&files.texture, &png)?;
    write_atomic(&files.mtl, mtl(name).as_bytes())?;
    write_atomic(&files.obj, obj(mesh, Some((name, texture))).as_bytes())?;
    write_atomic(&files.ply, &ply(mesh))?;
    write_atomic(&files.glb, &glb(mesh, texture, &png))?;
    Ok(files)
}

fn encode_png(texture: &Texture, path: &Path) -> Result<Vec<u8>, MeshError> {
    let mut png = Vec::new();
    image::codecs::png::PngEncoder::new(&mut png)
        .write_image(
            &texture.rgb,
            texture.width,
            texture.height,
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|e| MeshError::File {
            path: path.to_path_buf(),
            message: format!("encoding the texture: {e}"),
        })?;
    Ok(png)
}

fn mtl(name: &str) -> String {
    format!(
        "# omniscan\nnewmtl {name}\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\nmap_Kd {name}.png\n"
    )
}

/// OBJ text: vertices with their colours (`v x y z r g b`, read by MeshLab,
/// trimesh and Blender), and, with a texture, a `vt` per triangle corner
/// and the material.
pub fn obj(mesh: &TriMesh, textured: Option<(&str, &Texture)>) -> String {
    use std::fmt::Write;
    let mut s = String::from("# omniscan mesh, metres\n");
    if let Some((name, _)) = textured {
        let _ = writeln!(s, "mtllib {name}.mtl\nusemtl {name}");
    }
    for (p, c) in mesh.positions.iter().zip(&mesh.colors) {
        let _ = writeln!(
            s,
            "v {} {} {} {:.4} {:.4} {:.4}",
            p[0], p[1], p[2], c[0], c[1], c[2]
        );
    }
    match textured {
        Some((_, texture)) => {
            for uv in texture.uvs.iter().flatten() {
                // OBJ's v runs up from the bottom.
                let _ = writeln!(s, "vt {} {}", uv[0], 1.0 - uv[1]);
            }
            for (i, t) in mesh.triangles.iter().enumerate() {
                let [a, b, c] = t.map(|v| v + 1);
                let k = 3 * i + 1;
                let _ = writeln!(s, "f {a}/{k} {b}/{} {c}/{}", k + 1, k + 2);
            }
        }
        None => {
            for t in &mesh.triangles {
                let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
            }
        }
    }
    s
}

fn scalar(name: &str, scalar: ScalarType) -> Property {
    Property {
        name: name.into(),
        scalar,
        list_count: None,
    }
}

/// Binary PLY: float positions, 8-bit colours, faces with an `unseen` flag
/// (1: the triangle closes a region no view saw).
pub fn ply(mesh: &TriMesh) -> Vec<u8> {
    let n = mesh.positions.len();
    let axis = |k: usize| Column::Scalar(mesh.positions.iter().map(|p| p[k] as f64).collect());
    let color = |k: usize| {
        Column::Scalar(
            mesh.colors
                .iter()
                .map(|c| (c[k].clamp(0.0, 1.0) * 255.0).round() as f64)
                .collect(),
        )
    };
    let vertex = Element {
        name: "vertex".into(),
        count: n,
        properties: vec![
            scalar("x", ScalarType::F32),
            scalar("y", ScalarType::F32),
            scalar("z", ScalarType::F32),
            scalar("red", ScalarType::U8),
            scalar("green", ScalarType::U8),
            scalar("blue", ScalarType::U8),
        ],
        columns: vec![axis(0), axis(1), axis(2), color(0), color(1), color(2)],
    };
    let face = Element {
        name: "face".into(),
        count: mesh.triangles.len(),
        properties: vec![
            Property {
                name: "vertex_indices".into(),
                scalar: ScalarType::U32,
                list_count: Some(ScalarType::U8),
            },
            scalar("unseen", ScalarType::U8),
        ],
        columns: vec![
            Column::List(
                mesh.triangles
                    .iter()
                    .map(|t| t.map(f64::from).to_vec())
                    .collect(),
            ),
            Column::Scalar(mesh.unseen.iter().map(|&u| u as u8 as f64).collect()),
        ],
    };
    omniscan_core::ply::to_binary_le(&PlyFile {
        format: Format::BinaryLittleEndian,
        comments: vec!["omniscan mesh, metres".into()],
        elements: vec![vertex, face],
    })
}

/// Smooth normals (area-weighted face normals) per vertex.
pub fn vertex_normals(mesh: &TriMesh) -> Vec<[f32; 3]> {
    let mut normals = vec![[0.0f32; 3]; mesh.positions.len()];
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|v| mesh.positions[v as usize]);
        let (u, v) = (
            [0, 1, 2].map(|k| b[k] - a[k]),
            [0, 1, 2].map(|k| c[k] - a[k]),
        );
        let n = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        for &i in t {
            (0..3).for_each(|k| normals[i as usize][k] += n[k]);
        }
    }
    for n in &mut normals {
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        *n = if len > 0.0 {
            n.map(|c| c / len)
        } else {
            [0.0, 0.0, 1.0]
        };
    }
    normals
}

/// glTF binary: a corner per triangle corner (its UV is the triangle's
/// own), positions, smooth normals, UVs, the PNG texture.
pub fn glb(mesh: &TriMesh, texture: &Texture, png: &[u8]) -> Vec<u8> {
    let normals = vertex_normals(mesh);
    // glTF's axes: the half turn about z that the splat models get.
    let turn = |v: [f32; 3]| [-v[0], -v[1], v[2]];
    let corners = || mesh.triangles.iter().flatten().map(|&v| v as usize);
    let positions: Vec<[f32; 3]> = corners().map(|v| turn(mesh.positions[v])).collect();
    let normals: Vec<[f32; 3]> = corners().map(|v| turn(normals[v])).collect();
    let uvs: Vec<[f32; 2]> = texture.uvs.iter().flatten().copied().collect();
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in &positions {
        (0..3).for_each(|k| {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        });
    }
    let mut buffer = Vec::new();
    let mut views = Vec::new();
    let mut push = |bytes: Vec<u8>, target: Option<u32>| {
        let mut view = json!({"buffer": 0, "byteOffset": buffer.len(), "byteLength": bytes.len()});
        if let Some(t) = target {
            view["target"] = json!(t);
        }
        views.push(view);
        buffer.extend_from_slice(&bytes);
        buffer.resize(buffer.len().next_multiple_of(4), 0);
    };
    let floats = |v: &[f32]| v.iter().flat_map(|c| c.to_le_bytes()).collect::<Vec<u8>>();
    push(floats(positions.as_flattened()), Some(34962));
    push(floats(normals.as_flattened()), Some(34962));
    push(floats(uvs.as_flattened()), Some(34962));
    push(png.to_vec(), None);
    let count = positions.len();
    let document = json!({
        "asset": {"version": "2.0", "generator": concat!("omniscan ", env!("CARGO_PKG_VERSION"))},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "object"}],
        "meshes": [{"primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
            "material": 0,
            "mode": 4
        }]}],
        "materials": [{
            "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0, "roughnessFactor": 1.0},
            "doubleSided": false
        }],
        "textures": [{"source": 0, "sampler": 0}],
        "samplers": [{"magFilter": 9729, "minFilter": 9729}],
        "images": [{"bufferView": 3, "mimeType": "image/png"}],
        "buffers": [{"byteLength": buffer.len()}],
        "bufferViews": views,
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": count, "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5126, "count": count, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": count, "type": "VEC2"},
        ],
    });
    omniscan_splat::glb::pack_glb(&document, &buffer)
}

/// Writes a plain OBJ (positions and faces only), as collision hulls are.
pub fn write_plain_obj(path: &Path, mesh: &TriMesh) -> Result<(), MeshError> {
    Ok(write_atomic(path, obj(mesh, None).as_bytes())?)
}

/// Reads a triangle mesh from a PLY file (ours, or any with float `x y z`,
/// optional 8-bit `red green blue`, and triangular `vertex_indices`).
pub fn read_ply_mesh(path: &Path) -> Result<TriMesh, MeshError> {
    let bad = |message: String| MeshError::File {
        path: path.to_path_buf(),
        message,
    };
    let file = omniscan_core::ply::read(path)?;
    let vertex = file
        .element("vertex")
        .ok_or_else(|| bad("no vertex element".into()))?;
    let face = file
        .element("face")
        .ok_or_else(|| bad("no face element".into()))?;
    let axis = |name: &str| {
        vertex
            .scalar(name)
            .ok_or_else(|| bad(format!("no vertex property `{name}`")))
    };
    let (x, y, z) = (axis("x")?, axis("y")?, axis("z")?);
    let positions: Vec<[f32; 3]> = (0..vertex.count)
        .map(|i| [x[i], y[i], z[i]].map(|c| c as f32))
        .collect();
    let colors = match (
        vertex.scalar("red"),
        vertex.scalar("green"),
        vertex.scalar("blue"),
    ) {
        (Some(r), Some(g), Some(b)) => (0..vertex.count)
            .map(|i| [r[i], g[i], b[i]].map(|c| (c / 255.0) as f32))
            .collect(),
        _ => vec![[0.5; 3]; vertex.count],
    };
    let lists = face
        .list("vertex_indices")
        .or_else(|| face.list("vertex_index"))
        .ok_or_else(|| bad("no face property `vertex_indices`".into()))?;
    let mut triangles = Vec::with_capacity(lists.len());
    for (i, list) in lists.iter().enumerate() {
        let [a, b, c] = list[..] else {
            return Err(bad(format!(
                "face {i} has {} corners; only triangles are read",
                list.len()
            )));
        };
        let corner = |v: f64| {
            (v >= 0.0 && (v as usize) < positions.len() && v.fract() == 0.0)
                .then_some(v as u32)
                .ok_or_else(|| bad(format!("face {i} names vertex {v}, of {}", positions.len())))
        };
        triangles.push([corner(a)?, corner(b)?, corner(c)?]);
    }
    let unseen = match face.scalar("unseen") {
        Some(u) => u.iter().map(|&v| v != 0.0).collect(),
        None => vec![false; triangles.len()],
    };
    Ok(TriMesh {
        positions,
        colors,
        triangles,
        unseen,
    })
}
