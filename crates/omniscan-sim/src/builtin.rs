//! Built-in procedural objects of the paper's kind (rigid, 3-10 cm) with real
//! surface detail: printed text-like marks and patterns, ridges, knurling,
//! holes, slots and notches, so that reconstruction and inspection have
//! something to resolve. Units are metres; each object is centred on its
//! bounding box.

use std::f32::consts::{PI, TAU};
use std::sync::Arc;

use nalgebra::{Point3, Vector3};

use crate::canvas::Canvas;
use crate::mesh::{Material, Mesh, MeshBuilder};

/// Names accepted after `builtin:`.
pub const BUILTIN_OBJECTS: [&str; 5] = [
    "flashlight",
    "t_connector",
    "wire_connector",
    "l_bracket",
    "remote",
];

/// Builds the built-in object `name`, or `None` if there is no such object.
pub fn builtin_object(name: &str) -> Option<Mesh> {
    let mut mesh = match name {
        "flashlight" => flashlight(),
        "t_connector" => t_connector(),
        "wire_connector" => wire_connector(),
        "l_bracket" => l_bracket(),
        "remote" => remote(),
        _ => return None,
    };
    mesh.compute_normals();
    let (lo, hi) = mesh.bounds();
    let centre = (lo.coords + hi.coords) * 0.5;
    mesh.scale_translate(1.0, -centre);
    Some(mesh)
}

/// Revolves the (radius, z) polyline `profile` about z. `displace(angle, z)`
/// adds to the radius; v runs with z over [z_min, z_max].
fn lathe(
    b: &mut MeshBuilder,
    profile: &[(f32, f32)],
    segments: usize,
    material: u16,
    displace: impl Fn(f32, f32) -> f32,
) {
    // Resample the profile to at most 0.4 mm steps so ridges are resolved.
    let mut pts = vec![profile[0]];
    for w in profile.windows(2) {
        let (a, c) = (w[0], w[1]);
        let len = ((c.0 - a.0).powi(2) + (c.1 - a.1).powi(2)).sqrt();
        let n = (len / 0.0004).ceil().max(1.0) as usize;
        for i in 1..=n {
            let s = i as f32 / n as f32;
            pts.push((a.0 + (c.0 - a.0) * s, a.1 + (c.1 - a.1) * s));
        }
    }
    let z_min = pts.iter().map(|p| p.1).fold(f32::INFINITY, f32::min);
    let z_max = pts.iter().map(|p| p.1).fold(f32::NEG_INFINITY, f32::max);
    let base = b.mesh.positions.len() as u32;
    for &(r, z) in &pts {
        for s in 0..=segments {
            let angle = TAU * (s % segments) as f32 / segments as f32;
            let radius = if r > 0.0 {
                (r + displace(angle, z)).max(0.0)
            } else {
                0.0
            };
            let p = Point3::new(radius * angle.cos(), radius * angle.sin(), z);
            b.vertex(
                p,
                Vector3::z(),
                [s as f32 / segments as f32, (z - z_min) / (z_max - z_min)],
            );
        }
    }
    let row = (segments + 1) as u32;
    for j in 0..(pts.len() - 1) as u32 {
        for i in 0..segments as u32 {
            let a = base + j * row + i;
            b.quad(a, a + 1, a + row + 1, a + row, material);
        }
    }
}

fn textured(canvas: Canvas, specular: f32, shininess: f32) -> Material {
    Material::textured(Arc::new(canvas.into_texture())).with_specular(specular, shininess)
}

