//! CPU rasterizer for the scan simulator: tiled, z-buffered, with
//! perspective-correct attribute interpolation, near-plane clipping, texture
//! mapping, ambient + directional + Blinn-Phong specular lighting and
//! supersampling anti-aliasing.
//!
//! It works as a visibility buffer: tiles of samples are rasterized in
//! parallel (rayon), each sample keeping its nearest triangle and screen
//! barycentrics; shading then runs once per pixel where all of a pixel's
//! samples see the same triangle, and per sample on edges. Every pixel also
//! gets the label (object, gripper, arm, scene) seen by most of its samples
//! and the z-depth of those samples, which become the ground-truth masks and
//! depth maps.

use nalgebra::{Isometry3, Matrix3, Point3, Vector3};
use rayon::prelude::*;

use crate::mesh::Mesh;
use omniscan_core::Intrinsics;

/// What a pixel shows, for the ground-truth masks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum Label {
    /// Table, background, robot body: nothing that moves with the gripper.
    Scene = 0,
    /// The scanned object.
    Object = 1,
    /// Fingers, gripper body and wrist link: everything rigidly attached to the
    /// gripper that a gripper mask must cover.
    Gripper = 2,
    /// Forearm links of the holding arm.
    Arm = 3,
}

/// A mark painted on a surface in the mesh's own frame (visual defects).
#[derive(Debug, Clone, PartialEq)]
pub struct Decal {
    pub center: Point3<f32>,
    pub normal: Vector3<f32>,
    /// Unit tangent along the decal's length.
    pub tangent: Vector3<f32>,
    pub half_length: f32,
    pub half_width: f32,
    /// Sideways waviness amplitude (scratches), metres.
    pub wiggle: f32,
    /// How far from the tangent plane a surface point may be and still take
    /// the mark, so thin parts do not get it on their far side.
    pub depth_tolerance: f32,
    pub color: [f32; 3],
    pub specular: f32,
}

impl Decal {
    /// Whether the surface point `p` with (unnormalised) normal `n`, both in
    /// the mesh frame, carries the mark.
    #[inline]
    pub fn covers(&self, p: &Point3<f32>, n: &Vector3<f32>) -> bool {
        let d = p - self.center;
        let bound = self.half_length + self.half_width + self.wiggle;
        if d.norm_squared() > bound * bound {
            return false;
        }
        if d.dot(&self.normal).abs() > self.depth_tolerance || n.dot(&self.normal) <= 0.2 * n.norm()
        {
            return false;
        }
        let u = d.dot(&self.tangent);
        let bitangent = self.normal.cross(&self.tangent);
        let v = d.dot(&bitangent) - self.wiggle * (u / (self.half_length.max(1e-6)) * 4.0).sin();
        u.abs() <= self.half_length && v.abs() <= self.half_width
    }
}

/// A mesh placed in the world.
#[derive(Debug, Clone)]
pub struct Instance<'a> {
    pub mesh: &'a Mesh,
    /// Mesh frame to world.
    pub to_world: Isometry3<f64>,
    pub label: Label,
    pub decals: &'a [Decal],
}

/// A directional light.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Light {
    /// Unit direction from the surface towards the light, world frame.
    pub direction: Vector3<f32>,
    pub color: [f32; 3],
}

/// The scene's lights.
#[derive(Debug, Clone, PartialEq)]
pub struct Lighting {
    pub ambient: [f32; 3],
    pub lights: Vec<Light>,
}

/// One rendered view.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderedView {
    pub width: u32,
    pub height: u32,
    /// RGB, 8 bits per channel, row-major.
    pub rgb: Vec<u8>,
    /// Z-depth in metres of the pixel's majority label; 0 where nothing was hit.
    pub depth: Vec<f32>,
    /// Label seen by most of the pixel's samples.
    pub labels: Vec<Label>,
}

