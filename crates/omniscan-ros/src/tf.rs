//! A TF tree from `/tf` and `/tf_static`, looked up at a time as tf2 does:
//! each frame has one parent; a dynamic edge is interpolated between the
//! samples around the time (linear translation, spherical rotation), and a
//! lookup outside an edge's samples, or across a gap longer than allowed,
//! is an error rather than an extrapolation.

use std::collections::BTreeMap;

use nalgebra::{Quaternion, Translation3, UnitQuaternion};
use omniscan_core::geometry::Pose;

use crate::msgs::TransformStamped;

#[derive(Debug, Clone, Default)]
struct Edge {
    parent: String,
    fixed: Option<Pose>,
    /// (stamp ns, parent_T_child), sorted by stamp once [`TfTree::finish`] ran.
    samples: Vec<(i64, Pose)>,
}

/// The frames and their transforms, as recorded.
#[derive(Debug, Clone, Default)]
pub struct TfTree {
    edges: BTreeMap<String, Edge>,
}

/// A frame's pose in its parent from a message; `None` for a non-finite or
/// zero quaternion.
fn pose_of(t: &TransformStamped) -> Option<Pose> {
    let (v, q) = (t.transform.translation, t.transform.rotation);
    let values = [v.x, v.y, v.z, q.x, q.y, q.z, q.w];
    if values.iter().any(|x| !x.is_finite()) {
        return None;
    }
    let q = Quaternion::new(q.w, q.x, q.y, q.z);
    if q.norm() < 1e-9 {
        return None;
    }
    Some(Pose::from_parts(
        Translation3::new(v.x, v.y, v.z),
        UnitQuaternion::from_quaternion(q),
    ))
}

/// Seconds, for messages.
pub fn seconds(ns: i64) -> f64 {
    ns as f64 * 1e-9
}

impl TfTree {
    /// Adds one transform (`is_static` for `/tf_static`).
    pub fn add(&mut self, t: &TransformStamped, is_static: bool) -> Result<(), String> {
        let (parent, child) = (&t.header.frame_id, &t.child_frame_id);
        let pose = pose_of(t).ok_or_else(|| {
            format!(
                "the transform {parent} -> {child} at {:.6} s has a non-finite value or a zero quaternion",
                seconds(t.header.stamp.ns())
            )
        })?;
        let edge = self.edges.entry(child.clone()).or_insert_with(|| Edge {
            parent: parent.clone(),
            ..Edge::default()
        });
        if &edge.parent != parent {
            return Err(format!(
                "frame {child} has two parents, {} and {parent}; a TF tree gives each frame one",
                edge.parent
            ));
        }
        if is_static {
            edge.fixed = Some(pose);
        } else {
            edge.samples.push((t.header.stamp.ns(), pose));
        }
        Ok(())
    }

    /// Sorts the samples; call once everything is added.
    pub fn finish(&mut self) {
        for edge in self.edges.values_mut() {
            edge.samples.sort_by_key(|(t, _)| *t);
        }
    }

    /// Whether the tree knows `frame` (as a child or as a parent).
    pub fn has_frame(&self, frame: &str) -> bool {
        self.edges.contains_key(frame) || self.edges.values().any(|e| e.parent == frame)
    }

    /// Every frame the tree knows, for errors.
    pub fn frames(&self) -> Vec<String> {
        let mut frames: Vec<String> = self
            .edges
            .iter()
            .flat_map(|(child, e)| [child.clone(), e.parent.clone()])
            .collect();
        frames.sort();
        frames.dedup();
        frames
    }

    /// `root_T_frame` at `t_ns`; samples further apart than `max_gap_ns`
    /// around the time are an error.
    pub fn lookup(
        &self,
        root: &str,
        frame: &str,
        t_ns: i64,
        max_gap_ns: i64,
    ) -> Result<Pose, String> {
        let mut pose = Pose::identity();
        let mut current = frame.to_string();
        let mut steps = 0;
        while current != root {
            let Some(edge) = self.edges.get(&current) else {
                return Err(if self.has_frame(frame) {
                    format!("frame {frame} is not connected to {root} (its tree ends at {current})")
                } else {
                    format!("no TF names frame {frame}")
                });
            };
            pose = edge_pose(edge, &current, t_ns, max_gap_ns)? * pose;
            current = edge.parent.clone();
            steps += 1;
            if steps > self.edges.len() {
                return Err(format!("the TF tree above {frame} has a cycle"));
            }
        }
        Ok(pose)
    }
}

