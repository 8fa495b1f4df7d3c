//! Geometry from a twin for simulators and CAD: [`mesh`] (a watertight,
//! coloured mesh as OBJ + MTL + PNG, PLY and GLB) and [`asset`] (the mesh,
//! convex collision pieces, mass and inertia, URDF and MJCF). The
//! algorithms are in [`omniscan_mesh`].

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use omniscan_core::io::write_json_atomic;
use omniscan_mesh::files::{MeshFiles, write_all};
use omniscan_mesh::physics::{
    AssetLayout, MassFrom, MassProperties, convex_decomposition, mass_properties, mjcf, urdf,
    write_hulls,
};
use omniscan_mesh::texture::bake;
use omniscan_mesh::twin::{MeshConfig, MeshStats, ModelMesh, mesh_model};
use omniscan_splat::ply::read_splats;

use crate::Progress;
use crate::settings::default_from_flags;

/// How a twin is meshed.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MeshSettings {
    /// Triangles in the mesh (decimated to at most this).
    #[arg(long, default_value_t = MeshConfig::default().faces)]
    pub faces: usize,
    /// Voxel edge of the fusion, millimetres (default: the object's largest extent / 200, within 0.2-2 mm).
    #[arg(long)]
    pub voxel_mm: Option<f64>,
    /// Depth views rendered all round the object.
    #[arg(long, default_value_t = MeshConfig::default().views)]
    pub views: usize,
    /// Width and height of each depth view, pixels.
    #[arg(long, default_value_t = MeshConfig::default().view_px)]
    pub view_px: u32,
    /// Side of the baked texture, pixels.
    #[arg(long, default_value_t = MeshConfig::default().texture_px)]
    pub texture_px: u32,
    /// Metres per model unit: 1 for omniscan's twins, 0.001 for a model in millimetres.
    #[arg(long, default_value_t = MeshConfig::default().scale_m_per_unit)]
    pub scale_m_per_unit: f64,
    /// The share of decisive views that makes a voxel inside, against the bubbles under a trained twin's skin; it moves clean surfaces out by up to 3 voxels: give 2 (off) for a model with clean geometry (docs/mesh.md).
    #[arg(long, default_value_t = MeshConfig::default().inside_vote)]
    pub inside_vote: f32,
    /// The files' base name (default: the model's file name without its extension).
    #[arg(long)]
    pub name: Option<String>,
}

default_from_flags!(MeshSettings);

impl MeshSettings {
    fn config(&self) -> MeshConfig {
        MeshConfig {
            faces: self.faces,
            voxel_mm: self.voxel_mm,
            views: self.views,
            view_px: self.view_px,
            texture_px: self.texture_px,
            scale_m_per_unit: self.scale_m_per_unit,
            inside_vote: self.inside_vote,
            ..MeshConfig::default()
        }
    }
}

/// What [`mesh`] made.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MeshReport {
    pub model: PathBuf,
    pub files: MeshFiles,
    #[serde(flatten)]
    pub stats: MeshStats,
}

fn check_settings(settings: &MeshSettings) -> Result<()> {
    if settings.faces < 4 {
        bail!("--faces {}: a closed mesh needs at least 4", settings.faces);
    }
    if settings.views < 6 {
        bail!(
            "--views {}: at least 6 views are needed to see all round",
            settings.views
        );
    }
    if !(32..=4096).contains(&settings.view_px) {
        bail!("--view-px {}: give 32-4096 pixels", settings.view_px);
    }
    if settings.inside_vote.is_nan() || settings.inside_vote <= 0.0 {
        bail!(
            "--inside-vote {}: give a share above 0 (above 1 turns the vote off)",
            settings.inside_vote
        );
    }
    if !(16..=16384).contains(&settings.texture_px) {
        bail!("--texture-px {}: give 16-16384 pixels", settings.texture_px);
    }
    Ok(())
}

fn base_name(model: &Path, name: &Option<String>) -> Result<String> {
    let name = match name {
        Some(n) => n.clone(),
        None => model
            .file_name()
            .and_then(|n| n.to_str())
            .map(|n| n.split('.').next().unwrap_or(n).to_string())
            .unwrap_or_else(|| "object".into()),
    };
    if name.is_empty()
        || !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    {
        bail!(
            "--name `{name}`: use letters, digits, `_` and `-` (it names files and the asset's body)"
        );
    }
    Ok(name)
}

/// Reads and meshes `model`, and writes the mesh files to `out`.
fn mesh_and_write(
    model: &Path,
    out: &Path,
    settings: &MeshSettings,
    progress: &dyn Progress,
) -> Result<(ModelMesh, MeshFiles, String)> {
    check_settings(settings)?;
    let name = base_name(model, &settings.name)?;
    let splats = read_splats(model)?;
    progress.start("meshing", 0, "");
    progress.message("rendering depth all round, fusing, extracting");
    let meshed =
        mesh_model(&splats, &settings.config()).with_context(|| format!("{}", model.display()))?;
    progress.message("baking the texture, writing");
    let texture = bake(&meshed.mesh, Some(&meshed.tsdf), settings.texture_px);
    let files = write_all(out, &name, &meshed.mesh, &texture)?;
    progress.finish();
    for warning in &meshed.stats.warnings {
        tracing::warn!("{}: {warning}", model.display());
        progress.note(&format!("warning: {warning}"));
    }
    Ok((meshed, files, name))
}

