//! Mesh files: OBJ (+MTL + texture, through `tobj`), STL (binary and ASCII),
//! PLY (through omniscan-core's reader) and COLLADA (`.dae`, through
//! `mesh-loader`, which robot descriptions use; its nodes' transforms and
//! `<unit>` applied, `up_axis` not, as ROS's viewers do). Units are
//! whatever the file uses; the caller scales to metres.

use std::path::Path;
use std::sync::Arc;

use nalgebra::{Point3, Vector3};

use crate::SceneError;
use crate::mesh::{Material, Mesh, Texture};

/// Loads a mesh by extension (`.obj`, `.stl`, `.ply`).
pub fn load_mesh(path: &Path) -> Result<Mesh, SceneError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let mesh = match ext.as_str() {
        "obj" => load_obj(path)?,
        "stl" => load_stl(path)?,
        "ply" => load_ply(path)?,
        "dae" => load_collada(path)?,
        _ => {
            return Err(SceneError::mesh(
                path,
                "unsupported mesh format: use .obj (with .mtl and texture), .stl, .ply or .dae",
            ));
        }
    };
    check(path, mesh)
}

fn check(path: &Path, mut mesh: Mesh) -> Result<Mesh, SceneError> {
    if mesh.triangles.is_empty() {
        return Err(SceneError::mesh(path, "mesh has no triangles"));
    }
    let n = mesh.positions.len() as u32;
    if let Some(t) = mesh.triangles.iter().find(|t| t.iter().any(|&i| i >= n)) {
        return Err(SceneError::mesh(
            path,
            format!("triangle {t:?} refers to a vertex beyond the {n} vertices"),
        ));
    }
    if mesh
        .positions
        .iter()
        .any(|p| !p.coords.iter().all(|c| c.is_finite()))
    {
        return Err(SceneError::mesh(
            path,
            "mesh has a vertex with a NaN or infinite coordinate",
        ));
    }
    if mesh.normals.len() != mesh.positions.len()
        || mesh
            .normals
            .iter()
            .any(|n| !n.iter().all(|c| c.is_finite()) || n.norm() < 1e-6)
    {
        mesh.compute_normals();
    }
    if mesh.triangle_materials.len() != mesh.triangles.len() {
        mesh.triangle_materials = vec![0; mesh.triangles.len()];
    }
    if mesh.materials.is_empty() {
        mesh.materials.push(Material::color([0.7, 0.7, 0.7]));
    }
    Ok(mesh)
}

fn load_obj(path: &Path) -> Result<Mesh, SceneError> {
    let options = tobj::LoadOptions {
        single_index: true,
        triangulate: true,
        ignore_points: true,
        ignore_lines: true,
    };
    let (models, materials) = tobj::load_obj(path, &options)
        .map_err(|e| SceneError::mesh(path, format!("cannot read OBJ: {e}")))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut out = Mesh::default();
    let obj_materials = match materials {
        Ok(m) => m,
        Err(e) => {
            tracing::warn!(
                "{}: material library not loaded ({e}); using grey",
                path.display()
            );
            Vec::new()
        }
    };
    for m in &obj_materials {
        let albedo = m.diffuse.unwrap_or([0.8, 0.8, 0.8]);
        let texture = match &m.diffuse_texture {
            Some(name) => {
                let tex_path = dir.join(name.trim());
                let img = omniscan_core::image_io::read_rgb(&tex_path)
                    .map_err(|e| SceneError::mesh(path, format!("texture: {e}")))?;
                Some(Arc::new(Texture::from_rgb8(
                    img.width, img.height, &img.data,
                )))
            }
            None => None,
        };
        out.materials.push(Material {
            albedo,
            texture,
            specular: 0.12,
            shininess: 20.0,
        });
    }
    if out.materials.is_empty() {
        out.materials.push(Material::color([0.7, 0.7, 0.7]));
    }
    let mut any_uv = false;
    let mut all_uv = true;
    for model in &models {
        let m = &model.mesh;
        let base = out.positions.len() as u32;
        let count = m.positions.len() / 3;
        out.positions.extend(
            m.positions
                .chunks_exact(3)
                .map(|p| Point3::new(p[0], p[1], p[2])),
        );
        if m.normals.len() == m.positions.len() {
            out.normals.extend(
                m.normals
                    .chunks_exact(3)
                    .map(|n| Vector3::new(n[0], n[1], n[2])),
            );
        } else {
            out.normals
                .extend(std::iter::repeat_n(Vector3::zeros(), count));
        }
        if m.texcoords.len() / 2 == count && count > 0 {
            any_uv = true;
            out.uvs
                .extend(m.texcoords.chunks_exact(2).map(|t| [t[0], t[1]]));
        } else {
            all_uv = false;
            out.uvs.extend(std::iter::repeat_n([0.0, 0.0], count));
        }
        let material = m.material_id.unwrap_or(0).min(out.materials.len() - 1) as u16;
        for t in m.indices.chunks_exact(3) {
            out.triangles.push([t[0] + base, t[1] + base, t[2] + base]);
            out.triangle_materials.push(material);
        }
    }
    if !any_uv {
        out.uvs.clear();
    } else if !all_uv {
        tracing::warn!("{}: some parts have no texture coordinates", path.display());
    }
    Ok(out)
}

