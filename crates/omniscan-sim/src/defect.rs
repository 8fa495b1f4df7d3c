//! Planted defects (paper, "Defect Inspection"): geometric ones change the
//! surface (a dent, a bump, or a flat-bottomed cut), visual ones change only
//! its appearance (a scratch or a strip of tape). The place is drawn from the
//! surface by area with the given seed, away from where the fingers hold the
//! object so the defect can be seen; type, size and place go into the
//! capture's ground truth.
//!
//! Geometric defects first refine the mesh around the place (conforming
//! edge bisection keyed by welded positions, so UV seams do not crack) until
//! its edges are an eighth of the defect size, then move vertices.

use std::collections::HashMap;
use std::str::FromStr;

use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use crate::SimError;
use crate::mesh::Mesh;
use crate::raster::Decal;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum DefectKind {
    Dent,
    Bump,
    Cut,
    Scratch,
    Tape,
}

impl DefectKind {
    pub fn is_geometric(self) -> bool {
        matches!(self, DefectKind::Dent | DefectKind::Bump | DefectKind::Cut)
    }
}

/// A defect request: `geometric:dent|bump|cut,size_mm=S` or `visual:scratch|tape,size_mm=S`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DefectSpec {
    pub kind: DefectKind,
    pub size_mm: f64,
}

impl FromStr for DefectSpec {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let usage =
            "expected geometric:dent|bump|cut[,size_mm=S] or visual:scratch|tape[,size_mm=S]";
        let mut parts = s.split(',');
        let head = parts.next().unwrap_or("");
        let (category, kind) = head
            .split_once(':')
            .ok_or_else(|| format!("bad defect `{s}`: {usage}"))?;
        let kind = match (category, kind) {
            ("geometric", "dent") => DefectKind::Dent,
            ("geometric", "bump") => DefectKind::Bump,
            ("geometric", "cut") => DefectKind::Cut,
            ("visual", "scratch") => DefectKind::Scratch,
            ("visual", "tape") => DefectKind::Tape,
            _ => return Err(format!("unknown defect `{head}`: {usage}")),
        };
        let mut size_mm: f64 = if kind.is_geometric() { 6.0 } else { 4.0 };
        for p in parts {
            match p.split_once('=') {
                Some(("size_mm", v)) => {
                    size_mm = v
                        .parse()
                        .map_err(|_| format!("bad size_mm `{v}` in defect `{s}`"))?;
                }
                _ => return Err(format!("unknown defect option `{p}`: {usage}")),
            }
        }
        if !(size_mm.is_finite() && (0.5..=50.0).contains(&size_mm)) {
            return Err(format!("defect size {size_mm} mm is outside 0.5-50 mm"));
        }
        Ok(DefectSpec { kind, size_mm })
    }
}

/// Ground truth of a planted defect, object frame, metres.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DefectRecord {
    pub category: &'static str,
    pub kind: DefectKind,
    pub size_mm: f64,
    pub center_m: [f64; 3],
    pub normal: [f64; 3],
    pub tangent: [f64; 3],
    /// Depth of a dent or cut, height of a bump, millimetres (0 for visual defects).
    pub depth_mm: f64,
    /// Mesh vertices moved by a geometric defect.
    pub moved_vertices: usize,
}

