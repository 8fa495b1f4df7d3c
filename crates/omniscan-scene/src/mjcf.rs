//! A gripper from a MuJoCo MJCF file (MuJoCo Menagerie publishes many
//! grippers only so): the body subtree under the gripper root, read with
//! `roxmltree`. No maintained Rust crate reads MJCF, and a gripper needs a
//! small part of it, written here:
//!
//! - `<compiler angle eulerseq meshdir>`; `<default>` classes, nested, picked by an
//!   element's `class`, else the nearest `childclass` above it;
//! - bodies (`pos` and `quat`, `axisangle`, `euler` with the compiler's
//!   `eulerseq`, `xyaxes` or `zaxis`), each with at most one `hinge` or
//!   `slide` joint (`axis`, `pos`, `range`) or none (fixed), and `site`s
//!   (usable as the TCP);
//! - the geoms MuJoCo's viewer shows by default (groups 0-2): `mesh` (STL,
//!   OBJ, PLY assets with `scale`), `box`, `cylinder`; colour from `rgba` or
//!   the material;
//! - `<equality>`: `joint` (linear `polycoef`) as a mimic, `connect` as a
//!   loop closure (the 2F-85's four-bar linkage);
//! - the joints `<actuator>`s drive, directly or through a fixed tendon.
//!
//! Bodies are the links; a body's joint turns about its `pos` in the body.

use std::collections::BTreeMap;
use std::path::Path;

use nalgebra::{Isometry3, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use roxmltree::{Document, Node};

use crate::mesh::{Material, MeshBuilder};
use crate::robot::{Closure, Joint, LinkMesh, Motion, Tree};

/// Element tag -> attribute -> value, as one `<default>` class sets them.
type ClassAttributes<'a> = BTreeMap<String, BTreeMap<String, &'a str>>;

/// The `<default>` classes: class -> (parent class, its attributes).
struct Defaults<'a> {
    classes: BTreeMap<String, (Option<String>, ClassAttributes<'a>)>,
}

impl<'a> Defaults<'a> {
    fn read(root: Node<'a, 'a>) -> Defaults<'a> {
        let mut d = Defaults {
            classes: BTreeMap::new(),
        };
        for node in root.children().filter(|n| n.has_tag_name("default")) {
            d.add(node, None);
        }
        d
    }

    fn add(&mut self, node: Node<'a, 'a>, parent: Option<String>) {
        let class = node.attribute("class").unwrap_or("main").to_string();
        let mut elements: ClassAttributes<'a> = BTreeMap::new();
        for child in node.children().filter(|n| n.is_element()) {
            if child.has_tag_name("default") {
                self.add(child, Some(class.clone()));
            } else {
                let attrs = elements
                    .entry(child.tag_name().name().to_string())
                    .or_default();
                for a in child.attributes() {
                    attrs.insert(a.name().to_string(), a.value());
                }
            }
        }
        self.classes.insert(class, (parent, elements));
    }

    /// `attr` of a `tag` element in `class`, else in its parents.
    fn get(&self, class: &str, tag: &str, attr: &str) -> Option<&'a str> {
        let mut current = Some(class.to_string());
        while let Some(c) = current {
            let (parent, elements) = self.classes.get(&c)?;
            if let Some(v) = elements.get(tag).and_then(|e| e.get(attr)) {
                return Some(v);
            }
            current = parent
                .clone()
                .or_else(|| (c != "main").then(|| "main".into()));
        }
        None
    }
}

/// Reading context: the file, its defaults and compiler settings.
struct Reader<'a> {
    path: &'a Path,
    defaults: Defaults<'a>,
    radians: bool,
    /// `<compiler eulerseq>`: three of x y z X Y Z.
    eulerseq: String,
    meshdir: String,
    meshes: BTreeMap<String, (String, String)>,
    materials: BTreeMap<String, [f32; 3]>,
}

fn numbers(text: &str, what: &str) -> Result<Vec<f64>, String> {
    text.split_whitespace()
        .map(|v| {
            v.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| format!("{what}: `{text}` is not a list of numbers"))
        })
        .collect()
}

