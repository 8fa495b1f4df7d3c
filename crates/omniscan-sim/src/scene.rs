//! The static surroundings of the scan: a wooden table, the robot's torso, a
//! wall with posters and a pegboard, some clutter, and the lights. None of it
//! is a plain colour, so that masking cannot get away with colour keying.

use std::sync::Arc;

use nalgebra::{Point3, Vector3};

use crate::canvas::Canvas;
use crate::gripper::cylinder;
use crate::mesh::{Material, Mesh, MeshBuilder};
use crate::raster::{Light, Lighting};

/// The static scene as one mesh in world coordinates (robot base frame).
pub fn scene_mesh(seed: u64) -> Mesh {
    let mut wood = Canvas::new(512, 512, [0.56, 0.40, 0.25]);
    wood.noise(seed ^ 0x11, 0.25, 64);
    wood.noise(seed ^ 0x12, 0.12, 4);
    for i in 0..24 {
        let u = (i as f32 * 0.137).fract();
        wood.rect(u, 0.0, u + 0.004, 1.0, [0.42, 0.29, 0.17]);
    }
    let mut b = MeshBuilder::new(
        Material::textured(Arc::new(wood.into_texture())).with_specular(0.2, 12.0),
    );
    // Table top at z = 0, UVs repeating every 0.4 m.
    let (x0, x1, y0, y1) = (-0.4f32, 1.6f32, -1.2f32, 1.2f32);
    b.grid(8, 8, 0, |s, t| {
        let (x, y) = (x0 + (x1 - x0) * s, y0 + (y1 - y0) * t);
        (Point3::new(x, y, 0.0), [x / 0.4, y / 0.4])
    });

    let mut wall = Canvas::new(1024, 512, [0.80, 0.78, 0.72]);
    wall.noise(seed ^ 0x21, 0.06, 32);
    for j in 0..24 {
        for i in 0..48 {
            wall.disc(
                (i as f32 + 0.5) / 48.0,
                (j as f32 + 0.5) / 24.0,
                0.0015,
                [0.55, 0.52, 0.47],
            );
        }
    }
    let posters = [
        (0.05, 0.45, 0.22, 0.85, [0.20, 0.35, 0.60]),
        (0.30, 0.55, 0.42, 0.92, [0.85, 0.70, 0.20]),
        (0.58, 0.40, 0.78, 0.80, [0.25, 0.55, 0.35]),
        (0.84, 0.50, 0.97, 0.88, [0.75, 0.25, 0.20]),
    ];
    for (k, &(u0, v0, u1, v1, color)) in posters.iter().enumerate() {
        wall.rect(u0, v0, u1, v1, color);
        wall.rect(
            u0 + 0.01,
            v0 + 0.03,
            u1 - 0.01,
            v0 + 0.12,
            [0.95, 0.95, 0.93],
        );
        wall.text(
            ["SAFETY FIRST", "CELL 4 QA", "LOT 1187", "5S AUDIT"][k],
            u0 + 0.012,
            v1 - 0.09,
            0.05,
            [0.97, 0.97, 0.95],
        );
    }
    let wall_material =
        b.add_material(Material::textured(Arc::new(wall.into_texture())).with_specular(0.05, 8.0));
    // The wall behind the robot, 2.4 m wide, 1.6 m tall.
    b.grid(8, 4, wall_material, |s, t| {
        (Point3::new(-0.45, -1.2 + 2.4 * s, 1.6 * t), [s, t])
    });

    let mut body = Canvas::new(256, 256, [0.88, 0.88, 0.86]);
    body.noise(seed ^ 0x31, 0.05, 16);
    body.rect(0.3, 0.55, 0.7, 0.85, [0.25, 0.25, 0.27]);
    body.text("YUMI", 0.38, 0.65, 0.1, [0.9, 0.9, 0.9]);
    body.rect(0.0, 0.1, 1.0, 0.14, [0.95, 0.75, 0.1]);
    let body_material =
        b.add_material(Material::textured(Arc::new(body.into_texture())).with_specular(0.25, 20.0));
    b.cuboid(
        Point3::new(-0.22, -0.14, 0.0),
        Point3::new(0.10, 0.14, 0.55),
        body_material,
    );

    let mut card = Canvas::new(256, 256, [0.68, 0.52, 0.33]);
    card.noise(seed ^ 0x41, 0.1, 8);
    card.rect(0.0, 0.45, 1.0, 0.55, [0.85, 0.80, 0.60]);
    card.text("FRAGILE 12", 0.1, 0.7, 0.1, [0.15, 0.12, 0.1]);
    let card_material =
        b.add_material(Material::textured(Arc::new(card.into_texture())).with_specular(0.02, 4.0));
    b.cuboid(
        Point3::new(0.55, 0.28, 0.0),
        Point3::new(0.75, 0.46, 0.16),
        card_material,
    );
    b.cuboid(
        Point3::new(0.20, -0.50, 0.0),
        Point3::new(0.34, -0.36, 0.22),
        card_material,
    );
    let mug = b.add_material(Material::color([0.72, 0.12, 0.10]).with_specular(0.5, 40.0));
    let start = b.mesh.positions.len();
    cylinder(&mut b, 0.04, 0.0, 0.10, 40, mug);
    for p in &mut b.mesh.positions[start..] {
        *p += Vector3::new(0.62, -0.30, 0.0);
    }
    let mut mesh = b.finish();
    mesh.compute_normals();
    mesh
}

/// Fixed studio-like lighting: a key light from the upper front left, a fill
/// light from the right, and ambient light.
pub fn lighting() -> Lighting {
    Lighting {
        ambient: [0.30, 0.30, 0.31],
        lights: vec![
            Light {
                direction: Vector3::new(0.55, 0.45, 0.70).normalize(),
                color: [0.62, 0.60, 0.56],
            },
            Light {
                direction: Vector3::new(0.30, -0.80, 0.35).normalize(),
                color: [0.22, 0.23, 0.26],
            },
        ],
    }
}
