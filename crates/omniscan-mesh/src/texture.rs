//! A baked colour texture: every pair of triangles gets a square cell of
//! the atlas (one triangle in each half, a gap along the diagonal), and
//! every texel the colour the fused volume holds at the surface point it
//! maps to, so the texture keeps colour detail finer than the decimated
//! mesh's vertices.
//!
//! A chart per triangle rather than a real unwrap: the crates that unwrap
//! (xatlas bindings) are unmaintained or need C++ toolchains we do not
//! otherwise build, and a simulator or CAD tool only needs the lookup to
//! be right. Each cell's texels all map onto its triangles (outside a
//! triangle, to its nearest edge point), so sampling never bleeds in a
//! neighbour's colour.

use rayon::prelude::*;

use crate::TriMesh;
use crate::fusion::Tsdf;

/// An RGB texture with a UV per triangle corner (glTF's convention: u to
/// the right, v down from the top-left corner, 0-1).
#[derive(Debug, Clone, PartialEq)]
pub struct Texture {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
    pub uvs: Vec<[[f32; 2]; 3]>,
}

/// Cell-local corners (0-1) of the two triangles of a cell, with the gap
/// `g` along the diagonal.
fn cell_corners(second: bool, g: f32) -> [[f32; 2]; 3] {
    if second {
        [[1.0, 1.0], [g, 1.0], [1.0, g]]
    } else {
        [[0.0, 0.0], [1.0 - g, 0.0], [0.0, 1.0 - g]]
    }
}

/// Bakes `mesh`'s colour from `tsdf` into a `side` x `side` texture (the
/// vertex colours where the volume has none).
pub fn bake(mesh: &TriMesh, tsdf: Option<&Tsdf>, side: u32) -> Texture {
    let cells = mesh.triangles.len().div_ceil(2).max(1);
    let per_row = (cells as f64).sqrt().ceil() as u32;
    let cell_px = (side / per_row).max(4);
    let side = (cell_px * per_row).max(side);
    // In cell-local units: half a texel of padding round the cell's edge,
    // a texel and a half of gap along its diagonal.
    let pad = 0.5 / cell_px as f32;
    let gap = 1.5 / cell_px as f32;
    let to_atlas = |cell: u32, local: [f32; 2]| {
        let (cx, cy) = ((cell % per_row) as f32, (cell / per_row) as f32);
        let l = local.map(|c| pad + c * (1.0 - 2.0 * pad));
        [
            (cx + l[0]) * cell_px as f32 / side as f32,
            (cy + l[1]) * cell_px as f32 / side as f32,
        ]
    };
    let uvs: Vec<[[f32; 2]; 3]> = (0..mesh.triangles.len())
        .map(|t| cell_corners(t % 2 == 1, gap).map(|c| to_atlas((t / 2) as u32, c)))
        .collect();
    let mut rgb = vec![0u8; (side * side * 3) as usize];
    rgb.par_chunks_mut((side * 3) as usize)
        .enumerate()
        .for_each(|(y, row)| {
            let cy = y as u32 / cell_px;
            for x in 0..side {
                let cx = x / cell_px;
                if cx >= per_row || cy >= per_row {
                    continue;
                }
                let cell = cy * per_row + cx;
                let local = [
                    ((x % cell_px) as f32 + 0.5) / cell_px as f32,
                    ((y as u32 % cell_px) as f32 + 0.5) / cell_px as f32,
                ];
                let second = local[0] + local[1] > 1.0;
                let t = (cell * 2 + second as u32) as usize;
                let Some(&tri) = mesh.triangles.get(t) else {
                    continue;
                };
                let corners =
                    cell_corners(second, gap).map(|c| c.map(|v| pad + v * (1.0 - 2.0 * pad)));
                let l = local.map(|c| c.clamp(pad, 1.0 - pad));
                let w = barycentric(l, corners);
                let color = texel_color(mesh, tsdf, tri, w);
                let o = (x * 3) as usize;
                for k in 0..3 {
                    row[o + k] = (color[k].clamp(0.0, 1.0) * 255.0).round() as u8;
                }
            }
        });
    Texture {
        width: side,
        height: side,
        rgb,
        uvs,
    }
}

/// Barycentric weights of `p` in the 2D triangle `t`, clamped onto it.
fn barycentric(p: [f32; 2], t: [[f32; 2]; 3]) -> [f32; 3] {
    let (a, b, c) = (t[0], t[1], t[2]);
    let det = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1]);
    let w0 = ((b[1] - c[1]) * (p[0] - c[0]) + (c[0] - b[0]) * (p[1] - c[1])) / det;
    let w1 = ((c[1] - a[1]) * (p[0] - c[0]) + (a[0] - c[0]) * (p[1] - c[1])) / det;
    let w = [w0.max(0.0), w1.max(0.0), (1.0 - w0 - w1).max(0.0)];
    let sum = w[0] + w[1] + w[2];
    w.map(|v| v / sum)
}

fn texel_color(mesh: &TriMesh, tsdf: Option<&Tsdf>, tri: [u32; 3], w: [f32; 3]) -> [f32; 3] {
    let corner = |k: usize| mesh.positions[tri[k] as usize];
    let p = [0, 1, 2].map(|i| {
        (0..3)
            .map(|k| w[k] as f64 * corner(k)[i] as f64)
            .sum::<f64>()
    });
    tsdf.and_then(|v| v.color_at(p)).unwrap_or_else(|| {
        [0, 1, 2].map(|i| (0..3).map(|k| w[k] * mesh.colors[tri[k] as usize][i]).sum())
    })
}