/// A tile's side in samples, at most: a tile is a whole number of pixels,
/// `(TILE / supersample) · supersample` samples, so that it resolves into
/// exactly the pixels it covers. (At 3x3 supersampling 32-sample tiles
/// resolved into 10 pixels each, dropping the rest of their samples and
/// shrinking the image by 30/32 towards its top-left corner.)
const TILE: i32 = 32;
const NEAR: f32 = 0.005;
const NO_TRIANGLE: u32 = u32::MAX;

/// A triangle after clipping and projection, in sample coordinates.
struct ScreenTriangle {
    xy: [[f32; 2]; 3],
    inv_z: [f32; 3],
    /// Barycentric coordinates of each (clipped) vertex in the source triangle.
    source_bary: [[f32; 3]; 3],
    instance: u32,
    triangle: u32,
    bbox: [i32; 4],
}

struct PreparedInstance<'a> {
    mesh: &'a Mesh,
    label: Label,
    decals: &'a [Decal],
    camera_positions: Vec<Vector3<f32>>,
    rotation: Matrix3<f32>,
}

/// Renders `instances` seen by a camera with intrinsics `k` at `camera_to_world`.
pub fn render(
    instances: &[Instance],
    lighting: &Lighting,
    k: &Intrinsics,
    camera_to_world: &Isometry3<f64>,
    supersample: u32,
) -> RenderedView {
    let ss = supersample.max(1) as i32;
    let (width, height) = (k.width as i32, k.height as i32);
    let (sw, sh) = (width * ss, height * ss);
    let world_to_camera = camera_to_world.inverse();

    let prepared: Vec<PreparedInstance> = instances
        .par_iter()
        .map(|inst| {
            let to_camera = (world_to_camera * inst.to_world).cast::<f32>();
            let rotation = to_camera.rotation.to_rotation_matrix().into_inner();
            let t = to_camera.translation.vector;
            let camera_positions = inst
                .mesh
                .positions
                .iter()
                .map(|p| rotation * p.coords + t)
                .collect();
            PreparedInstance {
                mesh: inst.mesh,
                label: inst.label,
                decals: inst.decals,
                camera_positions,
                rotation,
            }
        })
        .collect();

    let projection = Projection {
        fx: (k.fx * ss as f64) as f32,
        fy: (k.fy * ss as f64) as f32,
        cx: (k.cx * ss as f64) as f32,
        cy: (k.cy * ss as f64) as f32,
        width: sw,
        height: sh,
    };
    // Runs of triangles project (and bin, below) on every thread; the
    // results keep mesh order. (Per instance, the object's mesh was one
    // thread's work while the other waited.)
    const RUN: usize = 4096;
    let runs: Vec<(usize, std::ops::Range<usize>)> = prepared
        .iter()
        .enumerate()
        .flat_map(|(i, inst)| {
            let n = inst.mesh.triangles.len();
            (0..n.div_ceil(RUN)).map(move |r| (i, r * RUN..((r + 1) * RUN).min(n)))
        })
        .collect();
    let triangles: Vec<ScreenTriangle> = runs
        .par_iter()
        .flat_map_iter(|(i, range)| {
            let inst = &prepared[*i];
            let mut out = Vec::new();
            for t in range.clone() {
                let v = inst.mesh.triangles[t].map(|v| inst.camera_positions[v as usize]);
                projection.clip_and_project(v, *i as u32, t as u32, &mut out);
            }
            out
        })
        .collect();

    // Bin triangles into tiles, each bin in triangle order.
    let tile = TILE / ss * ss;
    let tiles_x = (sw + tile - 1) / tile;
    let tiles_y = (sh + tile - 1) / tile;
    let bins = omniscan_core::tiles::bin_in_order(
        triangles.len(),
        (tiles_x * tiles_y) as usize,
        RUN,
        |i| {
            let [x0, y0, x1, y1] = triangles[i].bbox;
            ((y0 / tile)..=(y1 / tile)).flat_map(move |ty| {
                ((x0 / tile)..=(x1 / tile)).map(move |tx| (ty * tiles_x + tx) as usize)
            })
        },
    );

    // Lights in camera space.
    let r_wc = world_to_camera.rotation.cast::<f32>();
    let lights: Vec<(Vector3<f32>, [f32; 3])> = lighting
        .lights
        .iter()
        .map(|l| (r_wc * l.direction.normalize(), l.color))
        .collect();
    let grid = SampleGrid {
        width: sw,
        height: sh,
        supersample: ss,
        tile,
    };
    let shader = Shader {
        prepared: &prepared,
        triangles: &triangles,
        lights: &lights,
        ambient: lighting.ambient,
    };

    // In tile order, row by row.
    let tile_outputs: Vec<TileOutput> = (0..tiles_x * tiles_y)
        .into_par_iter()
        .map(|t| {
            let (tx, ty) = (t % tiles_x, t / tiles_x);
            rasterize_tile(tx, ty, grid, &bins[t as usize], &triangles, &shader)
        })
        .collect();

    let n = (width * height) as usize;
    let mut view = RenderedView {
        width: k.width,
        height: k.height,
        rgb: vec![0; n * 3],
        depth: vec![0.0; n],
        labels: vec![Label::Scene; n],
    };
    // Each band of tile rows is copied in by its own thread.
    let tile_px = tile / ss;
    let band = (tile_px * width) as usize;
    if band > 0 {
        (
            view.rgb.par_chunks_mut(3 * band),
            view.depth.par_chunks_mut(band),
            view.labels.par_chunks_mut(band),
        )
            .into_par_iter()
            .zip(tile_outputs.par_chunks(tiles_x as usize))
            .for_each(|((rgb, depth, labels), row)| {
                for (tx, out) in (0..).zip(row) {
                    for ly in 0..out.height {
                        for lx in 0..out.width {
                            let src = (ly * out.width + lx) as usize;
                            let dst = (ly * width + tx * tile_px + lx) as usize;
                            rgb[dst * 3..dst * 3 + 3].copy_from_slice(&out.rgb[src]);
                            depth[dst] = out.depth[src];
                            labels[dst] = out.labels[src];
                        }
                    }
                }
            });
    }
    view
}