/// An `rgba` attribute's colour (its alpha is not drawn).
fn colour(rgba: &str, what: &str) -> Result<[f32; 3], String> {
    match numbers(rgba, what)?.as_slice() {
        [r, g, b, _] => Ok([*r as f32, *g as f32, *b as f32]),
        _ => Err(format!("{what}: rgba `{rgba}` needs four numbers")),
    }
}

fn vec3(text: Option<&str>, what: &str, default: [f64; 3]) -> Result<Vector3<f64>, String> {
    match text {
        None => Ok(Vector3::from(default)),
        Some(t) => match numbers(t, what)?.as_slice() {
            [x, y, z] => Ok(Vector3::new(*x, *y, *z)),
            _ => Err(format!("{what}: `{t}` needs three numbers")),
        },
    }
}

impl<'a> Reader<'a> {
    /// An attribute of `node`, else of its class's defaults.
    fn attr(&self, node: Node<'a, 'a>, class: &str, name: &str) -> Option<&'a str> {
        node.attribute(name).or_else(|| {
            let class = node.attribute("class").unwrap_or(class);
            self.defaults.get(class, node.tag_name().name(), name)
        })
    }

    fn angle(&self, v: f64) -> f64 {
        if self.radians { v } else { v.to_radians() }
    }

    /// The frame of an element: `pos` and one of MJCF's orientations.
    fn frame(&self, node: Node<'a, 'a>, class: &str, what: &str) -> Result<Isometry3<f64>, String> {
        let pos = vec3(self.attr(node, class, "pos"), what, [0.0; 3])?;
        let rotation = self.orientation(node, what)?;
        Ok(Isometry3::from_parts(Translation3::from(pos), rotation))
    }

    /// An element's orientation from whichever of `quat` (w x y z),
    /// `axisangle`, `euler` (in `<compiler eulerseq>`'s order: lower case
    /// turns about the moving axes, upper case about the fixed ones),
    /// `xyaxes` or `zaxis` it gives (at most one); identity if none.
    fn orientation(&self, node: Node<'a, 'a>, what: &str) -> Result<UnitQuaternion<f64>, String> {
        let given: Vec<(&str, Vec<f64>)> = ["quat", "axisangle", "euler", "xyaxes", "zaxis"]
            .into_iter()
            .filter_map(|name| node.attribute(name).map(|text| (name, text)))
            .map(|(name, text)| Ok((name, numbers(text, what)?)))
            .collect::<Result<_, String>>()?;
        let small = |name: &str| format!("{what}: {name} is too small to give a direction");
        let unit = |v: Vector3<f64>, name: &str| Unit::try_new(v, 1e-12).ok_or_else(|| small(name));
        match given.as_slice() {
            [] => Ok(UnitQuaternion::identity()),
            [("quat", q)] if q.len() == 4 => {
                let q = nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]);
                if q.norm() < 1e-12 {
                    return Err(small("quat"));
                }
                Ok(UnitQuaternion::from_quaternion(q))
            }
            [("axisangle", a)] if a.len() == 4 => Ok(UnitQuaternion::from_axis_angle(
                &unit(Vector3::new(a[0], a[1], a[2]), "axisangle")?,
                self.angle(a[3]),
            )),
            [("euler", e)] if e.len() == 3 => Ok(self.euler(e)),
            [("xyaxes", v)] if v.len() == 6 => {
                let x = unit(Vector3::new(v[0], v[1], v[2]), "xyaxes' x")?;
                let y = Vector3::new(v[3], v[4], v[5]);
                let y = unit(y - x.into_inner() * x.dot(&y), "xyaxes' y")?;
                let z = x.cross(&y);
                Ok(UnitQuaternion::from_rotation_matrix(
                    &nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_columns(
                        &[x.into_inner(), y.into_inner(), z],
                    )),
                ))
            }
            [("zaxis", z)] if z.len() == 3 => {
                let z = unit(Vector3::new(z[0], z[1], z[2]), "zaxis")?;
                // The shortest turn from z to it; half a turn about x if opposite.
                Ok(
                    UnitQuaternion::rotation_between_axis(&Vector3::z_axis(), &z).unwrap_or_else(
                        || {
                            UnitQuaternion::from_axis_angle(
                                &Vector3::x_axis(),
                                std::f64::consts::PI,
                            )
                        },
                    ),
                )
            }
            [(name, v)] => Err(format!(
                "{what}: {name} needs {} numbers, not {}",
                match *name {
                    "quat" | "axisangle" => 4,
                    "xyaxes" => 6,
                    _ => 3,
                },
                v.len()
            )),
            _ => Err(format!(
                "{what}: give one orientation, not {}",
                given
                    .iter()
                    .map(|(n, _)| *n)
                    .collect::<Vec<_>>()
                    .join(" and ")
            )),
        }
    }

    /// Euler angles in `<compiler eulerseq>`'s order: a lower-case axis
    /// turns about the frame as turned so far (post-multiplied), an upper-case
    /// one about the fixed frame (pre-multiplied).
    fn euler(&self, angles: &[f64]) -> UnitQuaternion<f64> {
        let mut q = UnitQuaternion::identity();
        for (axis, angle) in self.eulerseq.chars().zip(angles) {
            let about = match axis.to_ascii_lowercase() {
                'x' => Vector3::x_axis(),
                'y' => Vector3::y_axis(),
                _ => Vector3::z_axis(),
            };
            let turn = UnitQuaternion::from_axis_angle(&about, self.angle(*angle));
            q = if axis.is_ascii_lowercase() {
                q * turn
            } else {
                turn * q
            };
        }
        q
    }

    /// A visible geom's mesh in its body's frame; `None` for a hidden one.
    fn geom(
        &self,
        node: Node<'a, 'a>,
        class: &str,
        body: &str,
    ) -> Result<Option<crate::mesh::Mesh>, String> {
        let what = format!("body {body}'s geom");
        let group: i64 = self
            .attr(node, class, "group")
            .and_then(|g| g.parse().ok())
            .unwrap_or(0);
        if group > 2 {
            return Ok(None);
        }
        let colour = match self.attr(node, class, "rgba") {
            Some(rgba) => colour(rgba, &what)?,
            None => self
                .attr(node, class, "material")
                .and_then(|m| self.materials.get(m).copied())
                .unwrap_or([0.5, 0.5, 0.5]),
        };
        let material = Material::color(colour).with_specular(0.2, 20.0);
        let kind =
            self.attr(node, class, "type")
                .unwrap_or(if self.attr(node, class, "mesh").is_some() {
                    "mesh"
                } else {
                    "sphere"
                });
        let mut mesh = match kind {
            "mesh" => {
                let name = self
                    .attr(node, class, "mesh")
                    .ok_or_else(|| format!("{what} has type mesh but no mesh"))?;
                let (file, scale) = self
                    .meshes
                    .get(name)
                    .ok_or_else(|| format!("{what} names mesh {name}, which <asset> lacks"))?;
                let path = self
                    .path
                    .parent()
                    .unwrap_or(Path::new("."))
                    .join(&self.meshdir)
                    .join(file);
                if !path.is_file() {
                    return Err(format!(
                        "{what}: mesh {name}: no such file {}",
                        path.display()
                    ));
                }
                let mut mesh = crate::loaders::load_mesh(&path).map_err(|e| e.to_string())?;
                let s = vec3(Some(scale), &what, [1.0; 3])?.cast::<f32>();
                for p in &mut mesh.positions {
                    *p = Point3::new(p.x * s.x, p.y * s.y, p.z * s.z);
                }
                mesh.materials = vec![material];
                mesh.triangle_materials = vec![0; mesh.triangles.len()];
                mesh
            }
            "box" => {
                let h = vec3(self.attr(node, class, "size"), &what, [0.0; 3])?.cast::<f32>();
                let mut b = MeshBuilder::new(material);
                b.cuboid(Point3::from(-h), Point3::from(h), 0);
                b.finish()
            }
            "cylinder" => {
                let size = numbers(self.attr(node, class, "size").unwrap_or("0 0"), &what)?;
                let (r, h) = (
                    size.first().copied().unwrap_or(0.0) as f32,
                    size.get(1).copied().unwrap_or(0.0) as f32,
                );
                let mut b = MeshBuilder::new(material);
                crate::gripper::cylinder(&mut b, r, -h, h, 32, 0);
                b.finish()
            }
            other => {
                return Err(format!(
                    "{what} is a {other}; drawn are mesh, box and cylinder geoms (or put it in group 3)"
                ));
            }
        };
        let frame = self.frame(node, class, &what)?;
        for p in &mut mesh.positions {
            *p = (frame * p.cast::<f64>()).cast::<f32>();
        }
        mesh.normals.clear();
        mesh.compute_normals();
        Ok(Some(mesh))
    }

    /// The joint that places `body` (with class `class`) in its parent.
    fn joint(
        &self,
        body: Node<'a, 'a>,
        class: &str,
        parent: &str,
        name: &str,
    ) -> Result<Joint, String> {
        let origin = self.frame(body, class, &format!("body {name}"))?;
        let joints: Vec<Node> = body
            .children()
            .filter(|n| n.has_tag_name("joint"))
            .collect();
        let Some(&j) = joints.first() else {
            return Ok(Joint::fixed(
                format!("{name} (fixed)"),
                parent,
                name,
                origin,
            ));
        };
        if joints.len() > 1 {
            return Err(format!(
                "body {name} has {} joints; a gripper's bodies have one at most",
                joints.len()
            ));
        }
        let class = j.attribute("class").unwrap_or(class);
        let joint_name = j.attribute("name").unwrap_or(name).to_string();
        let what = format!("joint {joint_name}");
        let motion = match self.attr(j, class, "type").unwrap_or("hinge") {
            "hinge" => Motion::Revolute,
            "slide" => Motion::Prismatic,
            other => {
                return Err(format!(
                    "{what} is a {other} joint; a gripper's joints are hinge or slide"
                ));
            }
        };
        let axis = vec3(self.attr(j, class, "axis"), &what, [0.0, 0.0, 1.0])?;
        if axis.norm() < 1e-9 {
            return Err(format!("{what} has a zero axis"));
        }
        let pos = vec3(self.attr(j, class, "pos"), &what, [0.0; 3])?;
        let (mut lower, mut upper) = (0.0, 0.0);
        if let Some(range) = self.attr(j, class, "range") {
            match numbers(range, &what)?.as_slice() {
                [a, b] => (lower, upper) = (*a, *b),
                _ => return Err(format!("{what}: range `{range}` needs two numbers")),
            }
            if motion == Motion::Revolute {
                (lower, upper) = (self.angle(lower), self.angle(upper));
            }
        }
        Ok(Joint {
            name: joint_name,
            parent: parent.into(),
            child: name.into(),
            origin: origin * Isometry3::translation(pos.x, pos.y, pos.z),
            post: Isometry3::translation(-pos.x, -pos.y, -pos.z),
            axis: axis.normalize(),
            motion,
            lower,
            upper,
            mimic: None,
            actuated: false,
        })
    }

    /// Walks the bodies under `node` (the body `name`, class `class`).
    fn subtree(
        &self,
        node: Node<'a, 'a>,
        name: &str,
        class: &str,
        tree: &mut Tree,
    ) -> Result<(), String> {
        for geom in node.children().filter(|n| n.has_tag_name("geom")) {
            if let Some(mesh) = self.geom(geom, class, name)? {
                tree.meshes.push(LinkMesh {
                    link: name.into(),
                    mesh,
                });
            }
        }
        for site in node.children().filter(|n| n.has_tag_name("site")) {
            if let Some(site_name) = site.attribute("name") {
                let origin = self.frame(site, class, &format!("site {site_name}"))?;
                tree.joints.push(Joint::fixed(
                    format!("{site_name} (site)"),
                    name,
                    site_name,
                    origin,
                ));
            }
        }
        for (k, child) in node
            .children()
            .filter(|n| n.has_tag_name("body"))
            .enumerate()
        {
            let child_name = child
                .attribute("name")
                .map_or_else(|| format!("{name}/body{k}"), String::from);
            let child_class = child.attribute("childclass").unwrap_or(class);
            tree.joints
                .push(self.joint(child, child_class, name, &child_name)?);
            self.subtree(child, &child_name, child_class, tree)?;
        }
        Ok(())
    }
}

