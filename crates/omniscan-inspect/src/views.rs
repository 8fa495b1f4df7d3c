//! The shared viewpoints of an inspection and what each model looks like
//! from them: K cameras spread evenly over a sphere around the reference
//! model (a Fibonacci lattice, so no direction is favoured), the renders of
//! every aligned model from those cameras, and the model's visible surface
//! sampled from the renders.
//!
//! Sampling the surface from renders rather than taking splat centres is
//! what keeps two good copies from disagreeing: trained models hold faint
//! floaters and Gaussians deep inside the object (paper, "Limitations"),
//! but neither survives compositing into an opaque pixel's depth.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use omniscan_core::geometry::look_at;
use omniscan_core::{Intrinsics, Pose};
use omniscan_register::PointCloud;
use omniscan_register::preprocess::voxel_downsample;
use omniscan_splat::Splats;
use omniscan_splat::backend::Renderer;
use omniscan_splat::raster::{Camera, render};

/// One viewpoint: where the camera is (camera-to-world, OpenCV axes) and its pinhole.
#[derive(Debug, Clone)]
pub struct View {
    pub camera_to_world: Pose,
    pub intrinsics: Intrinsics,
    /// Clipping distances along the optical axis (model units).
    pub near: f64,
    pub far: f64,
}

impl View {
    pub fn camera(&self) -> Camera<f32> {
        Camera {
            near: self.near as f32,
            far: self.far as f32,
            ..Camera::from_pose(&self.camera_to_world, &self.intrinsics)
        }
    }
}

/// Cameras to render instead of views spread over the sphere: the paper
/// renders "poses that align with the training dataset" of the first model,
/// its own scan's cameras. Camera-to-model poses (OpenCV axes, model units)
/// sharing one pinhole.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraSet {
    pub camera_to_model: Vec<Pose>,
    pub intrinsics: Intrinsics,
    /// Where the cameras come from, for the report (e.g. a capture's path).
    pub source: String,
}

impl CameraSet {
    /// `count` of the cameras taken evenly through the list (all of them
    /// when there are fewer), each with its pinhole scaled to a
    /// `width`x`height` image (square pixels, the capture's image centred
    /// in it). The inspection then zooms each onto the part.
    pub fn views(&self, count: usize, width: u32, height: u32) -> Vec<View> {
        let n = self.camera_to_model.len();
        let picked: Vec<usize> = if count >= n {
            (0..n).collect()
        } else {
            (0..count).map(|i| (2 * i + 1) * n / (2 * count)).collect()
        };
        let k = &self.intrinsics;
        let scale = (width as f64 / k.width as f64).min(height as f64 / k.height as f64);
        let intrinsics = Intrinsics {
            width,
            height,
            fx: k.fx * scale,
            fy: k.fy * scale,
            cx: 0.5 * width as f64 + (k.cx - 0.5 * k.width as f64) * scale,
            cy: 0.5 * height as f64 + (k.cy - 0.5 * k.height as f64) * scale,
        };
        picked
            .into_iter()
            .map(|i| {
                let pose = self.camera_to_model[i];
                let distance = pose.translation.vector.norm().max(1e-9);
                View {
                    camera_to_world: pose,
                    intrinsics,
                    near: 0.01 * distance,
                    far: 100.0 * distance,
                }
            })
            .collect()
    }
}

/// `count` views on a sphere around `centre`, far enough that a ball of
/// `radius` fills about 90% of the shorter image side.
pub fn sphere_views(
    centre: &Point3<f64>,
    radius: f64,
    count: usize,
    width: u32,
    height: u32,
) -> Vec<View> {
    let half_fov = 25f64.to_radians();
    let focal = 0.5 * width.min(height) as f64 / half_fov.tan();
    let distance = radius / (0.9 * half_fov).sin();
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..count)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / count as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let direction = Vector3::new(
                r * (golden * i as f64).cos(),
                r * (golden * i as f64).sin(),
                z,
            );
            let eye = centre + distance * direction;
            let up = if direction.z.abs() > 0.9 {
                Vector3::x()
            } else {
                Vector3::z()
            };
            View {
                camera_to_world: look_at(&eye, centre, &up),
                intrinsics: Intrinsics {
                    width,
                    height,
                    fx: focal,
                    fy: focal,
                    cx: width as f64 * 0.5,
                    cy: height as f64 * 0.5,
                },
                near: 0.01 * distance,
                far: 100.0 * distance,
            }
        })
        .collect()
}

/// A model rendered from one view on a black background.
#[derive(Debug, Clone)]
pub struct ViewRender {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<[f32; 3]>,
    pub alpha: Vec<f32>,
    /// Depth of the first surface along the optical axis (model units): the
    /// median depth, where the accumulated alpha reaches one half; 0 where
    /// it never does. The expected depth would blend a faint skin with what
    /// lies behind it.
    pub depth: Vec<f32>,
}

impl ViewRender {
    /// Depth of pixel `i` if it is opaque enough to count as surface.
    pub fn surface_depth(&self, i: usize, min_alpha: f32) -> Option<f32> {
        (self.alpha[i] >= min_alpha && self.depth[i] > 0.0).then_some(self.depth[i])
    }
}

