//! A watertight, coloured mesh from a splat model: the model's median
//! depth (where a ray's accumulated opacity reaches one half, the first
//! surface; [`crate::depth`]) rendered from views spread evenly over the whole sphere, fused
//! as a TSDF and extracted, as 2DGS meshes its models (Huang et al. 2024,
//! Sec. 5); median rather than expected depth as Gaussian Opacity Fields
//! argue (Yu et al. 2024, Sec. 4). The twin is complete (360°), so the
//! views come from below as well as above.

use std::time::Instant;

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use omniscan_core::geometry::look_at;
use omniscan_splat::Splats;
use omniscan_splat::raster::{Camera, render};

use crate::depth::median_surface_depth;
use crate::fusion::{DepthView, Grid, Sample, Tsdf, fuse};
use crate::topology::{Topology, area, largest_component, topology, unseen_area, volume};
use crate::{MeshError, TriMesh, extract, simplify};

/// How a model is meshed. `Default` is the documented default.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MeshConfig {
    /// Triangles in the written mesh (decimated to at most this).
    pub faces: usize,
    /// Voxel edge, millimetres; `None`: the object's largest extent / 200,
    /// within 0.2-2 mm.
    pub voxel_mm: Option<f64>,
    /// Depth views rendered over the sphere.
    pub views: usize,
    /// Width and height of each depth view, pixels.
    pub view_px: u32,
    /// The TSDF's truncation distance, in voxels.
    pub truncation_voxels: f64,
    /// Side of the baked texture, pixels.
    pub texture_px: u32,
    /// Metres per model unit (1 for omniscan's twins, 0.001 for a model in millimetres).
    pub scale_m_per_unit: f64,
    /// The share of decisive views that makes a voxel inside
    /// ([`crate::fusion::INSIDE_VOTE`]); above 1: no vote (clean depth).
    pub inside_vote: f32,
}

impl Default for MeshConfig {
    fn default() -> Self {
        MeshConfig {
            faces: 20_000,
            voxel_mm: None,
            views: 64,
            view_px: 320,
            truncation_voxels: 3.0,
            texture_px: 2048,
            scale_m_per_unit: 1.0,
            inside_vote: crate::fusion::INSIDE_VOTE,
        }
    }
}

/// The object sizes meshing takes, metres (the simulator's 1-40 cm, with room).
pub const OBJECT_SIZE_M: std::ops::RangeInclusive<f64> = 0.005..=1.0;

/// What [`mesh_model`] made and measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MeshStats {
    pub voxel_mm: f64,
    pub grid: [usize; 3],
    pub views: usize,
    /// Triangles extracted, before keeping the object's piece and decimating.
    pub extracted_faces: usize,
    /// Pieces dropped (floaters away from the object).
    pub dropped_components: usize,
    pub topology: Topology,
    pub area_mm2: f64,
    pub volume_mm3: f64,
    /// Surface closed over regions no view saw (marked in the files), mm².
    pub unseen_area_mm2: f64,
    /// How far the decimation moved the surface: the largest and the mean
    /// distance of the extracted mesh's vertices from the decimated mesh, mm.
    pub decimation_max_mm: f64,
    pub decimation_mean_mm: f64,
    pub extent_mm: [f64; 3],
    pub seconds: f64,
    /// Things the user should know (thin parts, a mesh that is not closed).
    pub warnings: Vec<String>,
}

/// A mesh and the fused volume it came from (for baking its texture).
pub struct ModelMesh {
    pub mesh: TriMesh,
    pub tsdf: Tsdf,
    pub stats: MeshStats,
}