struct Projection {
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: i32,
    height: i32,
}

impl Projection {
    fn clip_and_project(
        &self,
        v: [Vector3<f32>; 3],
        instance: u32,
        triangle: u32,
        out: &mut Vec<ScreenTriangle>,
    ) {
        let inside = v.map(|p| p.z >= NEAR);
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        match inside.iter().filter(|&&b| b).count() {
            0 => {}
            3 => self.emit(v, identity, instance, triangle, out),
            _ => {
                // Sutherland-Hodgman against z = NEAR, carrying barycentrics.
                let mut poly: Vec<(Vector3<f32>, [f32; 3])> = Vec::with_capacity(4);
                for i in 0..3 {
                    let j = (i + 1) % 3;
                    let (a, b) = (v[i], v[j]);
                    if inside[i] {
                        poly.push((a, identity[i]));
                    }
                    if inside[i] != inside[j] {
                        let s = (NEAR - a.z) / (b.z - a.z);
                        let p = a + (b - a) * s;
                        let mut bary = [0.0; 3];
                        for c in 0..3 {
                            bary[c] = identity[i][c] * (1.0 - s) + identity[j][c] * s;
                        }
                        poly.push((p, bary));
                    }
                }
                for k in 1..poly.len().saturating_sub(1) {
                    let (a, b, c) = (poly[0], poly[k], poly[k + 1]);
                    self.emit([a.0, b.0, c.0], [a.1, b.1, c.1], instance, triangle, out);
                }
            }
        }
    }