/// Plants `spec` on `mesh`, away from `avoid` (e.g. finger contacts) by at
/// least `avoid_radius` metres. Returns the record and, for visual defects,
/// the decal to render.
pub fn plant_defect(
    mesh: &mut Mesh,
    spec: &DefectSpec,
    seed: u64,
    avoid: &[Point3<f64>],
    avoid_radius: f64,
) -> Result<(DefectRecord, Vec<Decal>), SimError> {
    let size = spec.size_mm * 1e-3;
    let Place {
        point: center,
        normal,
        color: uv_color,
    } = pick_place(
        mesh,
        seed,
        avoid,
        avoid_radius,
        size,
        !spec.kind.is_geometric(),
    )?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xdef);
    let helper = if normal.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let t0 = normal.cross(&helper).normalize();
    let t1 = normal.cross(&t0);
    let angle: f64 = rng.random::<f64>() * std::f64::consts::PI;
    let tangent = t0 * angle.cos() + t1 * angle.sin();
    let mut record = DefectRecord {
        category: if spec.kind.is_geometric() {
            "geometric"
        } else {
            "visual"
        },
        kind: spec.kind,
        size_mm: spec.size_mm,
        center_m: center.coords.into(),
        normal: normal.into(),
        tangent: tangent.into(),
        depth_mm: 0.0,
        moved_vertices: 0,
    };
    let radius = 0.5 * size;
    let mut decals = Vec::new();
    match spec.kind {
        DefectKind::Dent | DefectKind::Bump | DefectKind::Cut => {
            refine_near(
                mesh,
                &center.cast(),
                (size * 1.2) as f32,
                (size / 8.0) as f32,
            );
            let depth = match spec.kind {
                DefectKind::Cut => 0.4 * size,
                _ => 0.35 * size,
            };
            record.depth_mm = depth * 1e3;
            let n = normal.cast::<f32>();
            let c = center.cast::<f32>();
            let (r, depth) = (radius as f32, depth as f32);
            let mut moved = 0;
            let normals = mesh.normals.clone();
            for (p, vn) in mesh.positions.iter_mut().zip(&normals) {
                let d = *p - c;
                let height = d.dot(&n);
                let lateral = (d - n * height).norm();
                if lateral >= r || vn.dot(&n) < -0.2 || height.abs() > r {
                    continue;
                }
                let offset = match spec.kind {
                    DefectKind::Cut => {
                        if height > -depth {
                            -(height + depth)
                        } else {
                            0.0
                        }
                    }
                    kind => {
                        let f = (1.0 - (lateral / r).powi(2)).powi(2);
                        if kind == DefectKind::Dent {
                            -depth * f
                        } else {
                            depth * f
                        }
                    }
                };
                if offset != 0.0 {
                    *p += n * offset;
                    moved += 1;
                }
            }
            if moved == 0 {
                return Err(SimError::Invalid(format!(
                    "the {:?} defect moved no vertex: the mesh is too coarse there",
                    spec.kind
                )));
            }
            record.moved_vertices = moved;
            mesh.compute_normals();
        }
        DefectKind::Scratch | DefectKind::Tape => {
            let brightness = (uv_color[0] + uv_color[1] + uv_color[2]) / 3.0;
            let (half_width, wiggle, color, specular) = if spec.kind == DefectKind::Scratch {
                let color = if brightness < 0.5 {
                    [0.86, 0.86, 0.84]
                } else {
                    [0.18, 0.17, 0.16]
                };
                ((0.00025f64).max(size * 0.04), size * 0.04, color, 0.6)
            } else {
                let color = if uv_color[2] < 0.3 && uv_color[0] > 0.6 {
                    [0.15, 0.45, 0.9]
                } else {
                    [0.96, 0.82, 0.10]
                };
                (size * 0.2, 0.0, color, 0.3)
            };
            decals.push(Decal {
                center: center.cast(),
                normal: normal.cast(),
                tangent: tangent.cast(),
                half_length: radius as f32,
                half_width: half_width as f32,
                wiggle: wiggle as f32,
                depth_tolerance: (0.25 * size + 0.001) as f32,
                color,
                specular,
            });
        }
    }
    Ok((record, decals))
}

/// Where a defect goes: a surface point, its outward normal and the surface colour there.
struct Place {
    point: Point3<f64>,
    normal: Vector3<f64>,
    color: [f32; 3],
}

/// A seeded surface point away from `avoid`, flat over the defect's size.
/// A mark on the surface (`surface_mark`) only needs its own side flat:
/// vertices behind the surface and facing away belong to the far side of a
/// sheet (a 2 mm bracket's opposite normals made every place fail); a dent
/// or a cut would go through to that side, so for them they count.
fn pick_place(
    mesh: &Mesh,
    seed: u64,
    avoid: &[Point3<f64>],
    avoid_radius: f64,
    size: f64,
    surface_mark: bool,
) -> Result<Place, SimError> {
    let areas: Vec<f64> = (0..mesh.triangles.len())
        .map(|t| {
            let [a, b, c] = mesh.triangle(t).map(|p| p.cast::<f64>());
            (b - a).cross(&(c - a)).norm()
        })
        .collect();
    let total: f64 = areas.iter().sum();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for _ in 0..2000 {
        let mut r = rng.random::<f64>() * total;
        let mut t = 0;
        while t + 1 < areas.len() && r > areas[t] {
            r -= areas[t];
            t += 1;
        }
        let (mut u, mut v): (f64, f64) = (rng.random(), rng.random());
        if u + v > 1.0 {
            u = 1.0 - u;
            v = 1.0 - v;
        }
        let [a, b, c] = mesh.triangle(t).map(|p| p.cast::<f64>());
        let p = a + (b - a) * u + (c - a) * v;
        if avoid.iter().any(|q| (p - q).norm() < avoid_radius) {
            continue;
        }
        let n = mesh.face_normal(t).cast::<f64>();
        // The place must be fairly flat over the defect's size: the vertex
        // normals of nearby vertices agree with the face normal.
        let flat = mesh
            .positions
            .iter()
            .zip(&mesh.normals)
            .filter(|(q, qn)| {
                let d = q.cast::<f64>() - p;
                let far_side = d.dot(&n) < 0.0 && qn.cast::<f64>().dot(&n) < -0.5;
                d.norm() < 0.5 * size && !(surface_mark && far_side)
            })
            .all(|(_, qn)| qn.cast::<f64>().dot(&n) > 0.5);
        if !flat {
            continue;
        }
        let [ia, ib, ic] = mesh.triangles[t].map(|i| i as usize);
        let material =
            &mesh.materials[mesh.triangle_materials.get(t).copied().unwrap_or(0) as usize];
        let mut color = material.albedo;
        if let Some(tex) = &material.texture
            && !mesh.uvs.is_empty()
        {
            let w = [1.0 - u - v, u, v].map(|x| x as f32);
            let uv = [0, 1]
                .map(|k| w[0] * mesh.uvs[ia][k] + w[1] * mesh.uvs[ib][k] + w[2] * mesh.uvs[ic][k]);
            let s = tex.sample(uv[0], uv[1]);
            color = [color[0] * s[0], color[1] * s[1], color[2] * s[2]];
        }
        return Ok(Place {
            point: p,
            normal: n,
            color,
        });
    }
    Err(SimError::Invalid("found no place for the defect: every sampled point is near the fingers or on a sharp feature".into()))
}