fn flashlight() -> Mesh {
    let mut c = Canvas::new(512, 512, [0.10, 0.16, 0.38]);
    c.noise(11, 0.08, 24);
    // v = 0 at the tail (z = -48 mm), 1 at the lens (z = +48 mm).
    let v = |z_mm: f32| (z_mm + 48.0) / 96.0;
    c.rect(0.0, v(-48.0), 1.0, v(-40.0), [0.08, 0.08, 0.09]);
    c.rect(0.0, v(12.0), 1.0, v(48.0), [0.07, 0.07, 0.08]);
    c.rect(0.0, v(45.5), 1.0, v(48.0), [0.85, 0.86, 0.88]);
    c.rect(0.05, v(-30.0), 0.5, v(-29.0), [0.9, 0.9, 0.9]);
    c.text("OMNI LED 300LM", 0.55, v(-14.0), 0.035, [0.95, 0.95, 0.95]);
    c.text("IPX4 CR123", 0.55, v(-24.0), 0.025, [0.85, 0.7, 0.2]);
    c.disc(0.25, v(8.0), 0.018, [0.8, 0.1, 0.1]);
    c.stripes(0.125, 0.3, [0.80, 0.80, 0.83], [0.0, v(2.0), 1.0, v(3.0)]);
    let mut b = MeshBuilder::new(textured(c, 0.35, 32.0));
    let profile = [
        (0.0, -0.048),
        (0.0105, -0.048),
        (0.0115, -0.047),
        (0.0115, -0.040),
        (0.0108, -0.040),
        (0.0108, -0.0385),
        (0.0120, -0.0385),
        (0.0120, 0.012),
        (0.0125, 0.014),
        (0.0160, 0.030),
        (0.0165, 0.030),
        (0.0165, 0.046),
        (0.0160, 0.048),
        (0.0135, 0.048),
        (0.0135, 0.0445),
        (0.0, 0.0445),
    ];
    lathe(&mut b, &profile, 128, 0, |angle, z| {
        let mut dr = 0.0;
        if (-0.030..0.0).contains(&z) {
            // Knurled grip.
            dr += 0.0005 * ((30.0 * angle).cos() * 4.0).clamp(-1.0, 1.0).max(0.0);
        }
        if (0.033..0.044).contains(&z) && ((z - 0.033) / 0.002).fract() < 0.5 {
            // Cooling rings on the head.
            dr += 0.0006;
        }
        if (0.004..0.011).contains(&z) && (angle - PI * 0.5).abs() < 0.28 {
            // The switch.
            dr += 0.0013;
        }
        dr
    });
    b.finish()
}

fn t_connector() -> Mesh {
    let mut c = Canvas::new(512, 512, [0.93, 0.93, 0.89]);
    c.noise(23, 0.05, 16);
    c.text("PVC SCH 40 NSF", 0.08, 0.52, 0.05, [0.15, 0.25, 0.65]);
    c.text("3/4 IN 480 PSI", 0.58, 0.46, 0.04, [0.15, 0.25, 0.65]);
    c.rect(0.0, 0.78, 1.0, 0.80, [0.75, 0.15, 0.12]);
    let mut b = MeshBuilder::new(textured(c, 0.25, 28.0));
    let main = [
        (0.0110, -0.036),
        (0.0150, -0.036),
        (0.0150, -0.024),
        (0.0135, -0.022),
        (0.0135, 0.022),
        (0.0150, 0.024),
        (0.0150, 0.036),
        (0.0110, 0.036),
        (0.0110, -0.036),
    ];
    let start = b.mesh.positions.len();
    lathe(&mut b, &main, 96, 0, |_, z| {
        if (0.026..0.034).contains(&z.abs()) && ((z.abs() - 0.026) / 0.002).fract() < 0.5 {
            0.0004
        } else {
            0.0
        }
    });
    // The main run lies along x.
    for p in &mut b.mesh.positions[start..] {
        *p = Point3::new(p.z, p.y, -p.x);
    }
    let branch = [
        (0.0110, 0.0),
        (0.0135, 0.0),
        (0.0135, 0.018),
        (0.0150, 0.020),
        (0.0150, 0.040),
        (0.0110, 0.040),
        (0.0110, 0.0),
    ];
    let start = b.mesh.positions.len();
    lathe(&mut b, &branch, 96, 0, |angle, z| {
        if (0.008..0.016).contains(&z) && (angle - PI).abs() < 0.12 {
            -0.0007
        } else {
            0.0
        }
    });
    for uv in &mut b.mesh.uvs[start..] {
        uv[1] = 0.7 + uv[1] * 0.3;
    }
    b.finish()
}