fn load_collada(path: &Path) -> Result<Mesh, SceneError> {
    let bytes =
        std::fs::read(path).map_err(|e| SceneError::Core(omniscan_core::CoreError::io(path, e)))?;
    check_collada_units(path, &bytes)?;
    let scene = mesh_loader::Loader::default()
        .merge_meshes(true)
        .load_collada_from_slice(&bytes, path)
        .map_err(|e| SceneError::mesh(path, format!("not a readable COLLADA file: {e}")))?;
    let mut mesh = Mesh::default();
    for part in &scene.meshes {
        let base = mesh.positions.len() as u32;
        mesh.positions
            .extend(part.vertices.iter().map(|&[x, y, z]| Point3::new(x, y, z)));
        mesh.triangles
            .extend(part.faces.iter().map(|f| f.map(|i| i + base)));
    }
    Ok(mesh)
}

/// `mesh-loader` (0.1.13) scales a COLLADA file's vertices by its `<unit>`
/// but not its nodes' translations: a file in millimetres whose parts are
/// moved by their nodes would come out with the parts misplaced, so it is
/// refused here rather than drawn wrong.
fn check_collada_units(path: &Path, bytes: &[u8]) -> Result<(), SceneError> {
    let text = std::str::from_utf8(bytes)
        .map_err(|e| SceneError::mesh(path, format!("not a readable COLLADA file: {e}")))?;
    let doc = roxmltree::Document::parse(text)
        .map_err(|e| SceneError::mesh(path, format!("not a readable COLLADA file: {e}")))?;
    let unit: f64 = doc
        .descendants()
        .find(|n| n.has_tag_name("unit"))
        .and_then(|n| n.attribute("meter"))
        .and_then(|m| m.trim().replace(',', ".").parse().ok())
        .unwrap_or(1.0);
    let moves = |n: &roxmltree::Node| {
        let values: Vec<f64> = n
            .text()
            .unwrap_or("")
            .split_whitespace()
            .filter_map(|v| v.parse().ok())
            .collect();
        match n.tag_name().name() {
            "translate" => values.iter().any(|v| *v != 0.0),
            "matrix" => [3, 7, 11]
                .iter()
                .any(|&i| values.get(i).is_some_and(|v| *v != 0.0)),
            _ => false,
        }
    };
    if unit != 1.0 && doc.descendants().any(|n| moves(&n)) {
        return Err(SceneError::mesh(
            path,
            format!(
                "a COLLADA file in units of {unit} m whose nodes move its parts is not read correctly yet; export it in metres, or as STL"
            ),
        ));
    }
    Ok(())
}

