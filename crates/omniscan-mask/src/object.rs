//! Object masks by the paper's pipeline ("Object Mask Generation"):
//!
//! 1. Foreground: pixels whose depth is small (nearer than the gripper's
//!    tool point plus a margin, from the kinematics) and that move between
//!    neighbouring frames (non-zero optical flow).
//! 2. Candidate segments of the near region (the paper prompts SAM with the
//!    foreground; a candidate must overlap the moving foreground).
//! 3. Scores per candidate M: the non-robot score
//!    S_NR = mean over p in M of |D_curr(p) − D_empty(p)|, with D_empty the
//!    empty-gripper pass at the same pose (the arm and the static scene look
//!    the same with and without the object), and the non-gripper score
//!    S_NG = 1 − |M ∩ G| / |M|.
//!    Where the empty pass shows its own closed fingers, D_empty says nothing
//!    about the robot now (the fingers have opened around the object), so
//!    those pixels are left out of the mean; the kinematics say where they are.
//! 4. The object mask is the union of candidates with S_NR ≥ t_NR and
//!    S_NG ≥ t_NG; gripper pixels are then removed and specks and pinholes
//!    cleaned (our additions: a pixel cannot be both, and a twin's opacity
//!    loss is hurt more by speckle than by a slightly conservative outline).
//!
//! Depth here is metric (the capture's sensor depth, metres) where the paper
//! thresholds relative mono-depth at 140 on its 0-255 scale; our threshold
//! t_NR is in metres and was chosen by measurement (`omniscan bench mask`).
//! The paper's t_NG = 0.89 is kept.

use omniscan_core::image_io::RgbImage;

use crate::plane::Plane;
use crate::segment::{CandidateProposer, SegmentSettings};

/// Thresholds of the object-mask pipeline.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ObjectSettings {
    /// Foreground depth limit beyond the gripper's tool point, metres.
    pub near_margin_m: f32,
    /// Flow magnitude that counts as motion, pixels.
    pub min_flow_px: f32,
    /// Share of a candidate's pixels that must be moving foreground.
    pub min_moving_fraction: f32,
    /// t_NR: smallest mean depth change against the empty-gripper pass, metres.
    pub non_robot_threshold_m: f32,
    /// t_NG: smallest share of a candidate outside the gripper mask (paper: 0.89).
    pub non_gripper_threshold: f32,
    /// Object components smaller than this are dropped, pixels.
    pub min_component_px: usize,
    /// Holes up to this size inside the object are filled, pixels.
    pub max_hole_px: usize,
    pub segmentation: SegmentSettings,
}

impl Default for ObjectSettings {
    fn default() -> Self {
        ObjectSettings {
            near_margin_m: 0.15,
            min_flow_px: 0.5,
            min_moving_fraction: 0.02,
            non_robot_threshold_m: 0.008,
            non_gripper_threshold: 0.89,
            min_component_px: 30,
            max_hole_px: 30,
            segmentation: SegmentSettings::default(),
        }
    }
}

/// What the object pipeline needs for one frame.
pub struct ObjectInputs<'a> {
    pub image: &'a RgbImage,
    /// Current depth, metres (0 = no measurement).
    pub depth_m: &'a Plane<f32>,
    /// Depth of the empty-gripper pass at the same pose, metres.
    pub empty_depth_m: &'a Plane<f32>,
    /// The gripper mask G.
    pub gripper: &'a Plane<bool>,
    /// Pixels where the empty-gripper pass shows the gripper itself (its
    /// fingers closed), from the kinematics. There D_empty is not what the
    /// robot looks like now, since the fingers have opened around the object.
    pub empty_gripper: Option<&'a Plane<bool>>,
    /// Pixels with non-zero flow to a neighbouring frame.
    pub moving: &'a Plane<bool>,
    /// Depth (z in the camera frame) of the gripper's tool point, metres.
    pub tool_depth_m: f32,
}

/// One scored candidate.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Candidate {
    pub pixels: usize,
    /// S_NR, metres.
    pub non_robot_m: f32,
    /// S_NG.
    pub non_gripper: f32,
    pub moving_fraction: f32,
    pub kept: bool,
}

/// The object mask of one frame and how it was chosen.
#[derive(Debug, Clone, PartialEq)]
pub struct ObjectMask {
    pub mask: Plane<bool>,
    pub foreground_pixels: usize,
    pub candidates: Vec<Candidate>,
}

