//! Triangle meshes with normals, texture coordinates and materials: the
//! geometry the simulator renders (objects, grippers, the scene).

use std::collections::HashMap;
use std::sync::Arc;

use nalgebra::{Point3, Vector3};

/// An RGB texture with values in [0, 1], sampled bilinearly with wrap-around.
#[derive(Debug, Clone, PartialEq)]
pub struct Texture {
    pub width: u32,
    pub height: u32,
    pub texels: Vec<[f32; 3]>,
}

impl Texture {
    pub fn from_rgb8(width: u32, height: u32, data: &[u8]) -> Texture {
        let texels = data
            .chunks_exact(3)
            .map(|c| {
                [
                    c[0] as f32 / 255.0,
                    c[1] as f32 / 255.0,
                    c[2] as f32 / 255.0,
                ]
            })
            .collect();
        Texture {
            width,
            height,
            texels,
        }
    }

    /// Bilinear sample at texture coordinates (u, v), v = 0 at the bottom (OBJ convention).
    #[inline]
    pub fn sample(&self, u: f32, v: f32) -> [f32; 3] {
        let (w, h) = (self.width as f32, self.height as f32);
        let x = (u - u.floor()) * w - 0.5;
        let y = (1.0 - (v - v.floor())) * h - 0.5;
        let x0 = x.floor();
        let y0 = y.floor();
        let fx = x - x0;
        let fy = y - y0;
        let wrap = |i: f32, n: u32| -> usize { (i as i64).rem_euclid(n as i64) as usize };
        let (xa, xb) = (wrap(x0, self.width), wrap(x0 + 1.0, self.width));
        let (ya, yb) = (wrap(y0, self.height), wrap(y0 + 1.0, self.height));
        let row = self.width as usize;
        let t00 = self.texels[ya * row + xa];
        let t10 = self.texels[ya * row + xb];
        let t01 = self.texels[yb * row + xa];
        let t11 = self.texels[yb * row + xb];
        let mut out = [0.0; 3];
        for c in 0..3 {
            let top = t00[c] + (t10[c] - t00[c]) * fx;
            let bottom = t01[c] + (t11[c] - t01[c]) * fx;
            out[c] = top + (bottom - top) * fy;
        }
        out
    }
}

/// Surface appearance: a colour or texture, plus a Blinn-Phong specular lobe.
#[derive(Debug, Clone, PartialEq)]
pub struct Material {
    /// Diffuse colour, multiplied with the texture when there is one.
    pub albedo: [f32; 3],
    pub texture: Option<Arc<Texture>>,
    /// Specular strength in [0, 1].
    pub specular: f32,
    /// Blinn-Phong exponent.
    pub shininess: f32,
}

impl Material {
    pub fn color(albedo: [f32; 3]) -> Material {
        Material {
            albedo,
            texture: None,
            specular: 0.15,
            shininess: 24.0,
        }
    }
    pub fn textured(texture: Arc<Texture>) -> Material {
        Material {
            albedo: [1.0; 3],
            texture: Some(texture),
            specular: 0.15,
            shininess: 24.0,
        }
    }
    pub fn with_specular(mut self, specular: f32, shininess: f32) -> Material {
        self.specular = specular;
        self.shininess = shininess;
        self
    }
}

/// A triangle mesh. `uvs` is empty or one per vertex; `triangle_materials`
/// indexes `materials` per triangle.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Mesh {
    pub positions: Vec<Point3<f32>>,
    pub normals: Vec<Vector3<f32>>,
    pub uvs: Vec<[f32; 2]>,
    pub triangles: Vec<[u32; 3]>,
    pub triangle_materials: Vec<u16>,
    pub materials: Vec<Material>,
}