fn load_stl(path: &Path) -> Result<Mesh, SceneError> {
    let bytes = std::fs::read(path).map_err(|e| SceneError::mesh(path, e.to_string()))?;
    let looks_ascii =
        bytes.starts_with(b"solid") && bytes.iter().take(1024).any(|&b| b == b'\n') && {
            let head = String::from_utf8_lossy(&bytes[..bytes.len().min(1024)]);
            head.contains("facet")
        };
    let mut mesh = Mesh::default();
    if looks_ascii {
        let text = std::str::from_utf8(&bytes)
            .map_err(|_| SceneError::mesh(path, "ASCII STL is not text"))?;
        let mut corner = Vec::with_capacity(3);
        for (line_no, line) in text.lines().enumerate() {
            let mut words = line.split_whitespace();
            if words.next() == Some("vertex") {
                let v: Vec<f32> = words
                    .map(|w| w.parse::<f32>())
                    .collect::<Result<_, _>>()
                    .map_err(|_| {
                        SceneError::mesh(
                            path,
                            format!("line {}: bad vertex `{}`", line_no + 1, line.trim()),
                        )
                    })?;
                if v.len() != 3 {
                    return Err(SceneError::mesh(
                        path,
                        format!("line {}: a vertex needs 3 numbers", line_no + 1),
                    ));
                }
                corner.push(Point3::new(v[0], v[1], v[2]));
                if corner.len() == 3 {
                    push_facet(&mut mesh, &corner);
                    corner.clear();
                }
            }
        }
    } else {
        if bytes.len() < 84 {
            return Err(SceneError::mesh(
                path,
                "binary STL is shorter than its 84-byte header",
            ));
        }
        let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as usize;
        let need = 84 + n * 50;
        if bytes.len() < need {
            return Err(SceneError::mesh(
                path,
                format!(
                    "binary STL is truncated: {n} triangles need {need} bytes, file has {}",
                    bytes.len()
                ),
            ));
        }
        let f = |o: usize| f32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
        for t in 0..n {
            let o = 84 + t * 50 + 12;
            let corner: Vec<Point3<f32>> = (0..3)
                .map(|k| Point3::new(f(o + 12 * k), f(o + 12 * k + 4), f(o + 12 * k + 8)))
                .collect();
            push_facet(&mut mesh, &corner);
        }
    }
    weld(&mut mesh);
    Ok(mesh)
}

fn push_facet(mesh: &mut Mesh, corner: &[Point3<f32>]) {
    let base = mesh.positions.len() as u32;
    mesh.positions.extend_from_slice(corner);
    mesh.triangles.push([base, base + 1, base + 2]);
    mesh.triangle_materials.push(0);
}

