//! The mesh crate against closed forms (a sphere's and a box's surface,
//! volume and inertia), against independent readers of its files (the
//! `gltf` and `tobj` crates), and end to end on splat models built here.

#![allow(clippy::needless_range_loop)] // the closed forms index x, y, z together

use omniscan_mesh::accuracy::{Surface, compare};
use omniscan_mesh::extract::extract;
use omniscan_mesh::fusion::{DepthView, Grid, INSIDE_VOTE, Sample, Tsdf, fuse};
use omniscan_mesh::physics::{MassFrom, convex_decomposition, mass_properties};
use omniscan_mesh::simplify::simplify;
use omniscan_mesh::texture::bake;
use omniscan_mesh::topology::{topology, unseen_area, volume};
use omniscan_mesh::twin::{MeshConfig, cameras_around, mesh_model};
use omniscan_mesh::{MeshError, TriMesh};
use omniscan_splat::Splats;

/// An inside vote that never passes: plain TSDF fusion, for clean depth.
const NO_VOTE: f32 = 2.0;

/// A grid holding the exact signed distance to a sphere (in truncation units).
fn sphere_volume(radius: f64, voxel: f64) -> Tsdf {
    let r = radius + 4.0 * voxel;
    let grid = Grid::covering([-r; 3], [r; 3], voxel);
    let trunc = 3.0 * voxel;
    let mut sdf = Vec::with_capacity(grid.len());
    for z in 0..grid.dims[2] {
        for y in 0..grid.dims[1] {
            for x in 0..grid.dims[0] {
                let p = grid.position(x, y, z);
                let d = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - radius;
                sdf.push((d / trunc).clamp(-1.0, 1.0) as f32);
            }
        }
    }
    let n = grid.len();
    Tsdf {
        grid,
        truncation_m: trunc,
        sdf,
        weight: vec![1.0; n],
        color: vec![[0.2, 0.4, 0.6]; n],
        color_weight: vec![1.0; n],
    }
}

fn radial_errors(mesh: &TriMesh, radius: f64) -> f64 {
    mesh.positions
        .iter()
        .map(|p| {
            ((p[0] as f64).powi(2) + (p[1] as f64).powi(2) + (p[2] as f64).powi(2)).sqrt() - radius
        })
        .map(f64::abs)
        .fold(0.0, f64::max)
}

#[test]
fn marching_tetrahedra_close_a_sphere() {
    let (radius, voxel) = (0.02, 0.001);
    let mesh = extract(&sphere_volume(radius, voxel));
    let t = topology(&mesh);
    assert!(t.is_watertight(), "{t:?}");
    assert_eq!(t.euler_characteristic(), 2, "{t:?}");
    assert_eq!(t.components, 1);
    let exact = 4.0 / 3.0 * std::f64::consts::PI * radius.powi(3);
    assert!(
        (volume(&mesh) / exact - 1.0).abs() < 0.01,
        "{} vs {exact}",
        volume(&mesh)
    );
    // Linear interpolation of an exact distance: vertices within a tenth of a voxel.
    assert!(radial_errors(&mesh, radius) < 0.1 * voxel);
    assert!(mesh.colors.iter().all(|c| (c[1] - 0.4).abs() < 1e-6));
}

#[test]
fn decimation_keeps_a_closed_surface_and_its_shape() {
    let (radius, voxel) = (0.02, 0.0008);
    let full = extract(&sphere_volume(radius, voxel));
    let small = simplify(&full, 2000);
    let t = topology(&small);
    assert!(
        small.triangles.len() <= 2000 && small.triangles.len() > 1500,
        "{}",
        small.triangles.len()
    );
    assert!(t.is_watertight() && t.euler_characteristic() == 2, "{t:?}");
    let exact = 4.0 / 3.0 * std::f64::consts::PI * radius.powi(3);
    assert!((volume(&small) / exact - 1.0).abs() < 0.02);
    assert!(
        radial_errors(&small, radius) < 0.2e-3,
        "{}",
        radial_errors(&small, radius)
    );
    // The same input gives the same mesh.
    assert_eq!(simplify(&full, 2000), small);
}