/// Bisects edges longer than `max_edge` near `center` until none is left.
pub fn refine_near(mesh: &mut Mesh, center: &Point3<f32>, radius: f32, max_edge: f32) {
    for _ in 0..10 {
        let mut weld: HashMap<[u32; 3], u32> = HashMap::new();
        let pid: Vec<u32> = mesh
            .positions
            .iter()
            .map(|p| {
                let n = weld.len() as u32;
                *weld
                    .entry([p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
                    .or_insert(n)
            })
            .collect();
        let key = |a: u32, b: u32| {
            let (x, y) = (pid[a as usize], pid[b as usize]);
            (x.min(y), x.max(y))
        };
        let mut marked = std::collections::HashSet::new();
        for t in &mesh.triangles {
            let ps = t.map(|i| mesh.positions[i as usize]);
            if crate::mesh::distance_to_triangle(center, &ps) > radius {
                continue;
            }
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                if (mesh.positions[a as usize] - mesh.positions[b as usize]).norm() > max_edge {
                    marked.insert(key(a, b));
                }
            }
        }
        if marked.is_empty() {
            return;
        }
        let mut midpoints: HashMap<(u32, u32), u32> = HashMap::new();
        let mut mid = |mesh: &mut Mesh, a: u32, b: u32| -> u32 {
            let k = (a.min(b), a.max(b));
            if let Some(&m) = midpoints.get(&k) {
                return m;
            }
            let (ia, ib) = (a as usize, b as usize);
            mesh.positions.push(Point3::from(
                (mesh.positions[ia].coords + mesh.positions[ib].coords) * 0.5,
            ));
            let n = mesh.normals[ia] + mesh.normals[ib];
            mesh.normals.push(if n.norm() > 0.0 {
                n.normalize()
            } else {
                mesh.normals[ia]
            });
            if !mesh.uvs.is_empty() {
                let (u, v) = (mesh.uvs[ia], mesh.uvs[ib]);
                mesh.uvs.push([(u[0] + v[0]) * 0.5, (u[1] + v[1]) * 0.5]);
            }
            let m = (mesh.positions.len() - 1) as u32;
            midpoints.insert(k, m);
            m
        };
        let old_triangles = std::mem::take(&mut mesh.triangles);
        let old_materials = std::mem::take(&mut mesh.triangle_materials);
        for (t, material) in old_triangles.into_iter().zip(old_materials) {
            let is = [0, 1, 2].map(|k| marked.contains(&key(t[k], t[(k + 1) % 3])));
            let count = is.iter().filter(|&&m| m).count();
            let push = |mesh: &mut Mesh, tri: [u32; 3]| {
                mesh.triangles.push(tri);
                mesh.triangle_materials.push(material);
            };
            match count {
                0 => push(mesh, t),
                1 => {
                    let k = is.iter().position(|&m| m).unwrap();
                    let (a, b, c) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
                    let m = mid(mesh, a, b);
                    push(mesh, [a, m, c]);
                    push(mesh, [m, b, c]);
                }
                2 => {
                    // Rotate so that edges (a,b) and (b,c) are the marked ones.
                    let k = is.iter().position(|&m| !m).unwrap();
                    let (a, b, c) = (t[(k + 1) % 3], t[(k + 2) % 3], t[k]);
                    let m1 = mid(mesh, a, b);
                    let m2 = mid(mesh, b, c);
                    push(mesh, [m1, b, m2]);
                    push(mesh, [a, m1, m2]);
                    push(mesh, [a, m2, c]);
                }
                _ => {
                    let (a, b, c) = (t[0], t[1], t[2]);
                    let (mab, mbc, mca) = (mid(mesh, a, b), mid(mesh, b, c), mid(mesh, c, a));
                    push(mesh, [a, mab, mca]);
                    push(mesh, [mab, b, mbc]);
                    push(mesh, [mca, mbc, c]);
                    push(mesh, [mab, mbc, mca]);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{Material, MeshBuilder};

    fn cube() -> Mesh {
        let mut b = MeshBuilder::new(Material::color([0.3; 3]));
        b.cuboid(
            Point3::new(-0.02, -0.02, -0.02),
            Point3::new(0.02, 0.02, 0.02),
            0,
        );
        let mut m = b.finish();
        m.compute_normals();
        m
    }

    #[test]
    fn parses_specs() {
        let s: DefectSpec = "geometric:dent,size_mm=7.5".parse().unwrap();
        assert_eq!(
            s,
            DefectSpec {
                kind: DefectKind::Dent,
                size_mm: 7.5
            }
        );
        assert_eq!(
            "visual:tape".parse::<DefectSpec>().unwrap().kind,
            DefectKind::Tape
        );
        for bad in [
            "geometric:crack",
            "dent",
            "visual:tape,size=3",
            "visual:tape,size_mm=-1",
            "visual:tape,size_mm=x",
        ] {
            assert!(bad.parse::<DefectSpec>().is_err(), "{bad}");
        }
    }

    #[test]
    fn refinement_is_conforming_and_keeps_area() {
        let mut m = cube();
        let area = m.area();
        refine_near(&mut m, &Point3::new(0.0, 0.0, 0.02), 0.01, 0.002);
        assert!((m.area() - area).abs() < 1e-9);
        // Every edge is shared by exactly two triangles (closed, no T-junctions).
        let mut edges: HashMap<([u32; 3], [u32; 3]), i32> = HashMap::new();
        let bits = |p: &Point3<f32>| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
        for t in &m.triangles {
            for k in 0..3 {
                let (a, b) = (
                    bits(&m.positions[t[k] as usize]),
                    bits(&m.positions[t[(k + 1) % 3] as usize]),
                );
                *edges.entry((a.min(b), a.max(b))).or_default() += 1;
            }
        }
        assert!(edges.values().all(|&c| c == 2));
        assert!(m.triangles.len() > 100);
    }

    #[test]
    fn dent_moves_the_surface_by_its_depth_at_the_centre() {
        let mut m = cube();
        let spec = DefectSpec {
            kind: DefectKind::Dent,
            size_mm: 8.0,
        };
        let (record, decals) = plant_defect(&mut m, &spec, 5, &[], 0.0).unwrap();
        assert!(decals.is_empty() && record.moved_vertices > 0);
        let c = Point3::from(record.center_m);
        let n = Vector3::from(record.normal);
        // Along the normal through the centre, the surface is now depth_mm deeper.
        let hits = m.line_hits(&(c + n * 0.01), &-n);
        let first = hits.first().unwrap().0 - 0.01;
        assert!(
            (first - record.depth_mm * 1e-3).abs() < 1e-4,
            "{first} vs {}",
            record.depth_mm
        );
    }

    #[test]
    fn a_mark_finds_a_place_on_a_thin_sheet_and_a_dent_does_not() {
        let mut b = MeshBuilder::new(Material::color([0.3; 3]));
        b.cuboid(
            Point3::new(-0.03, -0.03, -0.001),
            Point3::new(0.03, 0.03, 0.001),
            0,
        );
        let mut sheet = b.finish();
        refine_near(&mut sheet, &Point3::origin(), 0.1, 0.0015);
        sheet.compute_normals();
        let spec = |kind| DefectSpec { kind, size_mm: 8.0 };
        for seed in 0..3 {
            let (record, _) =
                plant_defect(&mut sheet.clone(), &spec(DefectKind::Tape), seed, &[], 0.0).unwrap();
            assert!(Vector3::from(record.normal).z.abs() > 0.99, "{record:?}");
            // 2.8 mm deep through a 2 mm sheet: no place is right for it.
            assert!(
                plant_defect(&mut sheet.clone(), &spec(DefectKind::Dent), seed, &[], 0.0).is_err()
            );
        }
    }

    #[test]
    fn visual_defect_is_a_decal_and_leaves_geometry_alone() {
        let mut m = cube();
        let before = m.clone();
        let spec = DefectSpec {
            kind: DefectKind::Tape,
            size_mm: 10.0,
        };
        let (record, decals) = plant_defect(&mut m, &spec, 9, &[], 0.0).unwrap();
        assert_eq!(m, before);
        assert_eq!(decals.len(), 1);
        let c = Point3::from(record.center_m).cast::<f32>();
        assert!(decals[0].covers(&c, &Vector3::from(record.normal).cast()));
        assert!(!decals[0].covers(
            &(c + decals[0].tangent * 0.02),
            &Vector3::from(record.normal).cast()
        ));
    }
}