/// A box whose six faces are grids displaced along their outward normals.
/// Face k uses atlas cell (k % 3, k / 3) of the texture.
struct DisplacedBox {
    half: Vector3<f32>,
    cell: f32,
}

impl DisplacedBox {
    fn faces() -> [(Vector3<f32>, Vector3<f32>, Vector3<f32>); 6] {
        let (x, y, z) = (Vector3::x(), Vector3::y(), Vector3::z());
        [
            (x, y, z),
            (-x, -y, z),
            (y, -x, z),
            (-y, x, z),
            (z, x, y),
            (-z, x, -y),
        ]
    }

    fn extents(&self, k: usize) -> (f32, f32, f32) {
        let (n, t1, t2) = Self::faces()[k];
        let h = self.half;
        let e = |v: Vector3<f32>| v.x.abs() * h.x + v.y.abs() * h.y + v.z.abs() * h.z;
        (e(n), e(t1), e(t2))
    }

    /// UV of face coordinates (a, b) in metres from the face centre.
    fn uv(&self, k: usize, a: f32, b: f32) -> [f32; 2] {
        let (_, e1, e2) = self.extents(k);
        let (col, row) = ((k % 3) as f32, (k / 3) as f32);
        [
            (col + (a + e1) / (2.0 * e1)) / 3.0,
            (row + (b + e2) / (2.0 * e2)) / 2.0,
        ]
    }

    fn build(&self, b: &mut MeshBuilder, material: u16, displace: impl Fn(usize, f32, f32) -> f32) {
        for (k, (n, t1, t2)) in Self::faces().into_iter().enumerate() {
            let (en, e1, e2) = self.extents(k);
            let nu = (2.0 * e1 / self.cell).round().max(1.0) as usize;
            let nv = (2.0 * e2 / self.cell).round().max(1.0) as usize;
            b.grid(nu, nv, material, |s, t| {
                let (a, bb) = (-e1 + 2.0 * e1 * s, -e2 + 2.0 * e2 * t);
                let d = displace(k, a, bb);
                (
                    Point3::from(n * (en + d) + t1 * a + t2 * bb),
                    self.uv(k, a, bb),
                )
            });
        }
    }

    /// Paints the face rectangle from corner `from` to corner `to` (face coordinates, metres).
    fn paint_rect(&self, c: &mut Canvas, k: usize, from: [f32; 2], to: [f32; 2], color: [f32; 3]) {
        let p = self.uv(k, from[0], from[1]);
        let q = self.uv(k, to[0], to[1]);
        c.rect(p[0], p[1], q[0], q[1], color);
    }

    fn paint_text(
        &self,
        c: &mut Canvas,
        k: usize,
        text: &str,
        at: [f32; 2],
        height_m: f32,
        color: [f32; 3],
    ) {
        let (_, _, e2) = self.extents(k);
        let p = self.uv(k, at[0], at[1]);
        c.text(text, p[0], p[1], height_m / (2.0 * e2) / 2.0, color);
    }
}