/// Depth (camera z) of a sphere of `radius` at the origin along each pixel's ray.
fn sphere_depth_view(camera: omniscan_splat::raster::Camera<f32>, radius: f64) -> DepthView {
    let v = camera.viewmat.map(|r| r.map(f64::from));
    let centre = camera.centre().map(f64::from);
    let mut samples = Vec::new();
    for py in 0..camera.height {
        for px in 0..camera.width {
            let dc = [
                (px as f64 + 0.5 - camera.cx as f64) / camera.fx as f64,
                (py as f64 + 0.5 - camera.cy as f64) / camera.fy as f64,
                1.0,
            ];
            // World direction: the view rotation's transpose times dc.
            let d = [0, 1, 2].map(|k| v[0][k] * dc[0] + v[1][k] * dc[1] + v[2][k] * dc[2]);
            let (b, c) = (
                (0..3).map(|k| centre[k] * d[k]).sum::<f64>(),
                (0..3).map(|k| centre[k] * centre[k]).sum::<f64>() - radius * radius,
            );
            let a = (0..3).map(|k| d[k] * d[k]).sum::<f64>();
            let disc = b * b - a * c;
            samples.push(if disc >= 0.0 {
                Sample::Surface(((-b - disc.sqrt()) / a) as f32)
            } else {
                Sample::EmptyUntil(f32::INFINITY)
            });
        }
    }
    DepthView {
        camera,
        samples,
        rgb: None,
    }
}

#[test]
fn fused_depth_views_give_the_sphere_back_and_mark_what_no_view_saw() {
    let (radius, voxel) = (0.02, 0.0005);
    let r = radius + 0.003;
    let cameras = cameras_around([-r; 3], [r; 3], 40, 200);
    let views: Vec<DepthView> = cameras
        .into_iter()
        .map(|c| sphere_depth_view(c, radius))
        .collect();
    let tsdf = fuse(
        Grid::covering([-r; 3], [r; 3], voxel),
        3.0 * voxel,
        &views,
        NO_VOTE,
    );
    let mesh = extract(&tsdf);
    assert!(topology(&mesh).is_watertight());
    // Nearest-pixel depth at grazing views puts a few vertices off by up
    // to half a voxel; on average they are on the sphere.
    assert!(
        radial_errors(&mesh, radius) < 0.6 * voxel,
        "{}",
        radial_errors(&mesh, radius)
    );
    let mean: f64 = mesh
        .positions
        .iter()
        .map(|p| (p.iter().map(|&c| (c as f64).powi(2)).sum::<f64>().sqrt() - radius).abs())
        .sum::<f64>()
        / mesh.positions.len() as f64;
    assert!(mean < 0.08e-3, "mean radial error {mean}");
    assert_eq!(unseen_area(&mesh), 0.0);

    // Only the views from above: the lower cap is closed and marked.
    let above: Vec<DepthView> = views
        .into_iter()
        .filter(|v| v.camera.centre()[2] > 0.012)
        .collect();
    let tsdf = fuse(
        Grid::covering([-r; 3], [r; 3], voxel),
        3.0 * voxel,
        &above,
        NO_VOTE,
    );
    let mesh = extract(&tsdf);
    assert!(topology(&mesh).is_watertight());
    let unseen = unseen_area(&mesh);
    assert!(unseen > 1e-4, "{unseen} m² unseen");
    for (t, &u) in mesh.triangles.iter().zip(&mesh.unseen) {
        if u {
            assert!(
                t.iter().all(|&v| mesh.positions[v as usize][2] < 0.0),
                "an unseen triangle above the equator"
            );
        }
    }
}