/// Meshes `model` (see the module docs).
pub fn mesh_model(model: &Splats, config: &MeshConfig) -> Result<ModelMesh, MeshError> {
    let start = Instant::now();
    let (lo, hi) = object_box(model, config.scale_m_per_unit)?;
    let extent = [0, 1, 2].map(|k| hi[k] - lo[k]);
    let largest = extent.iter().cloned().fold(0.0, f64::max);
    let voxel_m = match config.voxel_mm {
        Some(v) if v.is_finite() && v > 0.0 => v * 1e-3,
        Some(v) => {
            return Err(MeshError::Input(format!(
                "--voxel-mm must be positive, got {v}"
            )));
        }
        None => (largest / 200.0).clamp(0.2e-3, 2e-3),
    };
    let truncation_m = config.truncation_voxels.max(1.0) * voxel_m;
    let margin = truncation_m + 2.0 * voxel_m;
    let grid = Grid::covering(lo.map(|c| c - margin), hi.map(|c| c + margin), voxel_m);
    if grid.len() > 64_000_000 {
        return Err(MeshError::Input(format!(
            "a {:.2} mm voxel makes a grid of {} voxels for this {:.0} mm object, more than 64 million: pass a larger --voxel-mm",
            voxel_m * 1e3,
            grid.len(),
            largest * 1e3
        )));
    }
    let lap = |what: &str, since: Instant| {
        tracing::debug!("{what}: {:.2} s", since.elapsed().as_secs_f64())
    };
    let t = Instant::now();
    let views = depth_views(model, config, lo, hi);
    lap("rendering depth", t);
    let t = Instant::now();
    let tsdf = fuse(grid, truncation_m, &views, config.inside_vote);
    lap("fusing", t);
    let t = Instant::now();
    let extracted = extract::extract(&tsdf);
    let extracted_faces = extracted.triangles.len();
    let (object, dropped) = largest_component(&extracted);
    lap("extracting", t);
    let t = Instant::now();
    let mesh = simplify::simplify(&object, config.faces);
    let moved = decimation_distance(&object, &mesh)?;
    lap("decimating", t);
    let topology = topology(&mesh);
    let mut warnings = Vec::new();
    let (area_m2, volume_m3) = (area(&mesh), volume(&mesh));
    check_solid(&mesh, volume_m3, area_m2, voxel_m, &mut warnings)?;
    if !topology.is_watertight() {
        warnings.push(format!("the mesh is not watertight: {topology:?}"));
    }
    let (mlo, mhi) = mesh.bounds();
    let stats = MeshStats {
        voxel_mm: voxel_m * 1e3,
        grid: grid.dims,
        views: views.len(),
        extracted_faces,
        dropped_components: dropped,
        topology,
        area_mm2: area_m2 * 1e6,
        volume_mm3: volume_m3 * 1e9,
        unseen_area_mm2: unseen_area(&mesh) * 1e6,
        decimation_max_mm: moved.0 * 1e3,
        decimation_mean_mm: moved.1 * 1e3,
        extent_mm: [0, 1, 2].map(|k| (mhi[k] - mlo[k]) as f64 * 1e3),
        seconds: start.elapsed().as_secs_f64(),
        warnings,
    };
    Ok(ModelMesh { mesh, tsdf, stats })
}

/// The largest and mean distance (metres) of `before`'s vertices from `after`.
fn decimation_distance(before: &TriMesh, after: &TriMesh) -> Result<(f64, f64), MeshError> {
    use rayon::prelude::*;
    if before.triangles.len() == after.triangles.len() || after.triangles.is_empty() {
        return Ok((0.0, 0.0));
    }
    let surface = crate::accuracy::Surface::new(after)?;
    let d: Vec<f64> = before
        .positions
        .par_iter()
        .map(|&p| surface.distance(p) as f64)
        .collect();
    let max = d.iter().cloned().fold(0.0, f64::max);
    Ok((max, d.iter().sum::<f64>() / d.len().max(1) as f64))
}

/// Refuses a mesh with nothing solid in it and warns of parts thinner than
/// the voxels can hold (the mean thickness, twice volume over area).
fn check_solid(
    mesh: &TriMesh,
    volume_m3: f64,
    area_m2: f64,
    voxel_m: f64,
    warnings: &mut Vec<String>,
) -> Result<(), MeshError> {
    if mesh.triangles.is_empty() || volume_m3 <= 0.0 {
        return Err(MeshError::Input(format!(
            "no closed surface at {:.2} mm voxels: the object is thinner than the voxels or its splats are too faint; pass a smaller --voxel-mm",
            voxel_m * 1e3
        )));
    }
    let thickness = 2.0 * volume_m3 / area_m2;
    if thickness < 3.0 * voxel_m {
        warnings.push(format!(
            "the object is on average {:.2} mm thick, under three {:.2} mm voxels: thin parts may be lost or thickened; pass a smaller --voxel-mm",
            thickness * 1e3,
            voxel_m * 1e3
        ));
    }
    Ok(())
}

