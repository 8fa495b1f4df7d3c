//! What a simulator needs besides the looks: collision geometry by
//! approximate convex decomposition (parry3d's V-HACD, Mamou and Ghorbel
//! 2009), mass properties of the closed mesh (parry3d's
//! `MassProperties::from_trimesh`), and the asset files, URDF and MuJoCo's
//! MJCF, with visual and collision meshes in metres.

use std::fmt::Write;
use std::path::Path;

use nalgebra::{Matrix3, Rotation3, UnitQuaternion};
use parry3d::math::Vector;
use parry3d::transformation::vhacd::{VHACD, VHACDParameters};
use serde::{Deserialize, Serialize};

use crate::{MeshError, TriMesh};

/// Convex pieces whose union approximates `mesh`, at most `max_hulls`,
/// from a voxelisation `resolution` cells across.
pub fn convex_decomposition(mesh: &TriMesh, max_hulls: u32, resolution: u32) -> Vec<TriMesh> {
    let points: Vec<Vector> = mesh
        .positions
        .iter()
        .map(|p| Vector::new(p[0], p[1], p[2]))
        .collect();
    let params = VHACDParameters {
        resolution,
        max_convex_hulls: max_hulls.max(1),
        ..VHACDParameters::default()
    };
    let decomposition = VHACD::decompose(&params, &points, &mesh.triangles, false);
    decomposition
        .compute_convex_hulls(4)
        .into_iter()
        .filter(|(vertices, indices)| vertices.len() >= 4 && indices.len() >= 4)
        .map(|(vertices, indices)| TriMesh {
            colors: vec![[0.6; 3]; vertices.len()],
            positions: vertices.iter().map(|v| [v.x, v.y, v.z]).collect(),
            unseen: vec![false; indices.len()],
            triangles: indices,
        })
        .collect()
}

/// Mass, centre of mass and inertia of a body, SI units, in the mesh's frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MassProperties {
    pub mass_kg: f64,
    pub density_kg_m3: f64,
    pub volume_m3: f64,
    pub center_of_mass_m: [f64; 3],
    /// The inertia tensor about the centre of mass, axes of the mesh frame, kg·m².
    pub inertia_kg_m2: [[f64; 3]; 3],
    /// Its eigenvalues, kg·m².
    pub principal_inertia_kg_m2: [f64; 3],
    /// The rotation from the principal axes to the mesh frame (w, x, y, z).
    pub principal_axes_quat_wxyz: [f64; 4],
}

/// What the body's mass is set from.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum MassFrom {
    DensityKgM3(f64),
    MassKg(f64),
}

/// The mass properties of the solid `mesh` encloses (closed, outward).
pub fn mass_properties(mesh: &TriMesh, from: MassFrom) -> Result<MassProperties, MeshError> {
    if mesh.triangles.is_empty() {
        return Err(MeshError::Input(
            "the mesh is empty: mass and inertia need a closed surface".into(),
        ));
    }
    let points: Vec<Vector> = mesh
        .positions
        .iter()
        .map(|p| Vector::new(p[0], p[1], p[2]))
        .collect();
    let unit =
        parry3d::mass_properties::MassProperties::from_trimesh(1.0, &points, &mesh.triangles);
    let volume = if unit.inv_mass > 0.0 {
        1.0 / unit.inv_mass as f64
    } else {
        0.0
    };
    if volume.is_nan() || volume <= 0.0 {
        return Err(MeshError::Input(
            "the mesh encloses no volume: mass and inertia need a closed surface".into(),
        ));
    }
    let density = match from {
        MassFrom::DensityKgM3(d) if d.is_finite() && d > 0.0 => d,
        MassFrom::MassKg(m) if m.is_finite() && m > 0.0 => m / volume,
        MassFrom::DensityKgM3(d) => {
            return Err(MeshError::Input(format!(
                "--density-kg-m3 must be positive, got {d}"
            )));
        }
        MassFrom::MassKg(m) => {
            return Err(MeshError::Input(format!(
                "--mass-kg must be positive, got {m}"
            )));
        }
    };
    let unit_inertia = unit.reconstruct_inertia_matrix();
    let cols = [
        unit_inertia.x_axis,
        unit_inertia.y_axis,
        unit_inertia.z_axis,
    ];
    let inertia = Matrix3::from_fn(|r, c| cols[c][r] as f64 * density);
    let eigen = inertia.symmetric_eigen();
    let mut axes = eigen.eigenvectors;
    if axes.determinant() < 0.0 {
        axes.column_mut(2).neg_mut();
    }
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(axes));
    let com = unit.local_com;
    Ok(MassProperties {
        mass_kg: volume * density,
        density_kg_m3: density,
        volume_m3: volume,
        center_of_mass_m: [com.x as f64, com.y as f64, com.z as f64],
        inertia_kg_m2: std::array::from_fn(|r| std::array::from_fn(|c| inertia[(r, c)])),
        principal_inertia_kg_m2: [0, 1, 2].map(|k| eigen.eigenvalues[k]),
        principal_axes_quat_wxyz: [q.w, q.i, q.j, q.k],
    })
}