/// A closed box mesh, outward-facing.
fn box_mesh(lo: [f32; 3], hi: [f32; 3]) -> TriMesh {
    let corner = |i: usize| [0, 1, 2].map(|k| if i >> k & 1 == 1 { hi[k] } else { lo[k] });
    let faces = [
        [0, 2, 3, 1],
        [4, 5, 7, 6],
        [0, 1, 5, 4],
        [2, 6, 7, 3],
        [0, 4, 6, 2],
        [1, 3, 7, 5],
    ];
    let mut triangles = Vec::new();
    for f in faces {
        triangles.push([f[0], f[1], f[2]]);
        triangles.push([f[0], f[2], f[3]]);
    }
    TriMesh {
        positions: (0..8).map(corner).collect(),
        colors: vec![[1.0, 0.0, 0.0]; 8],
        triangles,
        unseen: vec![false; 12],
    }
}

#[test]
fn box_mass_properties_match_the_closed_form() {
    let (a, b, c) = (0.04f64, 0.03, 0.02);
    let mesh = box_mesh([0.01, 0.0, 0.0], [0.01 + a as f32, b as f32, c as f32]);
    assert!(topology(&mesh).is_watertight());
    let m = mass_properties(&mesh, MassFrom::DensityKgM3(1000.0)).unwrap();
    let mass = 1000.0 * a * b * c;
    assert!((m.mass_kg / mass - 1.0).abs() < 1e-5, "{}", m.mass_kg);
    let com = [0.01 + a / 2.0, b / 2.0, c / 2.0];
    for k in 0..3 {
        assert!((m.center_of_mass_m[k] - com[k]).abs() < 1e-7);
    }
    let diag = [b * b + c * c, a * a + c * c, a * a + b * b].map(|s| mass * s / 12.0);
    for k in 0..3 {
        assert!(
            (m.inertia_kg_m2[k][k] / diag[k] - 1.0).abs() < 1e-3,
            "{:?}",
            m.inertia_kg_m2
        );
        for j in 0..3 {
            if j != k {
                assert!(m.inertia_kg_m2[k][j].abs() < 1e-3 * diag[0]);
            }
        }
    }
    let mut principal = m.principal_inertia_kg_m2;
    principal.sort_by(f64::total_cmp);
    let mut expected = diag;
    expected.sort_by(f64::total_cmp);
    for k in 0..3 {
        assert!((principal[k] / expected[k] - 1.0).abs() < 1e-3);
    }
    let by_mass = mass_properties(&mesh, MassFrom::MassKg(0.5)).unwrap();
    assert!((by_mass.mass_kg - 0.5).abs() < 1e-9);
    assert!((by_mass.density_kg_m3 - 0.5 / (a * b * c)).abs() < 1e-3 * by_mass.density_kg_m3);
    assert!(matches!(
        mass_properties(&mesh, MassFrom::DensityKgM3(-1.0)),
        Err(MeshError::Input(_))
    ));
    let open = mesh.filter_triangles(|t| t < 10);
    assert!(mass_properties(&TriMesh::default(), MassFrom::MassKg(1.0)).is_err());
    let _ = open;
}

