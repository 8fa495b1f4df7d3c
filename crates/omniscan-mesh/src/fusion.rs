//! Truncated signed distance fusion (Curless and Levoy, SIGGRAPH 1996) of
//! depth images into a voxel grid, with colour; the approach 2DGS (Huang et
//! al. 2024, Sec. 5) uses to mesh a splat model from its rendered depth.
//!
//! Each pixel is one [`Sample`]: a surface at a depth (the band around it is
//! fused, what lies beyond stays unknown), or empty space up to a depth (a
//! ray that hit nothing, or hit something that is not the object, such as a
//! gripper finger in a sensor depth map). Voxels no view ever observed keep
//! weight zero: [`crate::extract`] takes them as inside, which closes the
//! surface where no view looked, and marks the triangles it built there.

use rayon::prelude::*;

use omniscan_splat::raster::Camera;

/// An axis-aligned grid of voxel centres: `origin` is voxel (0, 0, 0)'s
/// centre, metres; x varies fastest.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Grid {
    pub origin: [f64; 3],
    pub voxel_m: f64,
    pub dims: [usize; 3],
}

impl Grid {
    /// The grid of `voxel_m` voxels covering the box `lo`..`hi`.
    pub fn covering(lo: [f64; 3], hi: [f64; 3], voxel_m: f64) -> Grid {
        let dims = [0, 1, 2].map(|k| ((hi[k] - lo[k]) / voxel_m).ceil().max(1.0) as usize + 1);
        Grid {
            origin: lo,
            voxel_m,
            dims,
        }
    }

    pub fn len(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn index(&self, x: usize, y: usize, z: usize) -> usize {
        (z * self.dims[1] + y) * self.dims[0] + x
    }

    pub fn position(&self, x: usize, y: usize, z: usize) -> [f64; 3] {
        [
            self.origin[0] + x as f64 * self.voxel_m,
            self.origin[1] + y as f64 * self.voxel_m,
            self.origin[2] + z as f64 * self.voxel_m,
        ]
    }
}

/// What one pixel says about its ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Sample {
    /// The object's surface at this depth (camera z, metres).
    Surface(f32),
    /// Nothing of the object closer than this depth (`f32::INFINITY`: the
    /// ray hit nothing at all; 0: the pixel says nothing).
    EmptyUntil(f32),
}

/// One depth image to fuse: a pinhole camera, a sample per pixel (row
/// major) and, optionally, the colour seen at each pixel (0-1 RGB).
#[derive(Debug, Clone)]
pub struct DepthView {
    pub camera: Camera<f32>,
    pub samples: Vec<Sample>,
    pub rgb: Option<Vec<[f32; 3]>>,
}

/// The fused volume: per voxel the signed distance in units of the
/// truncation (positive outside, in [-1, 1]), its weight (observations),
/// and the mean colour of the observations near the surface.
#[derive(Debug, Clone)]
pub struct Tsdf {
    pub grid: Grid,
    pub truncation_m: f64,
    pub sdf: Vec<f32>,
    pub weight: Vec<f32>,
    pub color: Vec<[f32; 3]>,
    pub color_weight: Vec<f32>,
}

/// A view's camera in the form the inner loop reads.
struct Projector {
    rot: [[f32; 3]; 3],
    trans: [f32; 3],
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: usize,
    height: usize,
    near: f32,
}

impl Projector {
    fn new(c: &Camera<f32>) -> Projector {
        let v = &c.viewmat;
        Projector {
            rot: [0, 1, 2].map(|r| [v[r][0], v[r][1], v[r][2]]),
            trans: [v[0][3], v[1][3], v[2][3]],
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            width: c.width as usize,
            height: c.height as usize,
            near: c.near,
        }
    }

    /// The pixel index and camera depth of point `p`, if it is in view.
    fn project(&self, p: [f32; 3]) -> Option<(usize, f32)> {
        let r = &self.rot;
        let cam =
            [0, 1, 2].map(|k| r[k][0] * p[0] + r[k][1] * p[1] + r[k][2] * p[2] + self.trans[k]);
        if cam[2] <= self.near {
            return None;
        }
        let u = self.fx * cam[0] / cam[2] + self.cx;
        let v = self.fy * cam[1] / cam[2] + self.cy;
        if !(u >= 0.0 && v >= 0.0) {
            return None;
        }
        let (u, v) = (u as usize, v as usize);
        (u < self.width && v < self.height).then_some((v * self.width + u, cam[2]))
    }
}

/// Fuses `views` into a grid with truncation distance `truncation_m`;
/// `inside_vote` is [`INSIDE_VOTE`] for splat models, above 1 for none.
/// Voxels on the grid's faces are set to empty space, so the surface
/// [`crate::extract`] builds is closed.
pub fn fuse(grid: Grid, truncation_m: f64, views: &[DepthView], inside_vote: f32) -> Tsdf {
    let projectors: Vec<Projector> = views.iter().map(|v| Projector::new(&v.camera)).collect();
    let n = grid.len();
    let mut sdf = vec![0.0f32; n];
    let mut weight = vec![0.0f32; n];
    let mut color = vec![[0.0f32; 3]; n];
    let mut color_weight = vec![0.0f32; n];
    let trunc = truncation_m as f32;
    let slice = grid.dims[0] * grid.dims[1];
    sdf.par_chunks_mut(slice)
        .zip(weight.par_chunks_mut(slice))
        .zip(color.par_chunks_mut(slice))
        .zip(color_weight.par_chunks_mut(slice))
        .enumerate()
        .for_each(|(z, (((sdf, weight), color), color_weight))| {
            for y in 0..grid.dims[1] {
                for x in 0..grid.dims[0] {
                    let i = y * grid.dims[0] + x;
                    let p = grid.position(x, y, z).map(|c| c as f32);
                    let boundary = [x, y, z]
                        .iter()
                        .zip(grid.dims)
                        .any(|(&c, d)| c == 0 || c + 1 == d);
                    if boundary {
                        (sdf[i], weight[i]) = (1.0, 1.0);
                        continue;
                    }
                    let voxel = fuse_voxel(p, trunc, views, &projectors, inside_vote);
                    (sdf[i], weight[i], color[i], color_weight[i]) = voxel;
                }
            }
        });
    Tsdf {
        grid,
        truncation_m,
        sdf,
        weight,
        color,
        color_weight,
    }
}