/// Finds the body `name` under `node`, with the class in force for it.
fn find_body<'a>(node: Node<'a, 'a>, name: &str, class: &str) -> Option<(Node<'a, 'a>, String)> {
    for body in node.children().filter(|n| n.has_tag_name("body")) {
        let class = body.attribute("childclass").unwrap_or(class);
        if body.attribute("name") == Some(name) {
            return Some((body, class.to_string()));
        }
        if let Some(found) = find_body(body, name, class) {
            return Some(found);
        }
    }
    None
}

/// `<compiler eulerseq>`, "xyz" when absent.
fn euler_sequence(compiler: Option<Node>) -> Result<String, String> {
    let seq = compiler
        .and_then(|c| c.attribute("eulerseq"))
        .unwrap_or("xyz");
    if seq.len() == 3 && seq.chars().all(|c| "xyzXYZ".contains(c)) {
        Ok(seq.to_string())
    } else {
        Err(format!(
            "compiler: eulerseq `{seq}` is not three of x, y, z (turns about the moving axes) and X, Y, Z (about the fixed ones)"
        ))
    }
}

/// The gripper under body `root` of the MJCF `text` at `path`.
pub(crate) fn tree(text: &str, path: &Path, root: &str) -> Result<Tree, String> {
    let doc = Document::parse(text).map_err(|e| format!("not readable XML: {e}"))?;
    let mujoco = doc.root_element();
    let compiler = mujoco.children().find(|n| n.has_tag_name("compiler"));
    let mut reader = Reader {
        path,
        defaults: Defaults::read(mujoco),
        radians: compiler.and_then(|c| c.attribute("angle")) == Some("radian"),
        eulerseq: euler_sequence(compiler)?,
        meshdir: compiler
            .and_then(|c| c.attribute("meshdir"))
            .unwrap_or("")
            .to_string(),
        meshes: BTreeMap::new(),
        materials: BTreeMap::new(),
    };
    for asset in mujoco.children().filter(|n| n.has_tag_name("asset")) {
        for m in asset.children().filter(|n| n.has_tag_name("mesh")) {
            let file = m.attribute("file").ok_or("a <mesh> asset has no file")?;
            let name = m.attribute("name").map_or_else(
                || {
                    Path::new(file)
                        .file_stem()
                        .map_or(file.to_string(), |s| s.to_string_lossy().into_owned())
                },
                String::from,
            );
            let scale = reader
                .attr(m, "main", "scale")
                .unwrap_or("1 1 1")
                .to_string();
            reader.meshes.insert(name, (file.to_string(), scale));
        }
        for m in asset.children().filter(|n| n.has_tag_name("material")) {
            if let (Some(name), Some(rgba)) = (m.attribute("name"), m.attribute("rgba")) {
                let c = colour(rgba, &format!("material {name}"))?;
                reader.materials.insert(name.into(), c);
            }
        }
    }
    let world = mujoco
        .children()
        .find(|n| n.has_tag_name("worldbody"))
        .ok_or("no <worldbody>")?;
    let (body, class) = find_body(world, root, "main").ok_or_else(|| {
        let mut names = Vec::new();
        for n in world.descendants().filter(|n| n.has_tag_name("body")) {
            names.extend(n.attribute("name").map(String::from));
        }
        format!(
            "no body `{root}` (--gripper-root); its bodies are {}",
            names.join(", ")
        )
    })?;
    let mut tree = Tree::default();
    reader.subtree(body, root, &class, &mut tree)?;
    equalities(mujoco, &mut tree)?;
    mark_actuated(mujoco, &mut tree);
    Ok(tree)
}