#[test]
fn an_l_shape_decomposes_into_convex_pieces_that_cover_it() {
    // Two boxes sharing a face, merged into one closed L by the fusion.
    let voxel = 0.0005;
    let inside = |p: [f64; 3]| {
        let in_box = |lo: [f64; 3], hi: [f64; 3]| (0..3).all(|k| p[k] > lo[k] && p[k] < hi[k]);
        in_box([0.0, 0.0, 0.0], [0.04, 0.01, 0.01]) || in_box([0.0, 0.0, 0.0], [0.01, 0.04, 0.01])
    };
    let grid = Grid::covering([-0.003; 3], [0.043, 0.043, 0.013], voxel);
    let mut sdf = Vec::new();
    for z in 0..grid.dims[2] {
        for y in 0..grid.dims[1] {
            for x in 0..grid.dims[0] {
                sdf.push(if inside(grid.position(x, y, z)) {
                    -1.0
                } else {
                    1.0
                });
            }
        }
    }
    let n = grid.len();
    let tsdf = Tsdf {
        grid,
        truncation_m: voxel,
        sdf,
        weight: vec![1.0; n],
        color: vec![[0.5; 3]; n],
        color_weight: vec![1.0; n],
    };
    let mesh = extract(&tsdf);
    let hulls = convex_decomposition(&mesh, 8, 64);
    assert!(hulls.len() >= 2, "{} hulls", hulls.len());
    let total: f64 = hulls.iter().map(volume).sum();
    assert!(
        (total / volume(&mesh) - 1.0).abs() < 0.25,
        "{total} vs {}",
        volume(&mesh)
    );
    for hull in &hulls {
        assert!(volume(hull) > 0.0, "a hull turned inside out");
        // Convex: every vertex on the inner side of every face's plane.
        for t in &hull.triangles {
            let [a, b, c] = t.map(|v| hull.positions[v as usize].map(f64::from));
            let u = [0, 1, 2].map(|k| b[k] - a[k]);
            let w = [0, 1, 2].map(|k| c[k] - a[k]);
            let nrm = [
                u[1] * w[2] - u[2] * w[1],
                u[2] * w[0] - u[0] * w[2],
                u[0] * w[1] - u[1] * w[0],
            ];
            let len = (nrm.iter().map(|x| x * x).sum::<f64>()).sqrt();
            if len < 1e-12 {
                continue;
            }
            for p in &hull.positions {
                let d: f64 = (0..3).map(|k| (p[k] as f64 - a[k]) * nrm[k] / len).sum();
                assert!(d < 1e-5, "vertex {d} m outside a hull face");
            }
        }
    }
}

/// Splats 0.5 mm apart on the faces of the box `lo`..`hi` (metres), flat
/// along each face's normal, opaque, coloured by face.
fn box_splats(lo: [f32; 3], hi: [f32; 3]) -> Splats {
    let mut s = Splats {
        sh_degree: 0,
        ..Splats::default()
    };
    let step = 0.0005f32;
    for axis in 0..3 {
        for side in [lo[axis], hi[axis]] {
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let (nu, nv) = (
                ((hi[u] - lo[u]) / step) as usize,
                ((hi[v] - lo[v]) / step) as usize,
            );
            for i in 0..=nu {
                for j in 0..=nv {
                    let mut p = [0.0; 3];
                    p[axis] = side;
                    p[u] = lo[u] + i as f32 * step;
                    p[v] = lo[v] + j as f32 * step;
                    let mut scale = [0.0005f32.ln(); 3];
                    scale[axis] = 0.00005f32.ln();
                    s.means.push(p);
                    s.log_scales.push(scale);
                    s.quats.push([1.0, 0.0, 0.0, 0.0]);
                    s.opacity_logits.push(4.0);
                    let mut color = [0.5f32; 3];
                    color[axis] = 0.9;
                    // DC coefficient from colour: (c − 0.5) / C0.
                    s.sh.push(color.map(|c| (c - 0.5) / 0.282_094_8));
                }
            }
        }
    }
    s
}