fn wire_connector() -> Mesh {
    let shape = DisplacedBox {
        half: Vector3::new(0.020, 0.010, 0.0085),
        cell: 0.0005,
    };
    let poles = [-0.0062f32, 0.0, 0.0062];
    let mut c = Canvas::new(768, 512, [0.78, 0.80, 0.80]);
    c.noise(31, 0.04, 12);
    for y in poles {
        // Orange levers on the top face (face 4: a = x, b = y).
        shape.paint_rect(
            &mut c,
            4,
            [-0.019, y - 0.0022],
            [0.008, y + 0.0022],
            [0.95, 0.48, 0.08],
        );
        shape.paint_rect(
            &mut c,
            0,
            [y - 0.0021, -0.0041],
            [y + 0.0021, 0.0001],
            [0.12, 0.12, 0.12],
        );
    }
    shape.paint_text(
        &mut c,
        2,
        "221-413 32A",
        [-0.015, -0.003],
        0.0035,
        [0.1, 0.1, 0.1],
    );
    shape.paint_text(
        &mut c,
        3,
        "0.2-4MM2 450V",
        [-0.016, -0.002],
        0.0030,
        [0.1, 0.1, 0.1],
    );
    shape.paint_text(&mut c, 1, "CE", [-0.004, -0.003], 0.004, [0.2, 0.2, 0.2]);
    shape.paint_text(
        &mut c,
        4,
        "L1 N PE",
        [0.010, -0.006],
        0.0025,
        [0.15, 0.15, 0.15],
    );
    let mut b = MeshBuilder::new(textured(c, 0.3, 30.0));
    shape.build(&mut b, 0, |k, a, bb| {
        match k {
            // Front face: three square wire entries, 10 mm deep.
            0 if poles.iter().any(|&y| (a - y).abs() < 0.0020) && (-0.0040..0.0).contains(&bb) => {
                -0.010
            }
            // Top face: levers with a notch, test ports.
            4 => {
                let on_lever = poles.iter().any(|&y| (bb - y).abs() < 0.0021);
                if on_lever && (-0.0185..0.0075).contains(&a) && !(-0.003..-0.0015).contains(&a) {
                    0.0018
                } else if poles.iter().any(|&y| (bb - y).abs() < 0.0008)
                    && (0.0125..0.0145).contains(&a)
                {
                    -0.003
                } else {
                    0.0
                }
            }
            _ => 0.0,
        }
    });
    b.finish()
}

/// A flat plate cut from an occupancy grid: `size` (metres) in x and y,
/// `thickness` along z, square cells of `cell` metres, texture coordinates
/// spanning `uv_rect` = [u0, v0, u1, v1].
struct Plate {
    size: (f32, f32),
    thickness: f32,
    cell: f32,
    material: u16,
    uv_rect: [f32; 4],
}