    fn emit(
        &self,
        v: [Vector3<f32>; 3],
        source_bary: [[f32; 3]; 3],
        instance: u32,
        triangle: u32,
        out: &mut Vec<ScreenTriangle>,
    ) {
        let xy = v.map(|p| [self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy]);
        let area = (xy[1][0] - xy[0][0]) * (xy[2][1] - xy[0][1])
            - (xy[1][1] - xy[0][1]) * (xy[2][0] - xy[0][0]);
        if !area.is_finite() || area.abs() < 1e-8 {
            return;
        }
        let min_x = xy.iter().map(|p| p[0]).fold(f32::INFINITY, f32::min);
        let max_x = xy.iter().map(|p| p[0]).fold(f32::NEG_INFINITY, f32::max);
        let min_y = xy.iter().map(|p| p[1]).fold(f32::INFINITY, f32::min);
        let max_y = xy.iter().map(|p| p[1]).fold(f32::NEG_INFINITY, f32::max);
        // Samples sit at integer + 0.5.
        let x0 = (min_x - 0.5).ceil().max(0.0) as i32;
        let y0 = (min_y - 0.5).ceil().max(0.0) as i32;
        let x1 = ((max_x - 0.5).floor() as i32).min(self.width - 1);
        let y1 = ((max_y - 0.5).floor() as i32).min(self.height - 1);
        if x0 > x1 || y0 > y1 {
            return;
        }
        out.push(ScreenTriangle {
            xy,
            inv_z: v.map(|p| 1.0 / p.z),
            source_bary,
            instance,
            triangle,
            bbox: [x0, y0, x1, y1],
        });
    }
}

struct TileOutput {
    width: i32,
    height: i32,
    rgb: Vec<[u8; 3]>,
    depth: Vec<f32>,
    labels: Vec<Label>,
}

/// Per-sample visibility record.
#[derive(Clone, Copy)]
struct Sample {
    inv_z: f32,
    triangle: u32,
    w1: f32,
    w2: f32,
}

/// The sample grid being rendered: its size and the samples per pixel axis.
#[derive(Clone, Copy)]
struct SampleGrid {
    width: i32,
    height: i32,
    supersample: i32,
    /// Tile side in samples (see [`TILE`]).
    tile: i32,
}