/// Runs the pipeline of the module doc on one frame.
pub fn object_mask(
    inputs: &ObjectInputs,
    proposer: &dyn CandidateProposer,
    settings: &ObjectSettings,
) -> crate::Result<ObjectMask> {
    let (w, h) = (inputs.image.width as usize, inputs.image.height as usize);
    let n = w * h;
    for (name, len) in [
        ("depth", inputs.depth_m.len()),
        ("empty-gripper depth", inputs.empty_depth_m.len()),
        ("gripper mask", inputs.gripper.len()),
        ("motion mask", inputs.moving.len()),
    ] {
        if len != n {
            return Err(crate::MaskError::Invalid(format!(
                "the {name} has {len} pixels but the image {w}x{h} has {n}"
            )));
        }
    }
    let limit = inputs.tool_depth_m + settings.near_margin_m;
    let near = Plane {
        width: w,
        height: h,
        data: inputs
            .depth_m
            .data
            .iter()
            .map(|&d| d > 0.0 && d < limit)
            .collect(),
    };
    let foreground: Vec<bool> = near
        .data
        .iter()
        .zip(&inputs.moving.data)
        .map(|(&a, &b)| a && b)
        .collect();
    let foreground_pixels = foreground.iter().filter(|&&f| f).count();
    let segmentation = proposer.propose(inputs.image, inputs.depth_m, &near, inputs.gripper)?;

    // SAM, prompted with foreground points, returns whole objects; our
    // segments are smaller, so a segment counts as prompted when the
    // depth-connected surface it lies on moves. A part that spins about its
    // own axis (a torch held along the wrist axis) shows no flow on its
    // smooth end, yet that end is joined in depth to the textured middle.
    let surfaces = depth_connected(
        &near,
        inputs.depth_m,
        inputs.gripper,
        settings.segmentation.depth_jump_m,
    );
    let mut surface_moving = vec![0usize; surfaces.1.len()];
    for i in 0..n {
        let s = surfaces.0.data[i];
        if s != u32::MAX && foreground[i] {
            surface_moving[s as usize] += 1;
        }
    }

    let count = segmentation.sizes.len();
    let mut surface_of = vec![u32::MAX; count];
    let mut moving = vec![0usize; count];
    let mut in_gripper = vec![0usize; count];
    let mut depth_change = vec![0f64; count];
    let mut depth_pixels = vec![0usize; count];
    for i in 0..n {
        let l = segmentation.labels.data[i];
        if l == u32::MAX {
            continue;
        }
        let l = l as usize;
        surface_of[l] = surfaces.0.data[i];
        moving[l] += foreground[i] as usize;
        in_gripper[l] += inputs.gripper.data[i] as usize;
        let (d, e) = (inputs.depth_m.data[i], inputs.empty_depth_m.data[i]);
        let stale = inputs.empty_gripper.is_some_and(|g| g.data[i]);
        if d > 0.0 && e > 0.0 && !stale {
            depth_change[l] += (d - e).abs() as f64;
            depth_pixels[l] += 1;
        }
    }
    let candidates: Vec<Candidate> = (0..count)
        .map(|l| {
            let pixels = segmentation.sizes[l];
            // A candidate seen only where the empty pass had its closed
            // fingers shows something in a place the robot has left: not robot.
            let non_robot_m = if depth_pixels[l] > 0 {
                (depth_change[l] / depth_pixels[l] as f64) as f32
            } else if inputs.empty_gripper.is_some() {
                f32::INFINITY
            } else {
                0.0
            };
            let non_gripper = 1.0 - in_gripper[l] as f32 / pixels.max(1) as f32;
            let surface_fraction = match surface_of[l] {
                u32::MAX => 0.0,
                sf => surface_moving[sf as usize] as f32 / surfaces.1[sf as usize].max(1) as f32,
            };
            let moving_fraction = (moving[l] as f32 / pixels.max(1) as f32).max(surface_fraction);
            let kept = non_robot_m >= settings.non_robot_threshold_m
                && non_gripper >= settings.non_gripper_threshold
                && moving_fraction >= settings.min_moving_fraction;
            Candidate {
                pixels,
                non_robot_m,
                non_gripper,
                moving_fraction,
                kept,
            }
        })
        .collect();
    let data = (0..n)
        .map(|i| {
            let l = segmentation.labels.data[i];
            l != u32::MAX && candidates[l as usize].kept && !inputs.gripper.data[i]
        })
        .collect();
    let mask = Plane {
        width: w,
        height: h,
        data,
    }
    .cleaned(settings.min_component_px, settings.max_hole_px);
    // Holes are filled only where they are not gripper.
    let mask = Plane {
        width: w,
        height: h,
        data: mask
            .data
            .iter()
            .zip(&inputs.gripper.data)
            .map(|(&m, &g)| m && !g)
            .collect(),
    };
    Ok(ObjectMask {
        mask,
        foreground_pixels,
        candidates,
    })
}