/// Renders `model` from every view on the CPU.
pub fn render_views(model: &Splats, views: &[View]) -> Vec<ViewRender> {
    let gaussians = model.gaussians::<f32>();
    let settings = model.render_settings([0.0f32; 3]);
    views
        .par_iter()
        .map(|view| view_render(render(&gaussians, &view.camera(), &settings).1))
        .collect()
}

/// Renders `model` from every view on `renderer` (the CPU in parallel, a GPU
/// one view after another).
pub fn render_views_on(
    renderer: &Renderer,
    model: &Splats,
    views: &[View],
) -> Result<Vec<ViewRender>, omniscan_splat::SplatError> {
    if !renderer.is_gpu() {
        return Ok(render_views(model, views));
    }
    let gaussians = model.gaussians::<f32>();
    let settings = model.render_settings([0.0f32; 3]);
    views
        .iter()
        .map(|view| {
            Ok(view_render(renderer.render(
                &gaussians,
                &view.camera(),
                &settings,
            )?))
        })
        .collect()
}

/// A render with its surface depth.
fn view_render(r: omniscan_splat::raster::Render<f32>) -> ViewRender {
    ViewRender {
        width: r.width,
        height: r.height,
        rgb: r.rgb,
        alpha: r.alpha,
        depth: r.median_depth,
    }
}

/// Pixels at least this opaque are surface.
pub const SURFACE_ALPHA: f32 = 0.6;

/// Back-projects pixel `(x, y)` of `view` at `depth` into the world.
pub fn back_project(view: &View, x: u32, y: u32, depth: f64) -> Point3<f64> {
    let k = &view.intrinsics;
    let p = Point3::new(
        (x as f64 + 0.5 - k.cx) / k.fx * depth,
        (y as f64 + 0.5 - k.cy) / k.fy * depth,
        depth,
    );
    view.camera_to_world * p
}

/// Pixel `i`'s depth if it shows surface: opaque enough, and not on a depth
/// edge.
pub fn surface_pixel_depth(render: &ViewRender, view: &View, i: usize) -> Option<f32> {
    render
        .surface_depth(i, SURFACE_ALPHA)
        .filter(|_| smooth_depth(render, view, i))
}

/// Whether pixel `i`'s depth agrees with its four neighbours: pixels on a
/// depth edge blend two surfaces into a point on neither.
fn smooth_depth(render: &ViewRender, view: &View, i: usize) -> bool {
    let (w, h) = (render.width as usize, render.height as usize);
    let (x, y) = (i % w, i / w);
    let z = render.depth[i];
    // Neighbouring samples on a surface tilted up to ~80° from the view.
    let tolerance = 6.0 * z / view.intrinsics.fx as f32;
    let neighbours = [
        (x > 0).then(|| i - 1),
        (x + 1 < w).then(|| i + 1),
        (y > 0).then(|| i - w),
        (y + 1 < h).then(|| i + w),
    ];
    neighbours
        .into_iter()
        .flatten()
        .all(|j| render.alpha[j] >= 0.5 && (render.depth[j] - z).abs() <= tolerance)
}

/// The surface normal at a depth-smooth pixel, from its neighbours'
/// back-projections (central differences where both sides exist), turned
/// towards the camera; zero where it cannot be told.
fn pixel_normal(r: &ViewRender, view: &View, x: u32, y: u32, at: &Point3<f64>) -> Vector3<f64> {
    let (w, h) = (r.width, r.height);
    let point = |x: u32, y: u32| {
        let z = r.depth[(y * w + x) as usize] as f64;
        back_project(view, x, y, z)
    };
    let along = |lo: Option<(u32, u32)>, hi: Option<(u32, u32)>| match (lo, hi) {
        (Some(a), Some(b)) => point(b.0, b.1) - point(a.0, a.1),
        (Some(a), None) => at - point(a.0, a.1),
        (None, Some(b)) => point(b.0, b.1) - at,
        (None, None) => Vector3::zeros(),
    };
    let du = along((x > 0).then(|| (x - 1, y)), (x + 1 < w).then(|| (x + 1, y)));
    let dv = along((y > 0).then(|| (x, y - 1)), (y + 1 < h).then(|| (x, y + 1)));
    let mut n = du.cross(&dv);
    let length = n.norm();
    if !(length > 0.0 && length.is_finite()) {
        return Vector3::zeros();
    }
    n /= length;
    let to_camera = view.camera_to_world.translation.vector - at.coords;
    if n.dot(&to_camera) < 0.0 {
        n = -n;
    }
    n
}