fn rasterize_tile(
    tx: i32,
    ty: i32,
    grid: SampleGrid,
    bin: &[u32],
    triangles: &[ScreenTriangle],
    shader: &Shader,
) -> TileOutput {
    let SampleGrid {
        width: sw,
        height: sh,
        supersample: ss,
        tile,
    } = grid;
    let (ox, oy) = (tx * tile, ty * tile);
    let tw = tile.min(sw - ox);
    let th = tile.min(sh - oy);
    let mut samples = vec![
        Sample {
            inv_z: 0.0,
            triangle: NO_TRIANGLE,
            w1: 0.0,
            w2: 0.0
        };
        (tw * th) as usize
    ];
    for &id in bin {
        let tri = &triangles[id as usize];
        let [a, b, c] = tri.xy;
        // Barycentrics relative to vertex a: with a at the origin the edge
        // functions have no constant term, which keeps them accurate in f32
        // for small triangles far from the image origin.
        let (bx, by) = (b[0] - a[0], b[1] - a[1]);
        let (cx, cy) = (c[0] - a[0], c[1] - a[1]);
        let inv_area = 1.0 / (bx * cy - by * cx);
        let x0 = tri.bbox[0].max(ox);
        let x1 = tri.bbox[2].min(ox + tw - 1);
        let y0 = tri.bbox[1].max(oy);
        let y1 = tri.bbox[3].min(oy + th - 1);
        let [z0, z1, z2] = tri.inv_z;
        for y in y0..=y1 {
            let py = y as f32 + 0.5 - a[1];
            let row = ((y - oy) * tw) as usize;
            for x in x0..=x1 {
                let px = x as f32 + 0.5 - a[0];
                let w1 = (px * cy - py * cx) * inv_area;
                let w2 = (bx * py - by * px) * inv_area;
                let w0 = 1.0 - w1 - w2;
                if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                    continue;
                }
                let iz = w0 * z0 + w1 * z1 + w2 * z2;
                let s = &mut samples[row + (x - ox) as usize];
                if iz > s.inv_z {
                    *s = Sample {
                        inv_z: iz,
                        triangle: id,
                        w1,
                        w2,
                    };
                }
            }
        }
    }

    // Resolve samples into pixels.
    let (pw, ph) = (tw / ss, th / ss);
    let mut out = TileOutput {
        width: pw,
        height: ph,
        rgb: Vec::with_capacity((pw * ph) as usize),
        depth: Vec::with_capacity((pw * ph) as usize),
        labels: Vec::with_capacity((pw * ph) as usize),
    };
    let per_pixel = (ss * ss) as usize;
    let mut group: Vec<Sample> = Vec::with_capacity(per_pixel);
    for py in 0..ph {
        for px in 0..pw {
            group.clear();
            for sy in 0..ss {
                for sx in 0..ss {
                    group.push(samples[((py * ss + sy) * tw + px * ss + sx) as usize]);
                }
            }
            let first = group[0].triangle;
            let uniform = group.iter().all(|s| s.triangle == first);
            let mut color = [0.0f32; 3];
            if uniform {
                if first != NO_TRIANGLE {
                    let n = group.len() as f32;
                    let w1 = group.iter().map(|s| s.w1).sum::<f32>() / n;
                    let w2 = group.iter().map(|s| s.w2).sum::<f32>() / n;
                    color = shader.shade(first, w1, w2);
                }
            } else {
                for s in &group {
                    if s.triangle != NO_TRIANGLE {
                        let c = shader.shade(s.triangle, s.w1, s.w2);
                        for i in 0..3 {
                            color[i] += c[i];
                        }
                    }
                }
                for c in &mut color {
                    *c /= group.len() as f32;
                }
            }
            // Majority label (ties go to the lower label value, deterministic).
            let mut counts = [0usize; 5];
            for s in &group {
                counts[shader.label_index(s.triangle)] += 1;
            }
            let winner = (0..5)
                .max_by_key(|&i| (counts[i], std::cmp::Reverse(i)))
                .unwrap();
            let mut depth_sum = 0.0;
            let mut depth_n = 0;
            for s in &group {
                if shader.label_index(s.triangle) == winner && s.triangle != NO_TRIANGLE {
                    depth_sum += 1.0 / s.inv_z;
                    depth_n += 1;
                }
            }
            out.rgb
                .push(color.map(|c| (c.clamp(0.0, 1.0) * 255.0 + 0.5) as u8));
            out.depth.push(if depth_n > 0 {
                depth_sum / depth_n as f32
            } else {
                0.0
            });
            out.labels.push(match winner {
                1 => Label::Object,
                2 => Label::Gripper,
                3 => Label::Arm,
                _ => Label::Scene,
            });
        }
    }
    out
}

struct Shader<'a> {
    prepared: &'a [PreparedInstance<'a>],
    triangles: &'a [ScreenTriangle],
    lights: &'a [(Vector3<f32>, [f32; 3])],
    ambient: [f32; 3],
}