/// `<equality>`: joint couplings as mimics, `connect`s as loop closures
/// (the anchor's partner point taken at the rest pose, as MuJoCo does).
fn equalities(mujoco: Node, tree: &mut Tree) -> Result<(), String> {
    let rest = rest_poses(tree);
    for eq in mujoco.children().filter(|n| n.has_tag_name("equality")) {
        for c in eq.children().filter(|n| n.is_element()) {
            match c.tag_name().name() {
                "joint" => {
                    let (a, b) = (
                        c.attribute("joint1").unwrap_or(""),
                        c.attribute("joint2").unwrap_or(""),
                    );
                    let coef = numbers(c.attribute("polycoef").unwrap_or("0 1 0 0 0"), "polycoef")?;
                    if coef.iter().skip(2).any(|&v| v != 0.0) {
                        return Err(format!(
                            "the coupling of {a} to {b} is not linear (polycoef beyond the second)"
                        ));
                    }
                    if let Some(j) = tree.joints.iter_mut().find(|j| j.name == a) {
                        j.mimic = Some((b.into(), coef.get(1).copied().unwrap_or(1.0), coef[0]));
                    }
                }
                "connect" => {
                    let (a, b) = (
                        c.attribute("body1").unwrap_or(""),
                        c.attribute("body2").unwrap_or(""),
                    );
                    let (Some(pa), Some(pb)) = (rest.get(a), rest.get(b)) else {
                        continue; // a loop outside the gripper
                    };
                    let anchor = vec3(c.attribute("anchor"), "connect anchor", [0.0; 3])?;
                    let anchor_a = Point3::from(anchor);
                    tree.closures.push(Closure {
                        link_a: a.into(),
                        anchor_a,
                        link_b: b.into(),
                        anchor_b: pb.inverse() * (pa * anchor_a),
                    });
                }
                _ => {}
            }
        }
    }
    Ok(())
}

