//! The zero level set of a fused volume as a triangle mesh, by marching
//! tetrahedra (Doi and Koide 1991): each cube of eight voxels is cut into
//! six tetrahedra around its main diagonal, the same way in every cube, so
//! neighbouring cubes cut their shared faces alike.
//!
//! We write our own rather than use a marching-cubes crate because the
//! guarantee matters more than the triangle count: with no value exactly on
//! the level (zero counts as outside) and the grid's faces outside, the
//! tetrahedra give a closed, 2-manifold, consistently oriented surface with
//! no ambiguous cases, which the classic 256-case cube table does not, and
//! the decimation that follows brings the count down anyway. A vertex sits
//! on a grid edge and is shared by every triangle that cuts that edge.

use std::collections::HashMap;

use rayon::prelude::*;

use crate::TriMesh;
use crate::fusion::Tsdf;

/// The six tetrahedra of a cube, as corner numbers (bit 0: +x, bit 1: +y,
/// bit 2: +z), sharing the diagonal from corner 0 to corner 7.
const TETRAHEDRA: [[usize; 4]; 6] = [
    [0, 1, 3, 7],
    [0, 3, 2, 7],
    [0, 2, 6, 7],
    [0, 6, 4, 7],
    [0, 4, 5, 7],
    [0, 5, 1, 7],
];

/// A triangle whose corners are grid edges (pairs of voxel indices).
type EdgeTriangle = [(usize, usize); 3];

/// The surface where the signed distance crosses zero, oriented outwards
/// (towards positive distance), with a colour per vertex; triangles with a
/// corner on an edge to a voxel no view observed are marked `unseen`.
pub fn extract(tsdf: &Tsdf) -> TriMesh {
    let g = tsdf.grid;
    let [nx, ny, nz] = g.dims;
    if nx < 2 || ny < 2 || nz < 2 {
        return TriMesh::default();
    }
    let signs = tetrahedron_signs();
    let slabs: Vec<Vec<EdgeTriangle>> = (0..nz - 1)
        .into_par_iter()
        .map(|z| {
            let mut out = Vec::new();
            for y in 0..ny - 1 {
                for x in 0..nx - 1 {
                    cube_triangles(tsdf, [x, y, z], &signs, &mut out);
                }
            }
            out
        })
        .collect();
    let mut mesh = TriMesh::default();
    let mut vertex_of: HashMap<(usize, usize), u32> = HashMap::new();
    for triangle in slabs.into_iter().flatten() {
        let corners = triangle.map(|edge| {
            *vertex_of.entry(edge).or_insert_with(|| {
                let (p, color) = edge_vertex(tsdf, edge);
                mesh.positions.push(p);
                mesh.colors.push(color);
                (mesh.positions.len() - 1) as u32
            })
        });
        let unseen = triangle
            .iter()
            .any(|&(a, b)| tsdf.weight[a] == 0.0 || tsdf.weight[b] == 0.0);
        mesh.triangles.push(corners);
        mesh.unseen.push(unseen);
    }
    mesh
}

fn is_inside(sdf: f32) -> bool {
    sdf < 0.0
}

