//! What a mesh is made of: its connected pieces, whether it is closed and
//! 2-manifold, its area and the volume it encloses.

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

use crate::TriMesh;
use crate::extract::{cross, dot, sub};

/// The edge counts that decide whether a mesh is watertight.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Topology {
    pub vertices: usize,
    pub edges: usize,
    pub faces: usize,
    /// Edges with one triangle: the rims of holes.
    pub boundary_edges: usize,
    /// Edges with three or more triangles.
    pub non_manifold_edges: usize,
    /// Edges whose two triangles run along them the same way (flipped faces).
    pub misoriented_edges: usize,
    /// Connected pieces.
    pub components: usize,
}

impl Topology {
    /// Closed, 2-manifold and consistently oriented.
    pub fn is_watertight(&self) -> bool {
        self.boundary_edges == 0 && self.non_manifold_edges == 0 && self.misoriented_edges == 0
    }

    /// V − E + F: 2 for a closed surface with no handles.
    pub fn euler_characteristic(&self) -> i64 {
        self.vertices as i64 - self.edges as i64 + self.faces as i64
    }
}

/// The mesh's edge counts.
pub fn topology(mesh: &TriMesh) -> Topology {
    // Each undirected edge: how often it runs a→b (a < b) and b→a.
    let mut edges: HashMap<(u32, u32), (u32, u32)> = HashMap::new();
    for t in &mesh.triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            let entry = edges.entry((a.min(b), a.max(b))).or_default();
            if a < b {
                entry.0 += 1;
            } else {
                entry.1 += 1;
            }
        }
    }
    let mut used = vec![false; mesh.positions.len()];
    mesh.triangles
        .iter()
        .flatten()
        .for_each(|&v| used[v as usize] = true);
    let (mut boundary, mut non_manifold, mut misoriented) = (0, 0, 0);
    for &(forward, backward) in edges.values() {
        match forward + backward {
            1 => boundary += 1,
            2 if forward != 1 => misoriented += 1,
            2 => {}
            _ => non_manifold += 1,
        }
    }
    Topology {
        vertices: used.iter().filter(|&&u| u).count(),
        edges: edges.len(),
        faces: mesh.triangles.len(),
        boundary_edges: boundary,
        non_manifold_edges: non_manifold,
        misoriented_edges: misoriented,
        components: component_labels(mesh).1,
    }
}

/// A component number per triangle (triangles sharing a vertex are
/// connected), and how many components there are.
pub fn component_labels(mesh: &TriMesh) -> (Vec<usize>, usize) {
    let mut parent: Vec<u32> = (0..mesh.positions.len() as u32).collect();
    fn find(parent: &mut [u32], mut v: u32) -> u32 {
        while parent[v as usize] != v {
            parent[v as usize] = parent[parent[v as usize] as usize];
            v = parent[v as usize];
        }
        v
    }
    for t in &mesh.triangles {
        for k in 1..3 {
            let (a, b) = (find(&mut parent, t[0]), find(&mut parent, t[k]));
            if a != b {
                parent[a.max(b) as usize] = a.min(b);
            }
        }
    }
    let mut number: HashMap<u32, usize> = HashMap::new();
    let labels = mesh
        .triangles
        .iter()
        .map(|t| {
            let root = find(&mut parent, t[0]);
            let next = number.len();
            *number.entry(root).or_insert(next)
        })
        .collect();
    (labels, number.len())
}

/// Twice the area and six times the signed volume contributed by triangle `t`.
fn triangle_terms(mesh: &TriMesh, t: &[u32; 3]) -> (f64, f64) {
    let [a, b, c] = t.map(|v| mesh.positions[v as usize].map(f64::from));
    let n = cross(sub(b, a), sub(c, a));
    (dot(n, n).sqrt(), dot(a, cross(b, c)))
}

/// The area of triangle `t`, m².
pub fn triangle_area(mesh: &TriMesh, t: &[u32; 3]) -> f64 {
    triangle_terms(mesh, t).0 / 2.0
}

/// Surface area, m².
pub fn area(mesh: &TriMesh) -> f64 {
    mesh.triangles.iter().map(|t| triangle_area(mesh, t)).sum()
}

/// Area of the triangles marked unseen, m².
pub fn unseen_area(mesh: &TriMesh) -> f64 {
    mesh.triangles
        .iter()
        .zip(&mesh.unseen)
        .filter(|(_, u)| **u)
        .map(|(t, _)| triangle_area(mesh, t))
        .sum()
}

/// The volume a closed, outward-oriented mesh encloses, m³ (by the
/// divergence theorem: the sum of the signed tetrahedra to the origin).
pub fn volume(mesh: &TriMesh) -> f64 {
    mesh.triangles
        .iter()
        .map(|t| triangle_terms(mesh, t).1)
        .sum::<f64>()
        / 6.0
}

/// The mesh with only the component that encloses the most volume, and
/// how many components were dropped.
pub fn largest_component(mesh: &TriMesh) -> (TriMesh, usize) {
    let (labels, count) = component_labels(mesh);
    if count <= 1 {
        return (mesh.clone(), 0);
    }
    let mut volumes = vec![0.0f64; count];
    for (t, &label) in mesh.triangles.iter().zip(&labels) {
        volumes[label] += triangle_terms(mesh, t).1;
    }
    let keep = (0..count)
        .max_by(|&a, &b| volumes[a].total_cmp(&volumes[b]))
        .unwrap_or(0);
    let kept = mesh.filter_triangles(|t| labels[t] == keep);
    (kept, count - 1)
}