/// Extrudes the cells where `occupied(x, y)` holds into the plate, with walls
/// wherever occupancy changes, and moves it into place with `place`.
fn extruded_plate(
    b: &mut MeshBuilder,
    plate: &Plate,
    occupied: impl Fn(f32, f32) -> bool,
    place: impl Fn(Point3<f32>) -> Point3<f32>,
) {
    let Plate {
        size,
        thickness,
        cell,
        material,
        uv_rect,
    } = *plate;
    let nx = (size.0 / cell).round() as i32;
    let ny = (size.1 / cell).round() as i32;
    let occ = |i: i32, j: i32| {
        i >= 0
            && j >= 0
            && i < nx
            && j < ny
            && occupied((i as f32 + 0.5) * cell, (j as f32 + 0.5) * cell)
    };
    let uv = |x: f32, y: f32| {
        [
            uv_rect[0] + (uv_rect[2] - uv_rect[0]) * x / size.0,
            uv_rect[1] + (uv_rect[3] - uv_rect[1]) * y / size.1,
        ]
    };
    let quad = |b: &mut MeshBuilder, corners: [Point3<f32>; 4], uvs: [[f32; 2]; 4]| {
        let ids: Vec<u32> = corners
            .iter()
            .zip(uvs)
            .map(|(p, t)| b.vertex(place(*p), Vector3::z(), t))
            .collect();
        b.quad(ids[0], ids[1], ids[2], ids[3], material);
    };
    for j in 0..ny {
        for i in 0..nx {
            if !occ(i, j) {
                continue;
            }
            let (x0, y0) = (i as f32 * cell, j as f32 * cell);
            let (x1, y1) = (x0 + cell, y0 + cell);
            let t = thickness;
            let p = |x: f32, y: f32, z: f32| Point3::new(x, y, z);
            quad(
                b,
                [p(x0, y0, t), p(x1, y0, t), p(x1, y1, t), p(x0, y1, t)],
                [uv(x0, y0), uv(x1, y0), uv(x1, y1), uv(x0, y1)],
            );
            quad(
                b,
                [
                    p(x0, y1, 0.0),
                    p(x1, y1, 0.0),
                    p(x1, y0, 0.0),
                    p(x0, y0, 0.0),
                ],
                [uv(x0, y1), uv(x1, y1), uv(x1, y0), uv(x0, y0)],
            );
            let edge_uv = [uv(x0, y0); 4];
            if !occ(i - 1, j) {
                quad(
                    b,
                    [p(x0, y1, 0.0), p(x0, y0, 0.0), p(x0, y0, t), p(x0, y1, t)],
                    edge_uv,
                );
            }
            if !occ(i + 1, j) {
                quad(
                    b,
                    [p(x1, y0, 0.0), p(x1, y1, 0.0), p(x1, y1, t), p(x1, y0, t)],
                    edge_uv,
                );
            }
            if !occ(i, j - 1) {
                quad(
                    b,
                    [p(x0, y0, 0.0), p(x1, y0, 0.0), p(x1, y0, t), p(x0, y0, t)],
                    edge_uv,
                );
            }
            if !occ(i, j + 1) {
                quad(
                    b,
                    [p(x1, y1, 0.0), p(x0, y1, 0.0), p(x0, y1, t), p(x1, y1, t)],
                    edge_uv,
                );
            }
        }
    }
}

fn l_bracket() -> Mesh {
    let mut c = Canvas::new(512, 512, [0.70, 0.72, 0.75]);
    c.noise(41, 0.10, 3);
    c.noise(42, 0.05, 40);
    c.text("L50 ZN", 0.08, 0.30, 0.05, [0.35, 0.36, 0.38]);
    c.text("M5 2024", 0.60, 0.80, 0.04, [0.35, 0.36, 0.38]);
    c.rect(0.70, 0.10, 0.95, 0.14, [0.55, 0.50, 0.20]);
    let mut b = MeshBuilder::new(textured(c, 0.5, 40.0));
    let (len, depth, height, t) = (0.050f32, 0.026f32, 0.036f32, 0.003f32);
    let hole =
        |x: f32, y: f32, cx: f32, cy: f32, r: f32| (x - cx).powi(2) + (y - cy).powi(2) < r * r;
    // Base plate (x along the length, y across), with two round holes and a corner notch.
    extruded_plate(
        &mut b,
        &Plate {
            size: (len, depth),
            thickness: t,
            cell: 0.0005,
            material: 0,
            uv_rect: [0.0, 0.0, 0.5, 1.0],
        },
        |x, y| {
            !(hole(x, y, 0.012, 0.015, 0.0027)
                || hole(x, y, 0.038, 0.015, 0.0027)
                || (x > 0.044 && y > 0.020))
        },
        |p| p,
    );
    // Upright plate: a slot and a hole, standing at y = 0.
    extruded_plate(
        &mut b,
        &Plate {
            size: (len, height),
            thickness: t,
            cell: 0.0005,
            material: 0,
            uv_rect: [0.5, 0.0, 1.0, 1.0],
        },
        |x, z| {
            !(hole(x, z, 0.025, 0.028, 0.0025)
                || ((0.018..0.032).contains(&x) && (0.014..0.019).contains(&z)))
                && z > 0.0
        },
        |p| Point3::new(p.x, p.z, p.y + t),
    );
    b.finish()
}