fn edge_pose(edge: &Edge, child: &str, t_ns: i64, max_gap_ns: i64) -> Result<Pose, String> {
    if let Some(fixed) = edge.fixed {
        return Ok(fixed);
    }
    let samples = &edge.samples;
    let name = || format!("{} -> {child}", edge.parent);
    let after = samples.partition_point(|(s, _)| *s < t_ns);
    if let Some((s, p)) = samples.get(after)
        && *s == t_ns
    {
        return Ok(*p);
    }
    if after == 0 || after == samples.len() {
        let (first, last) = (samples[0].0, samples[samples.len() - 1].0);
        return Err(format!(
            "TF {} has no sample around {:.6} s (its samples span {:.6} to {:.6} s)",
            name(),
            seconds(t_ns),
            seconds(first),
            seconds(last)
        ));
    }
    let ((t0, p0), (t1, p1)) = (samples[after - 1], samples[after]);
    if t1 - t0 > max_gap_ns {
        return Err(format!(
            "TF {} has a gap of {:.3} s around {:.6} s (at most {:.3} s is interpolated; see --max-tf-gap-s)",
            name(),
            seconds(t1 - t0),
            seconds(t_ns),
            seconds(max_gap_ns)
        ));
    }
    let s = (t_ns - t0) as f64 / (t1 - t0) as f64;
    let translation = p0.translation.vector.lerp(&p1.translation.vector, s);
    let rotation = p0.rotation.try_slerp(&p1.rotation, s, 1e-9).ok_or_else(|| {
        format!(
            "TF {} turns half a revolution between {:.6} and {:.6} s; it cannot be interpolated",
            name(),
            seconds(t0),
            seconds(t1)
        )
    })?;
    Ok(Pose::from_parts(translation.into(), rotation))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{Header, Time, Transform, TransformStamped};
    use nalgebra::Vector3;

    fn sample(parent: &str, child: &str, t_ns: i64, pose: &Pose) -> TransformStamped {
        let (v, q) = (pose.translation.vector, pose.rotation.quaternion());
        TransformStamped {
            header: Header {
                stamp: Time {
                    sec: (t_ns / 1_000_000_000) as i32,
                    nanosec: (t_ns % 1_000_000_000) as u32,
                },
                frame_id: parent.into(),
            },
            child_frame_id: child.into(),
            transform: Transform {
                translation: crate::msgs::Vector3 {
                    x: v.x,
                    y: v.y,
                    z: v.z,
                },
                rotation: crate::msgs::Quaternion {
                    x: q.i,
                    y: q.j,
                    z: q.k,
                    w: q.w,
                },
            },
        }
    }

    /// A frame turning about z at a constant rate while moving in a straight
    /// line: slerp and lerp between samples are exact for it.
    fn moving(t_s: f64) -> Pose {
        Pose::from_parts(
            Translation3::new(0.1 * t_s, -0.02 * t_s, 0.3),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.4 * t_s),
        )
    }

    #[test]
    fn lookups_compose_static_and_interpolated_edges_and_refuse_gaps() {
        let base = Pose::from_parts(
            Translation3::new(1.0, 2.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.2),
        );
        let mut tree = TfTree::default();
        tree.add(&sample("world", "base", 0, &base), true).unwrap();
        for i in [0i64, 1, 2, 5] {
            let t = i * 100_000_000;
            tree.add(&sample("base", "tool", t, &moving(t as f64 * 1e-9)), false)
                .unwrap();
        }
        tree.finish();
        let gap = 150_000_000;
        for t in [0i64, 50_000_000, 137_000_000, 200_000_000] {
            let got = tree.lookup("world", "tool", t, gap).unwrap();
            let want = base * moving(t as f64 * 1e-9);
            let (rad, m) = omniscan_core::geometry::pose_difference(&got, &want);
            assert!(rad < 1e-12 && m < 1e-12, "at {t}: {rad} rad {m} m");
        }
        let e = tree.lookup("world", "tool", 300_000_000, gap).unwrap_err();
        assert!(e.contains("gap of 0.300 s"), "{e}");
        let e = tree.lookup("world", "tool", 600_000_000, gap).unwrap_err();
        assert!(e.contains("no sample around 0.600000 s"), "{e}");
        let e = tree.lookup("world", "camera", 0, gap).unwrap_err();
        assert!(e.contains("no TF names frame camera"), "{e}");
        let e = tree.lookup("map", "tool", 0, gap).unwrap_err();
        assert!(e.contains("not connected to map"), "{e}");
        let e = tree
            .add(&sample("world", "tool", 0, &base), false)
            .unwrap_err();
        assert!(e.contains("two parents"), "{e}");
    }
}