/// Each body's pose in the root at rest (every joint at 0).
fn rest_poses(tree: &Tree) -> BTreeMap<String, Isometry3<f64>> {
    let mut poses = BTreeMap::new();
    for j in &tree.joints {
        let parent = poses
            .get(&j.parent)
            .copied()
            .unwrap_or_else(Isometry3::identity);
        poses.insert(j.child.clone(), parent * j.origin * j.post);
    }
    poses
}

/// The joints the actuators drive (directly or through a fixed tendon);
/// every moving joint when no actuator names one.
fn mark_actuated(mujoco: Node, tree: &mut Tree) {
    let mut tendons: BTreeMap<&str, Vec<&str>> = BTreeMap::new();
    for t in mujoco.children().filter(|n| n.has_tag_name("tendon")) {
        for fixed in t.children().filter(|n| n.has_tag_name("fixed")) {
            let joints = fixed
                .children()
                .filter(|n| n.has_tag_name("joint"))
                .filter_map(|n| n.attribute("joint"))
                .collect();
            tendons.insert(fixed.attribute("name").unwrap_or(""), joints);
        }
    }
    let mut driven: Vec<&str> = Vec::new();
    for a in mujoco.children().filter(|n| n.has_tag_name("actuator")) {
        for act in a.children().filter(|n| n.is_element()) {
            driven.extend(act.attribute("joint"));
            if let Some(t) = act.attribute("tendon") {
                driven.extend(tendons.get(t).into_iter().flatten());
            }
        }
    }
    let any = tree
        .joints
        .iter()
        .any(|j| driven.contains(&j.name.as_str()));
    for j in &mut tree.joints {
        j.actuated = j.motion != Motion::Fixed
            && j.mimic.is_none()
            && (driven.contains(&j.name.as_str()) || (!any && tree.closures.is_empty()));
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;
    use std::path::Path;

    use nalgebra::{UnitQuaternion, Vector3};
    use omniscan_core::capture::RobotSpec;
    use roxmltree::Document;

    use super::{Defaults, Reader};
    use crate::robot::RobotGripper;

    /// The orientation a `<body ATTRS/>` gives, angles in degrees.
    fn orientation(attrs: &str, eulerseq: &str) -> Result<UnitQuaternion<f64>, String> {
        let xml = format!("<body {attrs}/>");
        let doc = Document::parse(&xml).unwrap();
        let reader = Reader {
            path: Path::new("hand.xml"),
            defaults: Defaults {
                classes: BTreeMap::new(),
            },
            radians: false,
            eulerseq: eulerseq.into(),
            meshdir: String::new(),
            meshes: BTreeMap::new(),
            materials: BTreeMap::new(),
        };
        reader.orientation(doc.root_element(), "body b")
    }

    fn maps(q: UnitQuaternion<f64>, from: [f64; 3], to: [f64; 3]) -> bool {
        (q * Vector3::from(from) - Vector3::from(to)).norm() < 1e-12
    }

    #[test]
    fn orientations_follow_mujocos_conventions() {
        let turn = |attrs: &str| orientation(attrs, "xyz").unwrap();
        // About the moving axes, Ry(90°) then Rz(90°) after it: R = Ry Rz,
        // and x -> Rz -> y -> Ry -> y.
        assert!(maps(
            turn(r#"euler="0 90 90""#),
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0]
        ));
        // About the fixed axes: R = Rz Ry, x -> Ry -> -z -> Rz -> -z.
        let fixed = orientation(r#"euler="0 90 90""#, "XYZ").unwrap();
        assert!(maps(fixed, [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]));
        let quarter_about_z = [
            r#"axisangle="0 0 2 90""#,
            r#"quat="0.7071067811865476 0 0 0.7071067811865476""#,
            r#"xyaxes="0 1 0 -1 0 0""#,
            // y need not be orthogonal to x: its part along x is dropped.
            r#"xyaxes="0 2 0 -1 5 0""#,
            r#"euler="0 0 90""#,
        ];
        for attrs in quarter_about_z {
            let q = turn(attrs);
            assert!(maps(q, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]), "{attrs}");
            assert!(maps(q, [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]), "{attrs}");
        }
        // zaxis: the shortest turn taking z there.
        let q = turn(r#"zaxis="1 0 0""#);
        assert!(maps(q, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]));
        assert!(maps(q, [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]));
        assert!(maps(
            turn(r#"zaxis="0 0 -3""#),
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0]
        ));
        assert_eq!(turn(""), UnitQuaternion::identity());
    }

    #[test]
    fn bad_orientations_are_refused_by_name() {
        let e = orientation(r#"euler="0 90""#, "xyz").unwrap_err();
        assert!(e.contains("body b: euler needs 3 numbers, not 2"), "{e}");
        let e = orientation(r#"quat="1 0 0 0" euler="0 0 0""#, "xyz").unwrap_err();
        assert!(
            e.contains("give one orientation, not quat and euler"),
            "{e}"
        );
        let e = orientation(r#"xyaxes="1 0 0 2 0 0""#, "xyz").unwrap_err();
        assert!(e.contains("xyaxes' y is too small"), "{e}");
        let e = orientation(r#"zaxis="0 0 0""#, "xyz").unwrap_err();
        assert!(e.contains("zaxis is too small"), "{e}");
        let dir = tempfile::tempdir().unwrap();
        let text = hand("0.7 0.7 0.7 1", "slide").replace(
            "<mujoco model=\"hand\">",
            "<mujoco model=\"hand\"><compiler eulerseq=\"xyw\"/>",
        );
        let e = load(dir.path(), &text, "palm").unwrap_err();
        assert!(
            e.contains("hand.xml") && e.contains("eulerseq `xyw`"),
            "{e}"
        );
    }

    #[test]
    fn a_hand_reads_the_same_whichever_way_its_finger_is_turned() {
        let dir = tempfile::tempdir().unwrap();
        for turned in [
            r#"euler="0 0 180""#,
            r#"axisangle="0 0 1 180""#,
            r#"xyaxes="-1 0 0 0 -1 0""#,
        ] {
            let text = hand("0.7 0.7 0.7 1", "slide").replace(r#"quat="0 0 0 1""#, turned);
            let gripper = load(dir.path(), &text, "palm").unwrap();
            assert!((gripper.max_opening_m() - 0.07).abs() < 1e-6, "{turned}");
        }
    }

    /// A parallel hand in MJCF: two slide fingers (boxes, half-sizes as MJCF
    /// gives them), the second coupled to the first by an equality, the
    /// first driven by an actuator, the TCP a site; degrees by default.
    fn hand(finger_rgba: &str, joint_type: &str) -> String {
        format!(
            r#"<mujoco model="hand">
  <default><default class="finger"><joint type="{joint_type}" axis="1 0 0" range="0 0.03"/></default></default>
  <worldbody>
    <body name="palm" pos="1 2 3" axisangle="0 0 1 30">
      <geom type="box" size="0.035 0.015 0.02" pos="0 0 0.02" rgba="0.2 0.2 0.2 1"/>
      <geom type="box" size="0.1 0.1 0.1" group="3"/>
      <site name="tcp" pos="0 0 0.08"/>
      <body name="finger_a" pos="0 0 0.04" childclass="finger">
        <joint name="a"/>
        <geom type="box" size="0.004 0.01 0.025" pos="0.009 0 0.025" rgba="{finger_rgba}"/>
      </body>
      <body name="finger_b" pos="0 0 0.04" quat="0 0 0 1" childclass="finger">
        <joint name="b"/>
        <geom type="box" size="0.004 0.01 0.025" pos="0.009 0 0.025"/>
      </body>
    </body>
  </worldbody>
  <equality><joint joint1="b" joint2="a" polycoef="0 1 0 0 0"/></equality>
  <actuator><position name="fingers" joint="a"/></actuator>
</mujoco>"#
        )
    }

    fn load(dir: &std::path::Path, text: &str, root: &str) -> Result<RobotGripper, String> {
        let path = dir.join("hand.xml");
        std::fs::write(&path, text).unwrap();
        let spec = RobotSpec {
            description: path.display().to_string(),
            gripper_root: root.into(),
            tcp_link: Some("tcp".into()),
            tcp_offset_m: None,
        };
        RobotGripper::load(&spec, std::path::Path::new("/")).map_err(|e| e.to_string())
    }

    #[test]
    fn an_mjcf_hand_opens_along_its_coupled_slides() {
        let dir = tempfile::tempdir().unwrap();
        let gripper = load(dir.path(), &hand("0.7 0.7 0.7 1", "slide"), "palm").unwrap();
        // Inner faces at ±(5 mm + q): 10 mm closed, 70 mm at 30 mm of travel.
        assert!(
            (gripper.max_opening_m() - 0.07).abs() < 1e-6,
            "{}",
            gripper.max_opening_m()
        );
        assert!((gripper.opening_at("a", 0.01).unwrap() - 0.03).abs() < 1e-6);
        assert_eq!(gripper.opening_at("b", 0.01), None, "b follows a");
        // The collision box (group 3) is not drawn: palm, two fingers.
        assert_eq!(gripper.placed(0.03).len(), 3);
    }

    #[test]
    fn bad_mjcf_is_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let e = load(dir.path(), &hand("0.7 0.7", "slide"), "palm").unwrap_err();
        assert!(
            e.contains("hand.xml") && e.contains("rgba `0.7 0.7` needs four numbers"),
            "{e}"
        );
        let e = load(dir.path(), &hand("0.7 0.7 0.7 1", "ball"), "palm").unwrap_err();
        assert!(e.contains("joint a is a ball joint"), "{e}");
        let e = load(dir.path(), &hand("0.7 0.7 0.7 1", "slide"), "wrist").unwrap_err();
        assert!(
            e.contains("no body `wrist`") && e.contains("palm, finger_a, finger_b"),
            "{e}"
        );
        let e = load(dir.path(), "<mujoco><worldbody>", "palm").unwrap_err();
        assert!(e.contains("not readable XML"), "{e}");
    }
}
