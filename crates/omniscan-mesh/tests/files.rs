//! The mesh files read back by independent readers: `gltf` for the GLB,
//! `tobj` for the OBJ and its material, our PLY reader for the PLY.

use omniscan_mesh::TriMesh;
use omniscan_mesh::files::{read_ply_mesh, write_all};
use omniscan_mesh::texture::bake;
use omniscan_mesh::topology::topology;

/// An octahedron with a colour per vertex.
fn octahedron() -> TriMesh {
    let positions = vec![
        [0.01, 0.0, 0.0],
        [-0.01, 0.0, 0.0],
        [0.0, 0.01, 0.0],
        [0.0, -0.01, 0.0],
        [0.0, 0.0, 0.01],
        [0.0, 0.0, -0.01],
    ];
    let triangles = vec![
        [0, 2, 4],
        [2, 1, 4],
        [1, 3, 4],
        [3, 0, 4],
        [2, 0, 5],
        [1, 2, 5],
        [3, 1, 5],
        [0, 3, 5],
    ];
    TriMesh {
        colors: (0..6)
            .map(|i| [i as f32 / 5.0, 0.5, 1.0 - i as f32 / 5.0])
            .collect(),
        positions,
        unseen: (0..8).map(|t| t >= 6).collect(),
        triangles,
    }
}

#[test]
fn the_files_read_back_in_other_readers() {
    let mesh = octahedron();
    assert!(topology(&mesh).is_watertight());
    let texture = bake(&mesh, None, 64);
    let dir = tempfile::tempdir().unwrap();
    let files = write_all(dir.path(), "octa", &mesh, &texture).unwrap();

    // PLY: positions, colours (8-bit) and the unseen flags back.
    let back = read_ply_mesh(&files.ply).unwrap();
    assert_eq!(back.positions, mesh.positions);
    assert_eq!(back.triangles, mesh.triangles);
    assert_eq!(back.unseen, mesh.unseen);
    for (a, b) in back.colors.iter().zip(&mesh.colors) {
        assert!((0..3).all(|k| (a[k] - b[k]).abs() <= 0.5 / 255.0 + 1e-6));
    }

    // OBJ through tobj: same triangles (as positions), the texture named.
    let (models, materials) = tobj::load_obj(
        &files.obj,
        &tobj::LoadOptions {
            triangulate: true,
            single_index: false,
            ..Default::default()
        },
    )
    .unwrap();
    let m = &models[0].mesh;
    assert_eq!(m.indices.len(), 24);
    let corners = mesh.triangles.iter().flatten();
    for (&index, &v) in m.indices.iter().zip(corners) {
        let index = index as usize;
        let p = &m.positions[3 * index..3 * index + 3];
        assert_eq!(p, &mesh.positions[v as usize][..]);
    }
    assert_eq!(m.texcoord_indices.len(), 24);
    let materials = materials.unwrap();
    assert_eq!(materials[0].diffuse_texture.as_deref(), Some("octa.png"));

    // GLB through gltf: the half turn about z, a UV per corner, the
    // texture decodes to the baked one.
    let (doc, buffers, images) = gltf::import(&files.glb).unwrap();
    let primitive = doc.meshes().next().unwrap().primitives().next().unwrap();
    let reader = primitive.reader(|b| Some(&buffers[b.index()]));
    let positions: Vec<[f32; 3]> = reader.read_positions().unwrap().collect();
    assert_eq!(positions.len(), 24);
    let corners = mesh.triangles.iter().flatten();
    for (q, &v) in positions.iter().zip(corners) {
        let p = mesh.positions[v as usize];
        assert_eq!(*q, [-p[0], -p[1], p[2]]);
    }
    let uvs: Vec<[f32; 2]> = reader.read_tex_coords(0).unwrap().into_f32().collect();
    assert_eq!(
        uvs,
        texture.uvs.iter().flatten().copied().collect::<Vec<_>>()
    );
    assert_eq!(images[0].pixels, texture.rgb);

    // The texture at each triangle's UV centroid is the vertex colours' mean.
    for (t, uv) in mesh.triangles.iter().zip(&texture.uvs) {
        let c = [0, 1].map(|k| (uv[0][k] + uv[1][k] + uv[2][k]) / 3.0);
        let (x, y) = (
            (c[0] * texture.width as f32) as u32,
            (c[1] * texture.height as f32) as u32,
        );
        let texel = &texture.rgb[((y * texture.width + x) * 3) as usize..][..3];
        for k in 0..3 {
            let mean: f32 = t.iter().map(|&v| mesh.colors[v as usize][k]).sum::<f32>() / 3.0;
            assert!(
                (texel[k] as f32 / 255.0 - mean).abs() < 0.08,
                "{texel:?} vs {mean}"
            );
        }
    }
}

#[test]
fn bad_ply_meshes_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("quad.ply");
    std::fs::write(
        &path,
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n",
    )
    .unwrap();
    let err = read_ply_mesh(&path).unwrap_err().to_string();
    assert!(
        err.contains("quad.ply") && err.contains("4 corners"),
        "{err}"
    );
    std::fs::write(
        &path,
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n3 0 1 7\n",
    )
    .unwrap();
    let err = read_ply_mesh(&path).unwrap_err().to_string();
    assert!(err.contains("vertex 7"), "{err}");
}