/// The visible surface of a model: opaque, depth-smooth pixels of every
/// render back-projected, with their rendered colour and a normal facing
/// the cameras that saw them, thinned to one point per `spacing` voxel.
pub fn surface_points(renders: &[ViewRender], views: &[View], spacing: f64) -> PointCloud {
    let per_view: Vec<PointCloud> = renders
        .par_iter()
        .zip(views)
        .map(|(r, view)| {
            let mut cloud = PointCloud::default();
            for i in 0..r.alpha.len() {
                let Some(z) = surface_pixel_depth(r, view, i) else {
                    continue;
                };
                let (x, y) = ((i % r.width as usize) as u32, (i / r.width as usize) as u32);
                let point = back_project(view, x, y, z as f64);
                cloud.normals.push(pixel_normal(r, view, x, y, &point));
                cloud.points.push(point);
                cloud.colors.push(r.rgb[i]);
            }
            cloud
        })
        .collect();
    let mut all = PointCloud::default();
    for c in &per_view {
        all.extend(c);
    }
    if all.is_empty() {
        return all;
    }
    voxel_downsample(&all, spacing)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sphere_views_look_at_the_centre_from_all_around() {
        let centre = Point3::new(0.1, -0.2, 0.3);
        let views = sphere_views(&centre, 0.05, 50, 64, 48);
        let mut mean = Vector3::zeros();
        for v in &views {
            let eye = v.camera_to_world.translation.vector;
            let forward = v.camera_to_world.rotation * Vector3::z();
            let to_centre = (centre.coords - eye).normalize();
            assert!((forward - to_centre).norm() < 1e-9);
            mean += (eye - centre.coords).normalize();
        }
        // Evenly spread: the mean direction nearly cancels.
        assert!(mean.norm() / 50.0 < 0.05, "{}", mean.norm() / 50.0);
    }

    #[test]
    fn a_camera_set_gives_evenly_taken_cameras_with_the_pinhole_scaled() {
        let cameras = CameraSet {
            camera_to_model: (0..10)
                .map(|i| Pose::translation(0.0, 0.0, -0.1 * (i + 1) as f64))
                .collect(),
            intrinsics: Intrinsics {
                width: 640,
                height: 480,
                fx: 600.0,
                fy: 610.0,
                cx: 330.0,
                cy: 236.0,
            },
            source: "test".into(),
        };
        let views = cameras.views(4, 160, 100);
        let depths: Vec<f64> = views
            .iter()
            .map(|v| -v.camera_to_world.translation.vector.z)
            .collect();
        // Cameras 1, 3, 6 and 8 of 0..10.
        assert_eq!(depths.len(), 4);
        for (d, want) in depths.iter().zip([0.2, 0.4, 0.7, 0.9]) {
            assert!((d - want).abs() < 1e-12, "{depths:?}");
        }
        // 640x480 fits 160x100 at a scale of 100/480, square pixels,
        // the principal point as far off centre (scaled) as it was.
        let k = views[0].intrinsics;
        let scale = 100.0 / 480.0;
        assert_eq!((k.width, k.height), (160, 100));
        assert!((k.fx - 600.0 * scale).abs() < 1e-9 && (k.fy - 610.0 * scale).abs() < 1e-9);
        assert!((k.cx - (80.0 + 10.0 * scale)).abs() < 1e-9);
        assert!((k.cy - (50.0 - 4.0 * scale)).abs() < 1e-9);
        assert!(views.iter().all(|v| v.near > 0.0 && v.far > v.near));
        // Fewer cameras than asked for: all of them.
        assert_eq!(cameras.views(100, 160, 100).len(), 10);
    }

    #[test]
    fn surface_normals_face_out_of_a_box() {
        let size = [0.06, 0.04, 0.025];
        let part = crate::generate::test_part(size, 0.0012);
        let views = sphere_views(&Point3::origin(), 0.12, 24, 96, 72);
        let surface = surface_points(&render_views(&part, &views), &views, 0.002);
        assert!(surface.len() > 500, "{}", surface.len());
        assert!(surface.has_normals());
        // Each point's face: the axis where it is closest to the box's
        // side; points within 3 mm of an edge see two faces and are left out.
        let (mut inside, mut facing_out) = (0, 0);
        for (p, n) in surface.points.iter().zip(&surface.normals) {
            let mut gaps: Vec<(f64, usize)> =
                (0..3).map(|k| (0.5 * size[k] - p[k].abs(), k)).collect();
            gaps.sort_by(|a, b| a.0.total_cmp(&b.0));
            if gaps[1].0 < 0.003 {
                continue;
            }
            let axis = gaps[0].1;
            let mut outward = Vector3::zeros();
            outward[axis] = p[axis].signum();
            inside += 1;
            facing_out += usize::from(n.dot(&outward) > 0.95);
        }
        assert!(inside > 300, "{inside}");
        assert!(
            facing_out as f64 > 0.95 * inside as f64,
            "{facing_out} of {inside} normals face out of their face"
        );
    }

    #[test]
    fn back_projection_inverts_projection() {
        let views = sphere_views(&Point3::origin(), 1.0, 3, 40, 30);
        let v = &views[1];
        let p = back_project(v, 7, 21, 2.5);
        let local = v.camera_to_world.inverse() * p;
        let k = &v.intrinsics;
        assert!((local.z - 2.5).abs() < 1e-12);
        assert!((k.fx * local.x / local.z + k.cx - 7.5).abs() < 1e-9);
        assert!((k.fy * local.y / local.z + k.cy - 21.5).abs() < 1e-9);
    }
}