/// Appends the triangles of the cube whose lowest corner is voxel `at`.
fn cube_triangles(tsdf: &Tsdf, at: [usize; 3], signs: &[f64; 6], out: &mut Vec<EdgeTriangle>) {
    let g = &tsdf.grid;
    let corner = |c: usize| {
        g.index(
            at[0] + (c & 1),
            at[1] + ((c >> 1) & 1),
            at[2] + ((c >> 2) & 1),
        )
    };
    let ids: [usize; 8] = std::array::from_fn(corner);
    let inside = ids.map(|i| is_inside(tsdf.sdf[i]));
    if inside.iter().all(|&b| b) || inside.iter().all(|&b| !b) {
        return;
    }
    for (tet, &sign) in TETRAHEDRA.iter().zip(signs) {
        // Inside corners first, keeping track of the permutation's parity:
        // orientation is decided combinatorially, so a triangle too thin
        // for its normal to be computed is still oriented like its
        // neighbours.
        let mut order = [0usize, 1, 2, 3];
        order.sort_by_key(|&k| !inside[tet[k]]);
        let inversions = (0..4)
            .flat_map(|i| (i + 1..4).map(move |j| (i, j)))
            .filter(|&(i, j)| order[i] > order[j])
            .count();
        let positive = (sign > 0.0) == (inversions % 2 == 0);
        let v = order.map(|k| ids[tet[k]]);
        let edge = |a: usize, b: usize| (v[a].min(v[b]), v[a].max(v[b]));
        let count = order.iter().filter(|&&k| inside[tet[k]]).count();
        match count {
            // (a, b, c, d) positive and a inside: (ab, ac, ad) faces out.
            1 => out.push(oriented([edge(0, 1), edge(0, 2), edge(0, 3)], positive)),
            // a, the one outside corner, is last after sorting: (a, b, c, d)
            // is an odd permutation of the sorted order, and (ab, ac, ad)
            // faces away from a, inwards, when (a, b, c, d) is positive.
            3 => out.push(oriented([edge(3, 0), edge(3, 1), edge(3, 2)], positive)),
            // (a, b) inside, (c, d) outside: the quad ac, ad, bd, bc.
            2 => {
                out.push(oriented([edge(0, 2), edge(0, 3), edge(1, 3)], positive));
                out.push(oriented([edge(0, 2), edge(1, 3), edge(1, 2)], positive));
            }
            _ => {}
        }
    }
}

/// The triangle as given when `keep`, else turned over.
fn oriented(mut t: EdgeTriangle, keep: bool) -> EdgeTriangle {
    if !keep {
        t.swap(1, 2);
    }
    t
}

/// The sign of each tetrahedron's volume, (c1 − c0)·((c2 − c0) × (c3 − c0)).
fn tetrahedron_signs() -> [f64; 6] {
    let corner = |c: usize| [(c & 1) as f64, ((c >> 1) & 1) as f64, ((c >> 2) & 1) as f64];
    TETRAHEDRA.map(|t| {
        let [a, b, c, d] = t.map(corner);
        dot(sub(b, a), cross(sub(c, a), sub(d, a)))
    })
}

fn voxel_position(tsdf: &Tsdf, i: usize) -> [f64; 3] {
    let [nx, ny, _] = tsdf.grid.dims;
    tsdf.grid.position(i % nx, (i / nx) % ny, i / (nx * ny))
}

/// Where the distance crosses zero on the grid edge between voxels `a`, `b`.
fn crossing(tsdf: &Tsdf, (a, b): (usize, usize)) -> [f64; 3] {
    let (pa, pb) = (voxel_position(tsdf, a), voxel_position(tsdf, b));
    let (da, db) = (tsdf.sdf[a] as f64, tsdf.sdf[b] as f64);
    let t = if da == db {
        0.5
    } else {
        (da / (da - db)).clamp(0.0, 1.0)
    };
    [0, 1, 2].map(|k| pa[k] + t * (pb[k] - pa[k]))
}

/// The vertex on edge (`a`, `b`) and its colour (the two voxels' colours,
/// weighted by how near and how often seen; grey where neither saw any).
fn edge_vertex(tsdf: &Tsdf, (a, b): (usize, usize)) -> ([f32; 3], [f32; 3]) {
    let p = crossing(tsdf, (a, b));
    let (da, db) = (tsdf.sdf[a].abs(), tsdf.sdf[b].abs());
    let wa = tsdf.color_weight[a] * (db + 1e-3);
    let wb = tsdf.color_weight[b] * (da + 1e-3);
    let color = if wa + wb > 0.0 {
        [0, 1, 2].map(|k| (wa * tsdf.color[a][k] + wb * tsdf.color[b][k]) / (wa + wb))
    } else {
        tsdf.color_at(p).unwrap_or([0.5; 3])
    };
    (p.map(|c| c as f32), color)
}

pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