/// Names of the asset's files, relative to its folder.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AssetLayout {
    pub name: String,
    pub visual_mesh: String,
    pub collision_meshes: Vec<String>,
}

fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// A URDF with one link: the inertial block, the visual mesh, a collision
/// element per convex piece. MuJoCo reads it as well (its `<mujoco>` block
/// keeps the visual mesh and takes the written inertia, not the geoms').
pub fn urdf(layout: &AssetLayout, mass: &MassProperties) -> String {
    let name = xml_escape(&layout.name);
    let c = mass.center_of_mass_m;
    let i = mass.inertia_kg_m2;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "<?xml version=\"1.0\"?>\n<!-- omniscan asset; metres, kilograms -->"
    );
    let _ = writeln!(s, "<robot name=\"{name}\">");
    let _ = writeln!(
        s,
        "  <mujoco>\n    <compiler discardvisual=\"false\" strippath=\"false\" inertiafromgeom=\"false\"/>\n  </mujoco>"
    );
    let _ = writeln!(s, "  <link name=\"{name}\">");
    let _ = writeln!(s, "    <inertial>");
    let _ = writeln!(
        s,
        "      <origin xyz=\"{} {} {}\" rpy=\"0 0 0\"/>",
        c[0], c[1], c[2]
    );
    let _ = writeln!(s, "      <mass value=\"{}\"/>", mass.mass_kg);
    let _ = writeln!(
        s,
        "      <inertia ixx=\"{}\" ixy=\"{}\" ixz=\"{}\" iyy=\"{}\" iyz=\"{}\" izz=\"{}\"/>",
        i[0][0], i[0][1], i[0][2], i[1][1], i[1][2], i[2][2]
    );
    let _ = writeln!(s, "    </inertial>");
    let _ = writeln!(
        s,
        "    <visual>\n      <origin xyz=\"0 0 0\" rpy=\"0 0 0\"/>\n      <geometry><mesh filename=\"{}\"/></geometry>\n    </visual>",
        xml_escape(&layout.visual_mesh)
    );
    for hull in &layout.collision_meshes {
        let _ = writeln!(
            s,
            "    <collision>\n      <origin xyz=\"0 0 0\" rpy=\"0 0 0\"/>\n      <geometry><mesh filename=\"{}\"/></geometry>\n    </collision>",
            xml_escape(hull)
        );
    }
    let _ = writeln!(s, "  </link>\n</robot>");
    s
}

/// An MJCF model: one free body with the written inertia, the visual mesh
/// (no contacts, group 1) and a collision geom per convex piece (group 3).
pub fn mjcf(layout: &AssetLayout, mass: &MassProperties) -> String {
    let name = xml_escape(&layout.name);
    let c = mass.center_of_mass_m;
    let q = mass.principal_axes_quat_wxyz;
    let d = mass.principal_inertia_kg_m2;
    let mut s = String::new();
    let _ = writeln!(s, "<!-- omniscan asset; metres, kilograms -->");
    let _ = writeln!(s, "<mujoco model=\"{name}\">");
    let _ = writeln!(s, "  <compiler angle=\"radian\" meshdir=\".\"/>");
    let _ = writeln!(s, "  <asset>");
    let _ = writeln!(
        s,
        "    <mesh name=\"{name}_visual\" file=\"{}\"/>",
        xml_escape(&layout.visual_mesh)
    );
    for (k, hull) in layout.collision_meshes.iter().enumerate() {
        let _ = writeln!(
            s,
            "    <mesh name=\"{name}_collision_{k}\" file=\"{}\"/>",
            xml_escape(hull)
        );
    }
    let _ = writeln!(s, "  </asset>\n  <worldbody>");
    let _ = writeln!(
        s,
        "    <body name=\"{name}\">\n      <freejoint name=\"{name}_free\"/>"
    );
    let _ = writeln!(
        s,
        "      <inertial pos=\"{} {} {}\" quat=\"{} {} {} {}\" mass=\"{}\" diaginertia=\"{} {} {}\"/>",
        c[0], c[1], c[2], q[0], q[1], q[2], q[3], mass.mass_kg, d[0], d[1], d[2]
    );
    let _ = writeln!(
        s,
        "      <geom name=\"{name}_visual\" type=\"mesh\" mesh=\"{name}_visual\" contype=\"0\" conaffinity=\"0\" group=\"1\" density=\"0\"/>"
    );
    for k in 0..layout.collision_meshes.len() {
        let _ = writeln!(
            s,
            "      <geom name=\"{name}_collision_{k}\" type=\"mesh\" mesh=\"{name}_collision_{k}\" group=\"3\" density=\"0\"/>"
        );
    }
    let _ = writeln!(s, "    </body>\n  </worldbody>\n</mujoco>");
    s
}

/// Writes the hulls as `NAME_collision_K.obj` and returns their names.
pub fn write_hulls(dir: &Path, name: &str, hulls: &[TriMesh]) -> Result<Vec<String>, MeshError> {
    hulls
        .iter()
        .enumerate()
        .map(|(k, hull)| {
            let file = format!("{name}_collision_{k}.obj");
            crate::files::write_plain_obj(&dir.join(&file), hull)?;
            Ok(file)
        })
        .collect()
}