impl Mesh {
    /// Axis-aligned bounds (min, max).
    pub fn bounds(&self) -> (Point3<f32>, Point3<f32>) {
        let mut lo = Point3::new(f32::INFINITY, f32::INFINITY, f32::INFINITY);
        let mut hi = Point3::new(f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY);
        for p in &self.positions {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        (lo, hi)
    }

    pub fn triangle(&self, t: usize) -> [Point3<f32>; 3] {
        let [a, b, c] = self.triangles[t];
        [
            self.positions[a as usize],
            self.positions[b as usize],
            self.positions[c as usize],
        ]
    }

    /// Area-weighted centroid of the surface.
    pub fn surface_centroid(&self) -> Point3<f64> {
        let mut sum = Vector3::zeros();
        let mut area = 0.0;
        for t in 0..self.triangles.len() {
            let [a, b, c] = self.triangle(t).map(|p| p.cast::<f64>());
            let w = (b - a).cross(&(c - a)).norm() * 0.5;
            sum += w * (a.coords + b.coords + c.coords) / 3.0;
            area += w;
        }
        if area > 0.0 {
            Point3::from(sum / area)
        } else {
            Point3::origin()
        }
    }

    /// Total surface area.
    pub fn area(&self) -> f64 {
        (0..self.triangles.len())
            .map(|t| {
                let [a, b, c] = self.triangle(t).map(|p| p.cast::<f64>());
                (b - a).cross(&(c - a)).norm() * 0.5
            })
            .sum()
    }

    /// Scales and translates every vertex.
    pub fn scale_translate(&mut self, scale: f32, offset: Vector3<f32>) {
        for p in &mut self.positions {
            *p = Point3::from(p.coords * scale + offset);
        }
        if scale < 0.0 {
            for t in &mut self.triangles {
                t.swap(1, 2);
            }
        }
    }

    /// Recomputes smooth vertex normals, area-weighted, shared between
    /// vertices at the same position (so UV seams do not show as creases).
    pub fn compute_normals(&mut self) {
        let mut by_position: HashMap<[u32; 3], Vector3<f32>> = HashMap::new();
        let key = |p: &Point3<f32>| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
        for t in &self.triangles {
            let [a, b, c] = t.map(|i| self.positions[i as usize]);
            let n = (b - a).cross(&(c - a));
            for v in [a, b, c] {
                *by_position.entry(key(&v)).or_insert_with(Vector3::zeros) += n;
            }
        }
        self.normals = self
            .positions
            .iter()
            .map(|p| {
                let n = by_position
                    .get(&key(p))
                    .copied()
                    .unwrap_or_else(Vector3::zeros);
                let len = n.norm();
                if len > 0.0 { n / len } else { Vector3::z() }
            })
            .collect();
    }

    /// Face normal of triangle `t` (unit, from the winding order).
    pub fn face_normal(&self, t: usize) -> Vector3<f32> {
        let [a, b, c] = self.triangle(t);
        let n = (b - a).cross(&(c - a));
        let len = n.norm();
        if len > 0.0 { n / len } else { Vector3::z() }
    }

    /// Distance from `p` to the nearest point of the surface (brute force).
    pub fn distance_to_surface(&self, p: &Point3<f32>) -> f32 {
        (0..self.triangles.len())
            .map(|t| distance_to_triangle(p, &self.triangle(t)))
            .fold(f32::INFINITY, f32::min)
    }

    /// Every crossing of the line `origin + s·direction` with the mesh, as
    /// (s, triangle) sorted by s (s may be negative).
    pub fn line_hits(&self, origin: &Point3<f64>, direction: &Vector3<f64>) -> Vec<(f64, usize)> {
        let mut hits = Vec::new();
        for t in 0..self.triangles.len() {
            let [a, b, c] = self.triangle(t).map(|p| p.cast::<f64>());
            let e1 = b - a;
            let e2 = c - a;
            let p = direction.cross(&e2);
            let det = e1.dot(&p);
            if det.abs() < 1e-18 {
                continue;
            }
            let inv = 1.0 / det;
            let s = origin - a;
            let u = s.dot(&p) * inv;
            if !(0.0..=1.0).contains(&u) {
                continue;
            }
            let q = s.cross(&e1);
            let v = direction.dot(&q) * inv;
            if v < 0.0 || u + v > 1.0 {
                continue;
            }
            hits.push((e2.dot(&q) * inv, t));
        }
        hits.sort_by(|x, y| x.0.total_cmp(&y.0));
        hits
    }
}

/// Distance from `p` to the triangle `t` (Ericson, Real-Time Collision Detection, 5.1.5).
pub fn distance_to_triangle(p: &Point3<f32>, t: &[Point3<f32>; 3]) -> f32 {
    let [a, b, c] = *t;
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(&ap), ac.dot(&ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return (p - a).norm();
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(&bp), ac.dot(&bp));
    if d3 >= 0.0 && d4 <= d3 {
        return (p - b).norm();
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (p - (a + ab * v)).norm();
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(&cp), ac.dot(&cp));
    if d6 >= 0.0 && d5 <= d6 {
        return (p - c).norm();
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (p - (a + ac * w)).norm();
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (p - (b + (c - b) * w)).norm();
    }
    let denom = 1.0 / (va + vb + vc);
    let (v, w) = (vb * denom, vc * denom);
    (p - (a + ab * v + ac * w)).norm()
}

/// Incremental builder for procedural meshes.
#[derive(Debug, Default)]
pub struct MeshBuilder {
    pub mesh: Mesh,
}

impl MeshBuilder {
    pub fn new(material: Material) -> MeshBuilder {
        MeshBuilder {
            mesh: Mesh {
                materials: vec![material],
                ..Default::default()
            },
        }
    }

