//! One training view: its camera and pixels (colour, object mask, excluded
//! pixels, depth), and [`TrainingView`], how training reads a view whether
//! it is held as floats ([`View`]) or packed ([`crate::packed`]).

use crate::raster::Camera;

/// One training image with its masks.
#[derive(Debug, Clone)]
pub struct View {
    pub camera: Camera<f32>,
    pub image: Vec<[f32; 3]>,
    /// 1 on the object, 0 elsewhere.
    pub object: Vec<f32>,
    /// 1 where every loss term is zeroed, 0 elsewhere: the gripper (the
    /// paper's gripper-agnostic losses), or where an undistorted photo's lens
    /// saw nothing ([`omniscan_core::lens`]).
    pub excluded: Vec<f32>,
    /// Sensor depth along the optical axis, metres, 0 where unknown; empty if the capture has none.
    pub depth: Vec<f32>,
}

/// One pixel of a training view, as [`View`] holds it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pixel {
    pub colour: [f32; 3],
    pub object: f32,
    pub excluded: f32,
    /// Metres; 0 where unknown or where the view has no depth.
    pub depth: f32,
}

/// What training reads of a view: its camera at any time, its pixels when a
/// step needs them. A [`View`] lends its own; a [`PackedView`](crate::packed::PackedView) is unpacked.
pub trait TrainingView: Sync {
    fn camera(&self) -> &Camera<f32>;
    /// The view's pixels.
    fn pixels(&self) -> std::borrow::Cow<'_, View>;
    /// The view's pixels, made in `scratch` if they must be made: a loop
    /// over views reuses one set of buffers (a 4K view unpacks in 13 ms on
    /// two threads into used buffers, in 140 ms into fresh ones, most of it
    /// page faults).
    fn pixels_in<'a>(&'a self, scratch: &'a mut Option<View>) -> &'a View;
    /// Pixel `i` alone, as [`pixels`](Self::pixels) would give it.
    fn pixel(&self, i: usize) -> Pixel;
}

impl TrainingView for View {
    fn camera(&self) -> &Camera<f32> {
        &self.camera
    }

    fn pixels(&self) -> std::borrow::Cow<'_, View> {
        std::borrow::Cow::Borrowed(self)
    }

    fn pixels_in<'a>(&'a self, _: &'a mut Option<View>) -> &'a View {
        self
    }

    fn pixel(&self, i: usize) -> Pixel {
        Pixel {
            colour: self.image[i],
            object: self.object[i],
            excluded: self.excluded[i],
            depth: self.depth.get(i).copied().unwrap_or(0.0),
        }
    }
}