/// Connected components of `region` where 4-neighbours join when their
/// depths differ by at most `depth_jump_m` and both are on the same side of
/// the gripper mask: the separate surfaces in front of the camera.
fn depth_connected(
    region: &Plane<bool>,
    depth_m: &Plane<f32>,
    gripper: &Plane<bool>,
    depth_jump_m: f32,
) -> (Plane<u32>, Vec<usize>) {
    region.components_joined_by(|i, j| {
        gripper.data[j] == gripper.data[i]
            && (depth_m.data[j] - depth_m.data[i]).abs() <= depth_jump_m
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::segment::GraphSegmenter;

    /// A synthetic frame: wall at 1 m, an arm block that is the same in the
    /// empty pass, a gripper block, and an object disc, all near.
    struct Scene {
        image: RgbImage,
        depth: Plane<f32>,
        empty: Plane<f32>,
        gripper: Plane<bool>,
        moving: Plane<bool>,
        truth: Plane<bool>,
    }

    fn scene(
        w: usize,
        h: usize,
        object: impl Fn(usize, usize) -> bool,
        object_colour: [u8; 3],
    ) -> Scene {
        let mut image = vec![0u8; w * h * 3];
        let mut depth = vec![1.0f32; w * h];
        let mut empty = vec![1.0f32; w * h];
        let mut gripper = vec![false; w * h];
        let mut truth = vec![false; w * h];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let mut c = [150u8, 140, 120]; // wall
                if x >= w * 3 / 4 && (h / 3..2 * h / 3).contains(&y) {
                    c = [200, 200, 200]; // arm, in both passes
                    depth[i] = 0.45;
                    empty[i] = 0.45;
                }
                if (w / 2..w * 3 / 4).contains(&x) && (h * 2 / 5..h * 3 / 5).contains(&y) {
                    c = [40, 40, 45]; // gripper
                    depth[i] = 0.40;
                    empty[i] = 0.40;
                    gripper[i] = true;
                }
                if object(x, y) {
                    c = object_colour;
                    depth[i] = 0.38;
                    gripper[i] = false;
                    truth[i] = true;
                }
                image[3 * i..3 * i + 3].copy_from_slice(&c);
            }
        }
        fn plane<T>(w: usize, h: usize, data: Vec<T>) -> Plane<T> {
            Plane {
                width: w,
                height: h,
                data,
            }
        }
        let moving = plane(
            w,
            h,
            (0..w * h)
                .map(|i| truth[i] || gripper[i] || i % w >= w * 3 / 4)
                .collect::<Vec<bool>>(),
        );
        Scene {
            image: RgbImage {
                width: w as u32,
                height: h as u32,
                data: image,
            },
            depth: plane(w, h, depth),
            empty: plane(w, h, empty),
            gripper: plane(w, h, gripper),
            moving,
            truth: plane(w, h, truth),
        }
    }

    fn run(s: &Scene) -> ObjectMask {
        let inputs = ObjectInputs {
            image: &s.image,
            depth_m: &s.depth,
            empty_depth_m: &s.empty,
            gripper: &s.gripper,
            empty_gripper: None,
            moving: &s.moving,
            tool_depth_m: 0.40,
        };
        object_mask(
            &inputs,
            &GraphSegmenter::default(),
            &ObjectSettings::default(),
        )
        .unwrap()
    }

    #[test]
    fn keeps_the_object_and_rejects_arm_gripper_and_background() {
        let (w, h) = (80, 60);
        let s = scene(
            w,
            h,
            |x, y| (x as f32 - 30.0).hypot(y as f32 - 30.0) < 12.0,
            [30, 60, 200],
        );
        let out = run(&s);
        assert_eq!(out.mask, s.truth);
        // The arm's candidate was seen and rejected by S_NR, the gripper's by S_NG.
        assert!(
            out.candidates
                .iter()
                .any(|c| !c.kept && c.non_robot_m < 1e-6 && c.non_gripper > 0.99)
        );
        assert!(
            out.candidates
                .iter()
                .any(|c| !c.kept && c.non_gripper < 0.01)
        );
    }

    #[test]
    fn an_object_of_the_background_colour_at_the_border_is_still_found() {
        let (w, h) = (80, 60);
        let s = scene(
            w,
            h,
            |x, y| x < 20 && (10..50).contains(&y),
            [150, 140, 120],
        );
        let out = run(&s);
        assert_eq!(out.mask, s.truth);
    }

    #[test]
    fn a_hidden_object_gives_an_empty_mask_not_the_whole_image() {
        let (w, h) = (80, 60);
        let s = scene(w, h, |_, _| false, [0, 0, 0]);
        let out = run(&s);
        assert_eq!(out.mask.count(), 0);
        // No depth at all: nothing is near, nothing is object.
        let mut blind = scene(
            w,
            h,
            |x, y| (x as f32 - 30.0).hypot(y as f32 - 30.0) < 12.0,
            [30, 60, 200],
        );
        blind.depth.data.iter_mut().for_each(|d| *d = 0.0);
        assert_eq!(run(&blind).mask.count(), 0);
    }
}