fn remote() -> Mesh {
    let shape = DisplacedBox {
        half: Vector3::new(0.050, 0.022, 0.009),
        cell: 0.0006,
    };
    let grid: Vec<(f32, f32)> = (0..4)
        .flat_map(|i| [-0.012, 0.0, 0.012].map(|y| (-0.030 + 0.011 * i as f32, y)))
        .collect();
    let mut c = Canvas::new(768, 512, [0.11, 0.11, 0.12]);
    c.noise(51, 0.10, 6);
    let top = 4;
    let disc = |c: &mut Canvas, x: f32, y: f32, r: f32, color: [f32; 3]| {
        let uv = shape.uv(top, x, y);
        c.disc(uv[0], uv[1], r / (2.0 * 0.050) / 3.0, color);
    };
    for &(x, y) in &grid {
        disc(&mut c, x, y, 0.0032, [0.55, 0.55, 0.58]);
        shape.paint_text(
            &mut c,
            top,
            "1",
            [x - 0.0045, y - 0.0005],
            0.0015,
            [0.9, 0.9, 0.9],
        );
    }
    disc(&mut c, 0.040, 0.012, 0.0042, [0.80, 0.10, 0.10]);
    disc(&mut c, 0.022, 0.0, 0.0100, [0.30, 0.30, 0.33]);
    disc(&mut c, 0.022, 0.0, 0.0060, [0.11, 0.11, 0.12]);
    disc(&mut c, 0.022, 0.0, 0.0040, [0.55, 0.55, 0.58]);
    shape.paint_text(
        &mut c,
        top,
        "VOL CH MENU",
        [-0.045, 0.015],
        0.0025,
        [0.9, 0.9, 0.9],
    );
    shape.paint_text(
        &mut c,
        5,
        "MODEL RC-55",
        [-0.030, -0.004],
        0.004,
        [0.7, 0.7, 0.7],
    );
    shape.paint_rect(
        &mut c,
        0,
        [-0.008, -0.003],
        [0.008, 0.003],
        [0.35, 0.05, 0.05],
    );
    let mut b = MeshBuilder::new(textured(c, 0.3, 36.0));
    shape.build(&mut b, 0, |k, a, bb| {
        let near = |x: f32, y: f32, r: f32| (a - x).powi(2) + (bb - y).powi(2) < r * r;
        match k {
            4 => {
                if grid.iter().any(|&(x, y)| near(x, y, 0.0032))
                    || near(0.040, 0.012, 0.0042)
                    || near(0.022, 0.0, 0.0040)
                {
                    0.0015
                } else if near(0.022, 0.0, 0.0100) && !near(0.022, 0.0, 0.0060) {
                    0.0010
                } else {
                    0.0
                }
            }
            5 => {
                // Battery-cover seam, a groove on the back.
                let inside = (-0.040..0.0).contains(&a) && bb.abs() < 0.016;
                let inner = (-0.0392..-0.0008).contains(&a) && bb.abs() < 0.0152;
                if inside && !inner { -0.0006 } else { 0.0 }
            }
            0 if a.abs() < 0.008 && bb.abs() < 0.003 => -0.0006,
            _ => 0.0,
        }
    });
    b.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtins_are_paper_sized_and_centred() {
        for name in BUILTIN_OBJECTS {
            let mesh = builtin_object(name).unwrap();
            let (lo, hi) = mesh.bounds();
            let extent = hi - lo;
            let diagonal = extent.norm();
            // Does not fit a 3 cm sphere, fits a 10 cm one (paper, problem statement)...
            assert!(diagonal > 0.03, "{name}: {diagonal}");
            assert!(extent.max() <= 0.105, "{name}: {extent:?}");
            // ...and is centred on its bounding box.
            assert!(((lo.coords + hi.coords) * 0.5).norm() < 1e-6, "{name}");
            assert!(
                mesh.triangles.len() > 5_000,
                "{name} lacks detail: {} triangles",
                mesh.triangles.len()
            );
            assert!(mesh.materials[0].texture.is_some());
        }
        assert!(builtin_object("teapot").is_none());
    }
}