/// The share of the decisive views (those that see a voxel more than the
/// truncation behind a surface, or more than it in front) above which a
/// voxel the distances call outside is inside.
///
/// Why: a trained twin's depth is not a clean sensor's. Just under its
/// surface, most views see a voxel too far behind the surface to count,
/// and the one or two that count (a grazing view, a pixel whose depth
/// belongs to a farther part) can call it outside; without this rule the
/// twins of `bench mesh` came out riddled with thousands of closed bubbles
/// under their skin, twice their true area, 1.9-3.3 mm Chamfer. Deep
/// inside, nearly every decisive view says "behind"; just outside a face,
/// about half do (the views from the other side), outside a concave corner
/// fewer still.
///
/// How much: chosen on `bench mesh`'s own objects (no held-out set; see
/// docs/results.md): 0.5 filled the L-bracket's inner corner (1.8 mm), 0.8
/// left bubbles (1.3 mm on the banana), 0.65 was best over all of them. It
/// fills pockets seen from fewer than about a third of the directions.
///
/// What it costs: voxels within the truncation outside a surface are seen
/// "behind" by the views from the other side and by none decisively in
/// front, so on clean depth the surface moves out by up to the truncation
/// (a splat box: 0.7 mm a face at 0.2 mm voxels; an exact sphere: 0.17 mm
/// mean). On twins the bubbles cost more than that.
pub const INSIDE_VOTE: f32 = 0.65;

/// One voxel's signed distance, weight, colour and colour weight.
fn fuse_voxel(
    p: [f32; 3],
    trunc: f32,
    views: &[DepthView],
    projectors: &[Projector],
    inside_vote: f32,
) -> (f32, f32, [f32; 3], f32) {
    let (mut sum, mut weight) = (0.0f32, 0.0f32);
    let (mut rgb, mut color_weight) = ([0.0f32; 3], 0.0f32);
    let (mut behind, mut in_front) = (0u32, 0u32);
    for (view, proj) in views.iter().zip(projectors) {
        let Some((pixel, z)) = proj.project(p) else {
            continue;
        };
        let d = match view.samples[pixel] {
            Sample::Surface(depth) => depth - z,
            // Empty space up to `until`: a voxel in front of it is outside.
            Sample::EmptyUntil(until) if z < until - trunc => trunc,
            Sample::EmptyUntil(_) => continue,
        };
        if d < -trunc {
            behind += 1;
            continue;
        }
        if d >= trunc {
            in_front += 1;
        }
        sum += (d / trunc).min(1.0);
        weight += 1.0;
        if let Some(colors) = &view.rgb
            && d.abs() < 0.5 * trunc
        {
            for (sum, c) in rgb.iter_mut().zip(colors[pixel]) {
                *sum += c;
            }
            color_weight += 1.0;
        }
    }
    if weight == 0.0 {
        return (-1.0, 0.0, [0.0; 3], 0.0);
    }
    let mean = if color_weight > 0.0 {
        rgb.map(|c| c / color_weight)
    } else {
        [0.0; 3]
    };
    let sdf = sum / weight;
    let votes = (behind + in_front) as f32;
    if sdf > 0.0 && behind as f32 >= inside_vote * votes {
        // Where no view saw a surface near it (every distance said empty
        // space), it counts as unobserved: the surface built against it
        // is marked unseen.
        let observed = if sdf >= 1.0 { 0.0 } else { weight };
        return (-1.0, observed, mean, color_weight);
    }
    (sdf, weight, mean, color_weight)
}

impl Tsdf {
    /// The mean colour near `p` (trilinear over the voxels that saw colour),
    /// or `None` where no view saw any.
    pub fn color_at(&self, p: [f64; 3]) -> Option<[f32; 3]> {
        let g = &self.grid;
        let f = [0, 1, 2].map(|k| ((p[k] - g.origin[k]) / g.voxel_m).max(0.0));
        let base = [0, 1, 2].map(|k| (f[k] as usize).min(g.dims[k].saturating_sub(2)));
        let (mut rgb, mut total) = ([0.0f32; 3], 0.0f32);
        for corner in 0..8 {
            let o = [corner & 1, (corner >> 1) & 1, (corner >> 2) & 1];
            let w: f64 = (0..3)
                .map(|k| {
                    let t = (f[k] - base[k] as f64).clamp(0.0, 1.0);
                    if o[k] == 1 { t } else { 1.0 - t }
                })
                .product();
            let i = g.index(base[0] + o[0], base[1] + o[1], base[2] + o[2]);
            if self.color_weight[i] > 0.0 && w > 0.0 {
                let w = w as f32;
                for (sum, c) in rgb.iter_mut().zip(self.color[i]) {
                    *sum += w * c;
                }
                total += w;
            }
        }
        (total > 0.0).then(|| rgb.map(|c| c / total))
    }
}