/// Meshes the twin `model` into `out` (see the module docs); writes
/// `mesh.json` there too.
pub fn mesh(
    model: &Path,
    out: &Path,
    settings: &MeshSettings,
    progress: &dyn Progress,
) -> Result<MeshReport> {
    let _lock = omniscan_core::lock::OutputLock::folder(out, "mesh")?;
    let (meshed, files, _) = mesh_and_write(model, out, settings, progress)?;
    let report = MeshReport {
        model: model.to_path_buf(),
        files,
        stats: meshed.stats,
    };
    write_json_atomic(&out.join("mesh.json"), &report)?;
    Ok(report)
}

/// How a twin becomes a simulation asset.
#[derive(clap::Args, Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AssetSettings {
    #[command(flatten)]
    #[serde(flatten)]
    pub mesh: MeshSettings,
    /// The material's density, kg/m³ (default 1000, water's; ABS plastic is about 1050, aluminium 2700).
    #[arg(long, conflicts_with = "mass_kg")]
    pub density_kg_m3: Option<f64>,
    /// The object's mass, kg (sets the density from the mesh's volume).
    #[arg(long)]
    pub mass_kg: Option<f64>,
    /// Most convex pieces in the collision geometry.
    #[arg(long, default_value_t = 16)]
    pub hulls: u32,
    /// Voxels across the object in the convex decomposition.
    #[arg(long, default_value_t = 64)]
    pub decomposition_resolution: u32,
}

default_from_flags!(AssetSettings);

/// The density used when neither a density nor a mass is given, kg/m³.
pub const DEFAULT_DENSITY_KG_M3: f64 = 1000.0;

/// What [`asset`] made.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AssetReport {
    pub model: PathBuf,
    pub mesh: MeshReport,
    pub urdf: PathBuf,
    pub mjcf: PathBuf,
    pub collision_meshes: Vec<PathBuf>,
    pub mass: MassProperties,
    /// Volume of the convex pieces' union bound: their summed volume over the mesh's, percent.
    pub hull_volume_percent: f64,
    pub seconds: f64,
}

/// Meshes the twin `model` and writes a simulation asset to `out`: the
/// mesh files, `NAME_collision_K.obj`, `NAME.urdf`, `NAME.xml` (MJCF) and
/// `asset.json`.
pub fn asset(
    model: &Path,
    out: &Path,
    settings: &AssetSettings,
    progress: &dyn Progress,
) -> Result<AssetReport> {
    let start = Instant::now();
    let from = match (settings.density_kg_m3, settings.mass_kg) {
        (Some(_), Some(_)) => bail!("give --density-kg-m3 or --mass-kg, not both"),
        (_, Some(m)) => MassFrom::MassKg(m),
        (d, None) => MassFrom::DensityKgM3(d.unwrap_or(DEFAULT_DENSITY_KG_M3)),
    };
    if settings.hulls == 0 || !(8..=512).contains(&settings.decomposition_resolution) {
        bail!(
            "--hulls {} and --decomposition-resolution {}: give at least one hull and 8-512 voxels",
            settings.hulls,
            settings.decomposition_resolution
        );
    }
    let _lock = omniscan_core::lock::OutputLock::folder(out, "asset")?;
    let (meshed, files, name) = mesh_and_write(model, out, &settings.mesh, progress)?;
    let mass = mass_properties(&meshed.mesh, from)?;
    progress.start("convex decomposition", 0, "");
    let hulls = convex_decomposition(
        &meshed.mesh,
        settings.hulls,
        settings.decomposition_resolution,
    );
    progress.finish();
    if hulls.is_empty() {
        bail!(
            "{}: the convex decomposition found no piece",
            model.display()
        );
    }
    let hull_volume: f64 = hulls.iter().map(omniscan_mesh::topology::volume).sum();
    let collision = write_hulls(out, &name, &hulls)?;
    let layout = AssetLayout {
        name: name.clone(),
        visual_mesh: files
            .obj
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default()
            .to_string(),
        collision_meshes: collision.clone(),
    };
    let (urdf_path, mjcf_path) = (
        out.join(format!("{name}.urdf")),
        out.join(format!("{name}.xml")),
    );
    omniscan_core::io::write_atomic(&urdf_path, urdf(&layout, &mass).as_bytes())?;
    omniscan_core::io::write_atomic(&mjcf_path, mjcf(&layout, &mass).as_bytes())?;
    let report = AssetReport {
        model: model.to_path_buf(),
        mesh: MeshReport {
            model: model.to_path_buf(),
            files,
            stats: meshed.stats,
        },
        urdf: urdf_path,
        mjcf: mjcf_path,
        collision_meshes: collision.iter().map(|c| out.join(c)).collect(),
        hull_volume_percent: 100.0 * hull_volume / mass.volume_m3,
        mass,
        seconds: start.elapsed().as_secs_f64(),
    };
    write_json_atomic(&out.join("asset.json"), &report)?;
    Ok(report)
}