/// The box holding the model's opaque splats (the 0.2-99.8th percentile per
/// axis, so floaters do not stretch it), metres; refuses a model with none
/// or one whose size says its units are not metres.
pub fn object_box(model: &Splats, scale: f64) -> Result<([f64; 3], [f64; 3]), MeshError> {
    if !(scale.is_finite() && scale > 0.0) {
        return Err(MeshError::Input(format!(
            "--scale-m-per-unit must be positive, got {scale}"
        )));
    }
    let opaque: Vec<[f32; 3]> = model
        .means
        .iter()
        .zip(&model.opacity_logits)
        .filter(|(_, logit)| **logit > 0.0)
        .map(|(m, _)| *m)
        .collect();
    if opaque.len() < 4 {
        return Err(MeshError::Input(format!(
            "the model has {} opaque splats (opacity above 0.5) of {}: nothing to mesh; is it a trained twin?",
            opaque.len(),
            model.len()
        )));
    }
    let mut lo = [0.0; 3];
    let mut hi = [0.0; 3];
    for k in 0..3 {
        let mut axis: Vec<f32> = opaque.iter().map(|p| p[k]).collect();
        axis.sort_by(f32::total_cmp);
        let cut = axis.len() / 500;
        lo[k] = axis[cut] as f64 * scale;
        hi[k] = axis[axis.len() - 1 - cut] as f64 * scale;
    }
    let largest = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
    if !OBJECT_SIZE_M.contains(&largest) {
        return Err(MeshError::Input(format!(
            "the model is {largest:.4} units across at {scale} m per unit, outside the {:.0} mm-{:.0} m that meshing takes: \
             if the model is not in metres, pass --scale-m-per-unit (0.001 for millimetres, 0.01 for centimetres)",
            OBJECT_SIZE_M.start() * 1e3,
            OBJECT_SIZE_M.end()
        )));
    }
    Ok((lo, hi))
}

/// `count` directions spread evenly over the sphere (a Fibonacci lattice).
pub fn sphere_directions(count: usize) -> Vec<Vector3<f64>> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..count)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / count as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f64;
            Vector3::new(r * phi.cos(), r * phi.sin(), z)
        })
        .collect()
}

/// Half the field of view of the depth cameras.
const HALF_FOV_DEG: f64 = 20.0;

/// Pinhole cameras looking at the box `lo`..`hi` (metres) from `count`
/// directions, far enough that its bounding sphere fills the view.
pub fn cameras_around(lo: [f64; 3], hi: [f64; 3], count: usize, px: u32) -> Vec<Camera<f32>> {
    let centre = Point3::from([0, 1, 2].map(|k| 0.5 * (lo[k] + hi[k])));
    let radius = 0.5 * (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt();
    let distance = radius / HALF_FOV_DEG.to_radians().sin() * 1.02;
    let focal = 0.5 * px as f64 / HALF_FOV_DEG.to_radians().tan();
    let intrinsics = omniscan_core::Intrinsics {
        width: px,
        height: px,
        fx: focal,
        fy: focal,
        cx: px as f64 * 0.5,
        cy: px as f64 * 0.5,
    };
    sphere_directions(count.max(1))
        .into_iter()
        .map(|d| {
            let eye = centre + distance * d;
            let pose = look_at(&eye, &centre, &Vector3::z());
            Camera {
                near: (0.05 * distance) as f32,
                far: (10.0 * distance) as f32,
                ..Camera::from_pose(&pose, &intrinsics)
            }
        })
        .collect()
}

/// The model's median depth and colour from views all round the object.
fn depth_views(model: &Splats, config: &MeshConfig, lo: [f64; 3], hi: [f64; 3]) -> Vec<DepthView> {
    let scaled;
    let model = if config.scale_m_per_unit == 1.0 {
        model
    } else {
        scaled = scale_model(model, config.scale_m_per_unit as f32);
        &scaled
    };
    let gaussians = model.gaussians::<f32>();
    let settings = model.render_settings([0.0f32; 3]);
    cameras_around(lo, hi, config.views, config.view_px)
        .into_iter()
        .map(|camera| {
            let (projected, r) = render(&gaussians, &camera, &settings);
            let depth = median_surface_depth(&gaussians, &camera, &projected);
            let samples = r
                .alpha
                .iter()
                .zip(&depth)
                .map(|(&a, &z)| {
                    if a >= 0.5 && z > 0.0 {
                        Sample::Surface(z)
                    } else {
                        Sample::EmptyUntil(f32::INFINITY)
                    }
                })
                .collect();
            let rgb = r
                .rgb
                .iter()
                .zip(&r.alpha)
                .map(|(c, &a)| c.map(|v| (v / a.max(1e-3)).clamp(0.0, 1.0)))
                .collect();
            DepthView {
                camera,
                samples,
                rgb: Some(rgb),
            }
        })
        .collect()
}

/// The model with positions and sizes multiplied by `scale`.
fn scale_model(model: &Splats, scale: f32) -> Splats {
    let mut out = model.clone();
    out.means.iter_mut().for_each(|m| *m = m.map(|c| c * scale));
    let ln = scale.ln();
    out.log_scales
        .iter_mut()
        .for_each(|s| *s = s.map(|c| c + ln));
    out
}