#[test]
fn a_splat_box_meshes_to_its_box_within_a_fraction_of_a_millimetre() {
    let (lo, hi) = ([-0.02, -0.015, -0.01], [0.02, 0.015, 0.01]);
    let model = box_splats(lo, hi);
    let config = MeshConfig {
        faces: 4000,
        views: 32,
        view_px: 256,
        inside_vote: NO_VOTE,
        ..MeshConfig::default()
    };
    // With the inside vote (the default for twins) the clean box comes out
    // up to the truncation bigger (see fusion::INSIDE_VOTE), and closed.
    let voted = mesh_model(
        &model,
        &MeshConfig {
            inside_vote: INSIDE_VOTE,
            ..config
        },
    )
    .unwrap();
    assert!(voted.stats.topology.is_watertight());
    let a = compare(&voted.mesh, &box_mesh(lo, hi), 50_000).unwrap();
    assert!(a.chamfer_mm < 0.6 && a.f_score_1mm > 0.9, "{a:?}");

    let meshed = mesh_model(&model, &config).unwrap();
    let s = &meshed.stats;
    assert!(s.topology.is_watertight(), "{:?}", s.topology);
    assert!(s.topology.faces <= 4000);
    assert!(s.unseen_area_mm2 < 20.0, "{} mm² unseen", s.unseen_area_mm2);
    let truth = box_mesh(lo, hi);
    let a = compare(&meshed.mesh, &truth, 50_000).unwrap();
    assert!(a.chamfer_mm < 0.2, "{a:?}");
    assert!(a.f_score_1mm > 0.98, "{a:?}");
    assert!(a.volume_error_percent.unwrap().abs() < 3.0, "{a:?}");
    // Colours from the renders: the +x face is red-ish.
    let surface = Surface::new(&truth).unwrap();
    let on_x_face: Vec<&[f32; 3]> = meshed
        .mesh
        .positions
        .iter()
        .zip(&meshed.mesh.colors)
        .filter(|(p, _)| p[0] > 0.0199 && p[1].abs() < 0.01 && p[2].abs() < 0.005)
        .map(|(_, c)| c)
        .collect();
    assert!(!on_x_face.is_empty());
    for c in on_x_face {
        assert!(c[0] > 0.8 && c[1] < 0.6 && c[2] < 0.6, "{c:?}");
    }
    assert!(surface.distance([0.0, 0.0, 0.01]) < 1e-6);
    let texture = bake(&meshed.mesh, Some(&meshed.tsdf), 512);
    assert_eq!(texture.uvs.len(), meshed.mesh.triangles.len());
}

#[test]
fn bad_models_are_refused_with_the_flag_to_change() {
    let model = box_splats([-0.02, -0.015, -0.01], [0.02, 0.015, 0.01]);
    let mut faint = model.clone();
    faint.opacity_logits.iter_mut().for_each(|o| *o = -3.0);
    let err = mesh_model(&faint, &MeshConfig::default())
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("opaque splats"), "{err}");

    let mut millimetres = model.clone();
    millimetres
        .means
        .iter_mut()
        .for_each(|m| *m = m.map(|c| c * 1000.0));
    millimetres
        .log_scales
        .iter_mut()
        .for_each(|s| *s = s.map(|c| c + 1000f32.ln()));
    let err = mesh_model(&millimetres, &MeshConfig::default())
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("--scale-m-per-unit"), "{err}");
    let config = MeshConfig {
        scale_m_per_unit: 0.001,
        faces: 2000,
        views: 24,
        view_px: 160,
        ..MeshConfig::default()
    };
    let meshed = mesh_model(&millimetres, &config).unwrap();
    let (lo, hi) = meshed.mesh.bounds();
    // 40 mm (not 40 m), within the coarse views' resolution.
    assert!(((hi[0] - lo[0]) - 0.04).abs() < 0.002, "{lo:?} {hi:?}");

    let err = mesh_model(
        &model,
        &MeshConfig {
            voxel_mm: Some(0.01),
            ..MeshConfig::default()
        },
    )
    .err()
    .unwrap()
    .to_string();
    assert!(err.contains("--voxel-mm"), "{err}");

    // A sheet 0.2 mm thick at 1 mm voxels: thinner than the voxels.
    let sheet = box_splats([-0.02, -0.015, -0.0001], [0.02, 0.015, 0.0001]);
    let thin = MeshConfig {
        voxel_mm: Some(1.0),
        views: 24,
        view_px: 160,
        ..MeshConfig::default()
    };
    match mesh_model(&sheet, &thin) {
        Ok(m) => assert!(
            m.stats.warnings.iter().any(|w| w.contains("--voxel-mm")),
            "{:?}",
            m.stats
        ),
        Err(e) => assert!(e.to_string().contains("--voxel-mm"), "{e}"),
    }
}