impl Shader<'_> {
    /// Label slot of a sample: 0-3 as [`Label`], 4 for "nothing hit".
    #[inline]
    fn label_index(&self, triangle: u32) -> usize {
        if triangle == NO_TRIANGLE {
            4
        } else {
            self.prepared[self.triangles[triangle as usize].instance as usize].label as usize
        }
    }

    /// Colour of a screen triangle at screen barycentrics (1 − w1 − w2, w1, w2).
    #[inline]
    fn shade(&self, id: u32, w1: f32, w2: f32) -> [f32; 3] {
        let tri = &self.triangles[id as usize];
        let inst = &self.prepared[tri.instance as usize];
        let mesh = inst.mesh;
        // Perspective-correct barycentrics in the clipped triangle...
        let w0 = 1.0 - w1 - w2;
        let p0 = w0 * tri.inv_z[0];
        let p1 = w1 * tri.inv_z[1];
        let p2 = w2 * tri.inv_z[2];
        let sum = p0 + p1 + p2;
        let (l0, l1, l2) = (p0 / sum, p1 / sum, p2 / sum);
        // ...and in the source triangle.
        let sb = &tri.source_bary;
        let b = [
            l0 * sb[0][0] + l1 * sb[1][0] + l2 * sb[2][0],
            l0 * sb[0][1] + l1 * sb[1][1] + l2 * sb[2][1],
            l0 * sb[0][2] + l1 * sb[1][2] + l2 * sb[2][2],
        ];
        let t = tri.triangle as usize;
        let [ia, ib, ic] = mesh.triangles[t].map(|i| i as usize);
        let material =
            &mesh.materials[mesh.triangle_materials.get(t).copied().unwrap_or(0) as usize];
        let mut albedo = material.albedo;
        if let Some(texture) = &material.texture
            && !mesh.uvs.is_empty()
        {
            let (ua, ub, uc) = (mesh.uvs[ia], mesh.uvs[ib], mesh.uvs[ic]);
            let u = b[0] * ua[0] + b[1] * ub[0] + b[2] * uc[0];
            let v = b[0] * ua[1] + b[1] * ub[1] + b[2] * uc[1];
            let tex = texture.sample(u, v);
            albedo = [albedo[0] * tex[0], albedo[1] * tex[1], albedo[2] * tex[2]];
        }
        let mut specular = material.specular;
        let n_mesh = mesh.normals[ia] * b[0] + mesh.normals[ib] * b[1] + mesh.normals[ic] * b[2];
        if !inst.decals.is_empty() {
            let p = Point3::from(
                mesh.positions[ia].coords * b[0]
                    + mesh.positions[ib].coords * b[1]
                    + mesh.positions[ic].coords * b[2],
            );
            for d in inst.decals {
                if d.covers(&p, &n_mesh) {
                    albedo = d.color;
                    specular = d.specular;
                }
            }
        }
        let mut n = inst.rotation * n_mesh;
        let len = n.norm();
        n = if len > 0.0 { n / len } else { Vector3::z() };
        let position = inst.camera_positions[ia] * b[0]
            + inst.camera_positions[ib] * b[1]
            + inst.camera_positions[ic] * b[2];
        let view = -position.normalize();
        if n.dot(&view) < 0.0 {
            n = -n;
        }
        let mut out = [
            albedo[0] * self.ambient[0],
            albedo[1] * self.ambient[1],
            albedo[2] * self.ambient[2],
        ];
        for (dir, color) in self.lights {
            let diffuse = n.dot(dir).max(0.0);
            if diffuse <= 0.0 {
                continue;
            }
            let half = (dir + view).normalize();
            let spec = specular * n.dot(&half).max(0.0).powf(material.shininess);
            for c in 0..3 {
                out[c] += (albedo[c] * diffuse + spec) * color[c];
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{Material, MeshBuilder};
    use omniscan_core::geometry::look_at;

    fn unit_box(color: [f32; 3]) -> Mesh {
        let mut b = MeshBuilder::new(Material::color(color));
        b.cuboid(Point3::new(-0.5, -0.5, -0.5), Point3::new(0.5, 0.5, 0.5), 0);
        b.finish()
    }

    fn camera() -> (Intrinsics, Isometry3<f64>) {
        let k = Intrinsics {
            width: 64,
            height: 48,
            fx: 60.0,
            fy: 60.0,
            cx: 32.0,
            cy: 24.0,
        };
        let pose = look_at(
            &Point3::new(0.0, 0.0, -5.0),
            &Point3::origin(),
            &Vector3::y(),
        );
        (k, pose)
    }

    fn lighting() -> Lighting {
        Lighting {
            ambient: [0.3; 3],
            lights: vec![Light {
                direction: Vector3::new(0.0, 0.0, -1.0),
                color: [0.7; 3],
            }],
        }
    }

    #[test]
    fn box_depth_and_silhouette_match_closed_form() {
        let mesh = unit_box([0.8, 0.2, 0.2]);
        let (k, pose) = camera();
        let inst = [Instance {
            mesh: &mesh,
            to_world: Isometry3::identity(),
            label: Label::Object,
            decals: &[],
        }];
        let view = render(&inst, &lighting(), &k, &pose, 1);
        // The front face is at distance 4.5 from the camera; it spans ±0.5 m,
        // i.e. ±60·0.5/4.5 = ±6.67 px around the centre.
        let centre = (24 * 64 + 32) as usize;
        assert_eq!(view.labels[centre], Label::Object);
        assert!(
            (view.depth[centre] - 4.5).abs() < 1e-4,
            "{}",
            view.depth[centre]
        );
        let covered = view.labels.iter().filter(|&&l| l == Label::Object).count();
        let expected = (2.0f32 * 60.0 * 0.5 / 4.5).powi(2);
        assert!(
            (covered as f32 - expected).abs() < 30.0,
            "{covered} vs {expected}"
        );
        // Lit face: ambient + full diffuse + the specular peak (light and view coincide).
        let r = view.rgb[centre * 3] as f32 / 255.0;
        assert!((r - (0.8 * (0.3 + 0.7) + 0.15 * 0.7)).abs() < 0.01, "{r}");
        assert_eq!(view.labels[0], Label::Scene);
        assert_eq!(view.depth[0], 0.0);
    }

    #[test]
    fn every_supersampling_puts_the_silhouette_in_the_same_place() {
        // A box in the image's lower right, where tiles that resolve into
        // the wrong pixels would have moved it most.
        let mesh = unit_box([0.8, 0.2, 0.2]);
        let (k, pose) = camera();
        let inst = [Instance {
            mesh: &mesh,
            to_world: Isometry3::translation(-1.2, -0.8, 0.0),
            label: Label::Object,
            decals: &[],
        }];
        let silhouette = |ss: u32| {
            let view = render(&inst, &lighting(), &k, &pose, ss);
            let (mut n, mut sx, mut sy) = (0.0, 0.0, 0.0);
            for (i, l) in view.labels.iter().enumerate() {
                if *l == Label::Object {
                    n += 1.0;
                    sx += (i % 64) as f64;
                    sy += (i / 64) as f64;
                }
            }
            (n, sx / n, sy / n)
        };
        let (n1, x1, y1) = silhouette(1);
        assert!(
            x1 > 40.0 && y1 > 30.0,
            "the box should sit lower right: {x1}, {y1}"
        );
        for ss in 2..=4 {
            let (n, x, y) = silhouette(ss);
            // Even supersampling has ties at the edges (two of four
            // samples), which move the count and the centroid a little.
            assert!(
                (n - n1).abs() < 0.15 * n1,
                "supersample {ss}: {n} pixels against {n1}"
            );
            assert!(
                (x - x1).abs() < 0.5 && (y - y1).abs() < 0.5,
                "supersample {ss}: centroid ({x}, {y}) against ({x1}, {y1})"
            );
        }
    }

    #[test]
    fn nearer_mesh_wins_and_clipping_keeps_geometry_behind_the_camera_out() {
        let near = unit_box([0.0, 1.0, 0.0]);
        let far = unit_box([1.0, 0.0, 0.0]);
        let (k, pose) = camera();
        let inst = [
            Instance {
                mesh: &far,
                to_world: Isometry3::translation(0.0, 0.0, 1.0),
                label: Label::Scene,
                decals: &[],
            },
            Instance {
                mesh: &near,
                to_world: Isometry3::translation(0.0, 0.0, -1.0),
                label: Label::Gripper,
                decals: &[],
            },
        ];
        let view = render(&inst, &lighting(), &k, &pose, 2);
        let centre = (24 * 64 + 32) as usize;
        assert_eq!(view.labels[centre], Label::Gripper);
        assert!((view.depth[centre] - 3.5).abs() < 1e-3);
        // A box around the camera: its walls cross the near plane and are
        // clipped; what remains is the wall 0.5 m ahead, over the whole image.
        let around = [Instance {
            mesh: &far,
            to_world: Isometry3::translation(0.0, 0.0, -5.0),
            label: Label::Arm,
            decals: &[],
        }];
        let view = render(&around, &lighting(), &k, &pose, 2);
        assert!(view.labels.iter().all(|&l| l == Label::Arm));
        assert!(
            (view.depth[centre] - 0.5).abs() < 1e-3,
            "{}",
            view.depth[centre]
        );
        assert!(view.depth.iter().all(|&d| d > 0.0 && d < 0.8));
    }
}