    pub fn vertex(&mut self, p: Point3<f32>, n: Vector3<f32>, uv: [f32; 2]) -> u32 {
        self.mesh.positions.push(p);
        self.mesh.normals.push(n);
        self.mesh.uvs.push(uv);
        (self.mesh.positions.len() - 1) as u32
    }

    pub fn triangle(&mut self, a: u32, b: u32, c: u32, material: u16) {
        self.mesh.triangles.push([a, b, c]);
        self.mesh.triangle_materials.push(material);
    }

    pub fn quad(&mut self, a: u32, b: u32, c: u32, d: u32, material: u16) {
        self.triangle(a, b, c, material);
        self.triangle(a, c, d, material);
    }

    pub fn add_material(&mut self, m: Material) -> u16 {
        self.mesh.materials.push(m);
        (self.mesh.materials.len() - 1) as u16
    }

    /// A grid surface `f(s, t) -> (position, uv)` over `[0,1]²`, `nu` x `nv`
    /// cells, normals computed afterwards by [`Mesh::compute_normals`].
    pub fn grid(
        &mut self,
        nu: usize,
        nv: usize,
        material: u16,
        f: impl Fn(f32, f32) -> (Point3<f32>, [f32; 2]),
    ) {
        let base = self.mesh.positions.len() as u32;
        for j in 0..=nv {
            for i in 0..=nu {
                let (p, uv) = f(i as f32 / nu as f32, j as f32 / nv as f32);
                self.vertex(p, Vector3::z(), uv);
            }
        }
        let row = (nu + 1) as u32;
        for j in 0..nv as u32 {
            for i in 0..nu as u32 {
                let a = base + j * row + i;
                self.quad(a, a + 1, a + row + 1, a + row, material);
            }
        }
    }

    /// An axis-aligned box with per-face UVs covering the whole texture.
    pub fn cuboid(&mut self, min: Point3<f32>, max: Point3<f32>, material: u16) {
        let c = |x: usize, y: usize, z: usize| {
            Point3::new([min.x, max.x][x], [min.y, max.y][y], [min.z, max.z][z])
        };
        // Each face: four corners counter-clockwise seen from outside.
        let faces = [
            [c(1, 0, 0), c(1, 1, 0), c(1, 1, 1), c(1, 0, 1)],
            [c(0, 1, 0), c(0, 0, 0), c(0, 0, 1), c(0, 1, 1)],
            [c(1, 1, 0), c(0, 1, 0), c(0, 1, 1), c(1, 1, 1)],
            [c(0, 0, 0), c(1, 0, 0), c(1, 0, 1), c(0, 0, 1)],
            [c(0, 0, 1), c(1, 0, 1), c(1, 1, 1), c(0, 1, 1)],
            [c(0, 1, 0), c(1, 1, 0), c(1, 0, 0), c(0, 0, 0)],
        ];
        for f in faces {
            let n = (f[1] - f[0]).cross(&(f[2] - f[0])).normalize();
            let ids: Vec<u32> = f
                .iter()
                .zip([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
                .map(|(p, uv)| self.vertex(*p, n, uv))
                .collect();
            self.quad(ids[0], ids[1], ids[2], ids[3], material);
        }
    }

    pub fn finish(self) -> Mesh {
        self.mesh
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_cube_area_centroid_and_line_hits() {
        let mut b = MeshBuilder::new(Material::color([1.0; 3]));
        b.cuboid(Point3::new(-0.5, -0.5, -0.5), Point3::new(0.5, 0.5, 0.5), 0);
        let mesh = b.finish();
        assert!((mesh.area() - 6.0).abs() < 1e-9);
        assert!(mesh.surface_centroid().coords.norm() < 1e-9);
        let hits = mesh.line_hits(&Point3::new(0.1, 0.2, -3.0), &Vector3::z());
        let s: Vec<f64> = hits.iter().map(|h| h.0).collect();
        assert_eq!(s.len(), 2);
        assert!((s[0] - 2.5).abs() < 1e-9 && (s[1] - 3.5).abs() < 1e-9);
        // Outward normals: the face hit first faces the ray's origin.
        assert!(mesh.face_normal(hits[0].1).z < -0.99);
    }

    #[test]
    fn bilinear_texture_sampling() {
        let t = Texture {
            width: 2,
            height: 1,
            texels: vec![[0.0; 3], [1.0; 3]],
        };
        // Texel centres are at u = 0.25 and 0.75.
        assert!((t.sample(0.25, 0.5)[0] - 0.0).abs() < 1e-6);
        assert!((t.sample(0.5, 0.5)[0] - 0.5).abs() < 1e-6);
        assert!((t.sample(0.75, 0.5)[0] - 1.0).abs() < 1e-6);
    }
}