/// Merges vertices at identical positions so smooth normals can be computed.
fn weld(mesh: &mut Mesh) {
    let mut index = std::collections::HashMap::new();
    let mut positions = Vec::new();
    let remap: Vec<u32> = mesh
        .positions
        .iter()
        .map(|p| {
            *index
                .entry([p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
                .or_insert_with(|| {
                    positions.push(*p);
                    (positions.len() - 1) as u32
                })
        })
        .collect();
    mesh.positions = positions;
    for t in &mut mesh.triangles {
        *t = t.map(|i| remap[i as usize]);
    }
    mesh.normals.clear();
}

fn load_ply(path: &Path) -> Result<Mesh, SceneError> {
    let ply = omniscan_core::ply::read(path).map_err(|e| SceneError::mesh(path, e.to_string()))?;
    let vertex = ply
        .element("vertex")
        .ok_or_else(|| SceneError::mesh(path, "PLY has no `vertex` element"))?;
    let col = |name: &str| vertex.scalar(name);
    let (Some(x), Some(y), Some(z)) = (col("x"), col("y"), col("z")) else {
        return Err(SceneError::mesh(
            path,
            "PLY vertices need x, y and z properties",
        ));
    };
    let mut mesh = Mesh {
        positions: (0..vertex.count)
            .map(|i| Point3::new(x[i] as f32, y[i] as f32, z[i] as f32))
            .collect(),
        ..Default::default()
    };
    if let (Some(nx), Some(ny), Some(nz)) = (col("nx"), col("ny"), col("nz")) {
        mesh.normals = (0..vertex.count)
            .map(|i| Vector3::new(nx[i] as f32, ny[i] as f32, nz[i] as f32))
            .collect();
    }
    let uv = [("u", "v"), ("s", "t"), ("texture_u", "texture_v")]
        .iter()
        .find_map(|(a, b)| Some((col(a)?, col(b)?)));
    if let Some((u, v)) = uv {
        mesh.uvs = (0..vertex.count)
            .map(|i| [u[i] as f32, v[i] as f32])
            .collect();
    }
    let face = ply.element("face").ok_or_else(|| {
        SceneError::mesh(
            path,
            "PLY has no `face` element: a point cloud is not a mesh",
        )
    })?;
    let lists = face
        .list("vertex_indices")
        .or_else(|| face.list("vertex_index"))
        .ok_or_else(|| SceneError::mesh(path, "PLY faces need a `vertex_indices` list"))?;
    for f in lists {
        for k in 1..f.len().saturating_sub(1) {
            mesh.triangles
                .push([f[0] as u32, f[k] as u32, f[k + 1] as u32]);
        }
    }
    mesh.triangle_materials = vec![0; mesh.triangles.len()];
    let color = match (col("red"), col("green"), col("blue")) {
        (Some(r), Some(g), Some(b)) => {
            // Per-vertex colours become an average colour (the simulator's
            // materials are per triangle); a textured PLY keeps its UVs.
            let n = vertex.count.max(1) as f64;
            let scale = if r.iter().chain(g).chain(b).any(|&v| v > 1.0) {
                255.0
            } else {
                1.0
            };
            [r, g, b].map(|c| (c.iter().sum::<f64>() / n / scale) as f32)
        }
        _ => [0.7, 0.7, 0.7],
    };
    mesh.materials.push(Material::color(color));
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A COLLADA triangle placed by a node (translated, turned 90° about
    /// z) comes out where the closed form puts it; in millimetres
    /// (`<unit meter="0.001">`) it is scaled, and refused where its node
    /// would move it (see `check_collada_units`).
    #[test]
    fn collada_nodes_and_units_apply() {
        let dir = tempfile::tempdir().unwrap();
        let dae = |unit: &str, translate: &str| {
            format!(
                r##"<?xml version="1.0" encoding="utf-8"?>
<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">
  <asset><unit meter="{unit}"/><up_axis>Z_UP</up_axis></asset>
  <library_geometries>
    <geometry id="tri"><mesh>
      <source id="tri-pos"><float_array id="tri-pos-array" count="9">0 0 0 20 0 0 0 30 0</float_array>
        <technique_common><accessor source="#tri-pos-array" count="3" stride="3">
          <param name="X" type="float"/><param name="Y" type="float"/><param name="Z" type="float"/>
        </accessor></technique_common></source>
      <vertices id="tri-vtx"><input semantic="POSITION" source="#tri-pos"/></vertices>
      <triangles count="1"><input semantic="VERTEX" source="#tri-vtx" offset="0"/><p>0 1 2</p></triangles>
    </mesh></geometry>
  </library_geometries>
  <library_visual_scenes><visual_scene id="scene">
    <node id="n"><translate>{translate}</translate><rotate>0 0 1 90</rotate><instance_geometry url="#tri"/></node>
  </visual_scene></library_visual_scenes>
  <scene><instance_visual_scene url="#scene"/></scene>
</COLLADA>"##
            )
        };
        let path = dir.path().join("tri.dae");
        let check = |m: &Mesh, want: [[f32; 2]; 3]| {
            assert_eq!(m.triangles.len(), 1);
            for (p, w) in m.positions.iter().zip(want) {
                assert!(
                    (p.x - w[0]).abs() < 1e-5 && (p.y - w[1]).abs() < 1e-5 && p.z.abs() < 1e-6,
                    "{p:?} vs {w:?}"
                );
            }
        };
        // Metres: (x, y) -> (10 - y, x).
        std::fs::write(&path, dae("1", "10 0 0")).unwrap();
        check(
            &load_mesh(&path).unwrap(),
            [[10.0, 0.0], [10.0, 20.0], [-20.0, 0.0]],
        );
        // Millimetres, turned in place: (x, y) -> (-y, x) / 1000.
        std::fs::write(&path, dae("0.001", "0 0 0")).unwrap();
        check(
            &load_mesh(&path).unwrap(),
            [[0.0, 0.0], [0.0, 0.020], [-0.030, 0.0]],
        );
        std::fs::write(&path, dae("0.001", "10 0 0")).unwrap();
        let e = load_mesh(&path).unwrap_err().to_string();
        assert!(
            e.contains("tri.dae") && e.contains("units of 0.001 m"),
            "{e}"
        );
        std::fs::write(&path, "<COLLADA><library_geometries>").unwrap();
        let e = load_mesh(&path).unwrap_err().to_string();
        assert!(
            e.contains("tri.dae") && e.contains("not a readable COLLADA file"),
            "{e}"
        );
    }

    #[test]
    fn stl_binary_ascii_and_errors() {
        let dir = tempfile::tempdir().unwrap();
        let ascii = "solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid t\n";
        std::fs::write(dir.path().join("a.stl"), ascii).unwrap();
        let m = load_mesh(&dir.path().join("a.stl")).unwrap();
        assert_eq!(m.triangles.len(), 1);
        let mut bin = vec![0u8; 80];
        bin.extend(1u32.to_le_bytes());
        for v in [
            0.0f32, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0,
        ] {
            bin.extend(v.to_le_bytes());
        }
        bin.extend([0, 0]);
        std::fs::write(dir.path().join("b.stl"), &bin).unwrap();
        let m = load_mesh(&dir.path().join("b.stl")).unwrap();
        assert_eq!(m.triangles.len(), 1);
        assert!((m.normals[0].z - 1.0).abs() < 1e-6);
        std::fs::write(dir.path().join("c.stl"), &bin[..100]).unwrap();
        let err = load_mesh(&dir.path().join("c.stl"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("c.stl") && err.contains("truncated"), "{err}");
        std::fs::write(dir.path().join("d.xyz"), "1 2 3").unwrap();
        assert!(load_mesh(&dir.path().join("d.xyz")).is_err());
    }

    #[test]
    fn obj_with_texture_and_ply() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("m.mtl"),
            "newmtl a\nKd 1 1 1\nmap_Kd tex.png\n",
        )
        .unwrap();
        let tex = omniscan_core::image_io::RgbImage {
            width: 2,
            height: 2,
            data: vec![255, 0, 0, 0, 255, 0, 0, 0, 255, 255, 255, 255],
        };
        omniscan_core::image_io::write_rgb(&dir.path().join("tex.png"), &tex).unwrap();
        std::fs::write(
            dir.path().join("m.obj"),
            "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl a\nf 1/1 2/2 3/3\n",
        )
        .unwrap();
        let m = load_mesh(&dir.path().join("m.obj")).unwrap();
        assert_eq!(m.triangles.len(), 1);
        assert_eq!(m.uvs.len(), 3);
        assert!(m.materials[0].texture.is_some());
        std::fs::write(
            dir.path().join("bad.obj"),
            "mtllib m.mtl\nv 0 0 0\nf 1 2 3\n",
        )
        .unwrap();
        assert!(load_mesh(&dir.path().join("bad.obj")).is_err());
        let ply = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n";
        std::fs::write(dir.path().join("q.ply"), ply).unwrap();
        let m = load_mesh(&dir.path().join("q.ply")).unwrap();
        assert_eq!(m.triangles.len(), 2);
    }
}
