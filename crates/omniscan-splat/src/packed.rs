//! Training views as they wait in memory between steps: each shrunk pixel
//! kept as the integers it was made from (8-bit colour sums, object
//! sub-pixel counts, gripper flags, depth in millimetres) instead of the
//! floats a step reads, and made into a [`View`] again only when a step
//! needs it.
//!
//! Why: training visits every view many times, so all of them stay in
//! memory, and as floats a view costs 24 bytes a pixel. The paper's scans are
//! 100 4K images an arm: 40 GB for both arms at full size, 10 GB at half
//! size. Packed, a full-size pixel takes 7 bytes (3 of colour, 1 of object,
//! 1 of gripper, 2 of depth) and a shrunk one 10, and unpacking repeats the
//! very arithmetic the floats were made by, so a packed view trains
//! bit-for-bit as its floats did. Blocks over 15 pixels wide (a count of
//! sub-pixels past 255) are kept as floats. Measured: `train` on the demo
//! capture's 200 views at full size peaked at 1.78 GB with floats and at
//! 0.72 GB packed, to the same model by md5.
//!
//! The shrinking itself (box filter, object-only colour, "any" for the
//! gripper, nearest depth) is done here, as [`crate::views`] reads a view.

use rayon::prelude::*;

use omniscan_core::image_io::{DepthMm, Mask, RgbImage};

use crate::raster::Camera;
use crate::view::{Pixel, TrainingView, View};

/// The widest block whose sub-pixel counts fit a byte (15² = 225) and whose
/// colour sums fit 16 bits (225 · 255 < 65,536).
const WIDEST_PACKED_BLOCK: u32 = 15;

/// One view, packed ([module docs](self)).
#[derive(Debug, Clone, PartialEq)]
pub struct PackedView {
    pub camera: Camera<f32>,
    colour: Colour,
    /// 1 where every loss term is zeroed (see [`View::excluded`]).
    excluded: Vec<u8>,
    /// Sensor depth, millimetres, 0 where unknown; empty if there is none.
    depth_mm: Vec<u16>,
}

/// Each shrunk pixel's colour and object coverage.
#[derive(Debug, Clone, PartialEq)]
enum Colour {
    /// Full size: each pixel's 8-bit colour, and 1 on the object.
    FullSize {
        colour: Vec<[u8; 3]>,
        object: Vec<u8>,
    },
    /// Shrunk by `block` (2 to [`WIDEST_PACKED_BLOCK`]): `inside[i]` of the
    /// block's sub-pixels are on the object, and `sums[i]` adds their 8-bit
    /// colours (every sub-pixel's where none is).
    Shrunk {
        block: u32,
        inside: Vec<u8>,
        sums: Vec<[u16; 3]>,
    },
    /// Shrunk by more: as a step reads it.
    Floats {
        image: Vec<[f32; 3]>,
        object: Vec<f32>,
    },
}

/// An 8-bit colour as training reads it (a full-size pixel is its own
/// block of one, and x / 1 is x, so this is the shrunk formula's value).
fn full_size_colour(v: u8) -> f32 {
    f32::from(v) / 255.0
}

/// A depth in millimetres as training reads it, in metres (0: unknown).
fn metres(mm: u16) -> f32 {
    mm as f32 * 0.001
}

/// A shrunk pixel's colour and coverage from its colour sums and the count
/// of its `sub_pixels` on the object.
fn shrunk_colour(sum: [u32; 3], inside: u32, sub_pixels: u32) -> ([f32; 3], f32) {
    let count = if inside > 0 { inside } else { sub_pixels };
    (
        sum.map(|v| v as f32 / 255.0 / count as f32),
        inside as f32 / sub_pixels as f32,
    )
}

impl PackedView {
    /// Shrinks a photo by `block` (≥ 1, dividing nothing: the last partial
    /// row and column are dropped) with its object mask, gripper or unseen
    /// mask (`None`: nothing excluded) and depth map, all the photo's size.
    /// The caller checks the sizes.
    pub fn shrink(
        camera: Camera<f32>,
        rgb: &RgbImage,
        object: &Mask,
        excluded: Option<&Mask>,
        depth: Option<&DepthMm>,
        block: u32,
    ) -> PackedView {
        let (w, h) = (rgb.width / block, rgb.height / block);
        PackedView {
            camera,
            colour: shrink_object(rgb, object, block),
            excluded: match excluded {
                Some(mask) => shrink_any(mask, block),
                None => vec![0; (w * h) as usize],
            },
            depth_mm: depth.map(|d| shrink_depth(d, block)).unwrap_or_default(),
        }
    }

    /// Pixel `i`'s values as a step reads them.
    pub fn pixel(&self, i: usize) -> Pixel {
        let (colour, object) = match &self.colour {
            Colour::FullSize { colour, object } => {
                (colour[i].map(full_size_colour), f32::from(object[i]))
            }
            Colour::Shrunk {
                block,
                inside,
                sums,
            } => shrunk_colour(sums[i].map(u32::from), u32::from(inside[i]), block * block),
            Colour::Floats { image, object } => (image[i], object[i]),
        };
        Pixel {
            colour,
            object,
            excluded: f32::from(self.excluded[i]),
            depth: self.depth_mm.get(i).map_or(0.0, |&mm| metres(mm)),
        }
    }

    /// The view a step reads, the same to the bit as shrinking to floats.
    pub fn unpack(&self) -> View {
        let mut view = View {
            camera: self.camera,
            image: Vec::new(),
            object: Vec::new(),
            excluded: Vec::new(),
            depth: Vec::new(),
        };
        self.unpack_into(&mut view);
        view
    }

    /// [`unpack`](Self::unpack) into `view`'s buffers, which a step reuses
    /// (see [`crate::view::TrainingView::pixels_in`]).
    pub fn unpack_into(&self, view: &mut View) {
        let n = self.excluded.len();
        view.camera = self.camera;
        view.image.resize(n, [0.0; 3]);
        view.object.resize(n, 0.0);
        view.excluded.resize(n, 0.0);
        view.depth
            .resize(if self.depth_mm.is_empty() { 0 } else { n }, 0.0);
        let colour_and_object = view.image.par_iter_mut().zip(view.object.par_iter_mut());
        match &self.colour {
            Colour::FullSize { colour, object } => {
                let table: [f32; 256] = std::array::from_fn(|v| full_size_colour(v as u8));
                colour_and_object
                    .zip(colour.par_iter().zip(object))
                    .for_each(|((c, o), (packed, &on))| {
                        *c = packed.map(|v| table[usize::from(v)]);
                        *o = f32::from(on);
                    });
            }
            Colour::Shrunk {
                block,
                inside,
                sums,
            } => colour_and_object.zip(sums.par_iter().zip(inside)).for_each(
                |((c, o), (&sum, &inside))| {
                    (*c, *o) = shrunk_colour(sum.map(u32::from), u32::from(inside), block * block)
                },
            ),
            Colour::Floats { image, object } => {
                view.image.copy_from_slice(image);
                view.object.copy_from_slice(object);
            }
        }
        view.excluded
            .par_iter_mut()
            .zip(&self.excluded)
            .for_each(|(e, &x)| *e = f32::from(x));
        view.depth
            .par_iter_mut()
            .zip(&self.depth_mm)
            .for_each(|(z, &mm)| *z = metres(mm));
    }

    /// Bytes a pixel of a view shrunk by `block` takes packed, with or
    /// without depth: what [`pixel_bytes`](Self::pixel_bytes) comes to,
    /// known before any image is read.
    pub fn bytes_per_pixel(block: u32, depth: bool) -> usize {
        let colour = match block {
            1 => 3 + 1,
            2..=WIDEST_PACKED_BLOCK => 6 + 1,
            _ => 12 + 4,
        };
        colour + 1 + if depth { 2 } else { 0 }
    }

    /// Bytes its pixels take in memory.
    pub fn pixel_bytes(&self) -> usize {
        let colour = match &self.colour {
            Colour::FullSize { colour, object } => colour.len() * 3 + object.len(),
            Colour::Shrunk { inside, sums, .. } => inside.len() + sums.len() * 6,
            Colour::Floats { image, object } => image.len() * 12 + object.len() * 4,
        };
        colour + self.excluded.len() + self.depth_mm.len() * 2
    }
}

/// The sub-pixel offsets of block (x, y) of size `f` in an image `full_w` wide.
fn block_pixels(x: usize, y: usize, f: usize, full_w: usize) -> impl Iterator<Item = usize> {
    (0..f * f).map(move |d| (y * f + d / f) * full_w + x * f + d % f)
}

/// A photo and its object mask shrunk by `f` (box filter): each pixel's
/// object coverage, and its colour averaged over its object sub-pixels only
/// (over all of them where it has none). Colour × coverage is then the
/// object alone over black, the exact shrunk composite that training and
/// evaluation compare renders with. Averaging the whole photo instead mixed
/// the background behind the object's edge (DTU's white table beside dark
/// steel) into every edge pixel's target, an error no render of the object
/// can match.
fn shrink_object(rgb: &RgbImage, mask: &Mask, f: u32) -> Colour {
    let (w, h) = ((rgb.width / f) as usize, (rgb.height / f) as usize);
    let full_w = rgb.width as usize;
    let blocks: Vec<(u32, [u32; 3])> = (0..w * h)
        .into_par_iter()
        .map(|o| {
            let (mut all, mut object, mut inside) = ([0u32; 3], [0u32; 3], 0u32);
            for p in block_pixels(o % w, o / w, f as usize, full_w) {
                let is_object = mask.data[p] >= 128;
                inside += is_object as u32;
                for c in 0..3 {
                    let v = rgb.data[p * 3 + c] as u32;
                    all[c] += v;
                    object[c] += v * is_object as u32;
                }
            }
            (inside, if inside > 0 { object } else { all })
        })
        .collect();
    // The narrowing casts below hold by WIDEST_PACKED_BLOCK's arithmetic.
    match f {
        1 => Colour::FullSize {
            colour: blocks.iter().map(|(_, s)| s.map(|v| v as u8)).collect(),
            object: blocks.iter().map(|&(inside, _)| inside as u8).collect(),
        },
        2..=WIDEST_PACKED_BLOCK => Colour::Shrunk {
            block: f,
            inside: blocks.iter().map(|&(inside, _)| inside as u8).collect(),
            sums: blocks.iter().map(|(_, s)| s.map(|v| v as u16)).collect(),
        },
        _ => {
            let (image, object) = blocks
                .into_iter()
                .map(|(inside, sum)| shrunk_colour(sum, inside, f * f))
                .unzip();
            Colour::Floats { image, object }
        }
    }
}

/// A mask shrunk by `f`: 1 where any pixel of the block is in it (a pixel
/// partly on the gripper, or partly unseen, is left out of the loss whole),
/// 0 elsewhere.
fn shrink_any(mask: &Mask, f: u32) -> Vec<u8> {
    let (w, h) = ((mask.width / f) as usize, (mask.height / f) as usize);
    let full_w = mask.width as usize;
    (0..w * h)
        .into_par_iter()
        .map(|o| {
            u8::from(block_pixels(o % w, o / w, f as usize, full_w).any(|p| mask.data[p] >= 128))
        })
        .collect()
}

/// A depth map shrunk by `f`: each block's nearest valid sample, 0 where it
/// has none (still millimetres: [`PackedView::unpack`] makes metres).
fn shrink_depth(depth: &DepthMm, f: u32) -> Vec<u16> {
    let (w, h) = ((depth.width / f) as usize, (depth.height / f) as usize);
    let full_w = depth.width as usize;
    (0..w * h)
        .into_par_iter()
        .map(|o| {
            block_pixels(o % w, o / w, f as usize, full_w)
                .map(|p| depth.data[p])
                .filter(|&mm| mm > 0)
                .min()
                .unwrap_or(0)
        })
        .collect()
}

impl TrainingView for PackedView {
    fn camera(&self) -> &Camera<f32> {
        &self.camera
    }

    fn pixels(&self) -> std::borrow::Cow<'_, View> {
        std::borrow::Cow::Owned(self.unpack())
    }

    fn pixels_in<'a>(&'a self, scratch: &'a mut Option<View>) -> &'a View {
        match scratch {
            Some(view) => {
                self.unpack_into(view);
                view
            }
            None => scratch.insert(self.unpack()),
        }
    }

    fn pixel(&self, i: usize) -> Pixel {
        PackedView::pixel(self, i)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::Lcg;

    /// Shrinking straight to floats, as views were made before packing:
    /// the reference a packed view must match to the bit.
    fn floats_directly(
        rgb: &RgbImage,
        mask: &Mask,
        excluded: &Mask,
        depth: &DepthMm,
        f: usize,
    ) -> (Vec<[f32; 3]>, Vec<f32>, Vec<f32>, Vec<f32>) {
        let (w, h, full_w) = (
            rgb.width as usize / f,
            rgb.height as usize / f,
            rgb.width as usize,
        );
        let (mut image, mut coverage) = (vec![[0.0f32; 3]; w * h], vec![0.0f32; w * h]);
        let (mut gone, mut near) = (vec![0.0f32; w * h], vec![0.0f32; w * h]);
        for y in 0..h {
            for x in 0..w {
                let (mut all, mut object, mut inside) = ([0u32; 3], [0u32; 3], 0u32);
                let o = y * w + x;
                for dy in 0..f {
                    for dx in 0..f {
                        let p = (y * f + dy) * full_w + x * f + dx;
                        let is_object = mask.data[p] >= 128;
                        inside += is_object as u32;
                        for c in 0..3 {
                            let v = rgb.data[p * 3 + c] as u32;
                            all[c] += v;
                            object[c] += v * is_object as u32;
                        }
                        if excluded.data[p] >= 128 {
                            gone[o] = 1.0;
                        }
                        let z = depth.data[p] as f32 * 0.001;
                        if z > 0.0 && (near[o] == 0.0 || z < near[o]) {
                            near[o] = z;
                        }
                    }
                }
                coverage[o] = inside as f32 / (f * f) as f32;
                let (sum, count) = if inside > 0 {
                    (object, inside)
                } else {
                    (all, (f * f) as u32)
                };
                image[o] = sum.map(|v| v as f32 / 255.0 / count as f32);
            }
        }
        (image, coverage, gone, near)
    }

    /// A pinhole at the origin, for views whose camera nothing reads.
    fn camera(width: u32, height: u32) -> Camera<f32> {
        let mut viewmat = [[0.0; 4]; 4];
        (0..4).for_each(|i| viewmat[i][i] = 1.0);
        crate::test_support::pinhole(viewmat, 10.0, width, height)
    }

    fn bits<const N: usize>(v: &[[f32; N]]) -> Vec<[u32; N]> {
        v.iter().map(|p| p.map(f32::to_bits)).collect()
    }

    #[test]
    fn a_packed_view_unpacks_to_the_floats_shrinking_made_for_every_block_size() {
        let (width, height) = (34u32, 32u32);
        let n = (width * height) as usize;
        let mut lcg = Lcg(7);
        let mut byte = |p: f64| (lcg.next() * 256.0) as u8 & if lcg.next() < p { 0 } else { 255 };
        // Masks and depth with holes, so blocks of every kind occur: all
        // object, none, part; depth missing in some sub-pixels, in all of others.
        let rgb = RgbImage {
            width,
            height,
            data: (0..n * 3).map(|_| byte(0.0)).collect(),
        };
        let mask = |bytes: Vec<u8>| Mask {
            width,
            height,
            data: bytes,
        };
        let object = mask(
            (0..n)
                .map(|i| if (i / 5) % 3 == 0 { 0 } else { 200 })
                .collect(),
        );
        let excluded = mask((0..n).map(|_| byte(0.9)).collect());
        let depth = DepthMm {
            width,
            height,
            data: (0..n)
                .map(|i| {
                    if i % 7 < 3 {
                        0
                    } else {
                        250 + (i as u16 * 37) % 4000
                    }
                })
                .collect(),
        };
        let camera = camera(34, 32);
        for f in [1u32, 2, 3, 15, 16] {
            let packed =
                PackedView::shrink(camera, &rgb, &object, Some(&excluded), Some(&depth), f);
            let view = packed.unpack();
            let (image, coverage, gone, near) =
                floats_directly(&rgb, &object, &excluded, &depth, f as usize);
            assert_eq!(bits(&view.image), bits(&image), "block {f}");
            let as_bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(as_bits(&view.object), as_bits(&coverage), "block {f}");
            assert_eq!(as_bits(&view.excluded), as_bits(&gone), "block {f}");
            assert_eq!(as_bits(&view.depth), as_bits(&near), "block {f}");
            // Part-object blocks occur at every size, so the test sees
            // colour averaged over a block's object sub-pixels only.
            assert!(view.object.iter().any(|&c| c > 0.0 && c < 1.0) || f == 1);
            let per_pixel = packed.pixel_bytes() as f64 / view.image.len() as f64;
            assert_eq!(per_pixel, PackedView::bytes_per_pixel(f, true) as f64);
            assert_eq!(
                per_pixel,
                [7.0, 10.0, 19.0][(f > 1) as usize + (f > 15) as usize]
            );
        }
    }

    #[test]
    fn shrinking_keeps_the_background_out_of_the_object_edge() {
        // A 4x2 photo shrunk by 2: the left block is half object (dark red)
        // on a white table, the right block is all table.
        let (object, table) = ([60u8, 10, 10], [250u8, 250, 250]);
        let is_object = [true, false, false, false, true, false, false, false];
        let rgb = RgbImage {
            width: 4,
            height: 2,
            data: is_object
                .iter()
                .flat_map(|&o| if o { object } else { table })
                .collect(),
        };
        let mask = Mask {
            width: 4,
            height: 2,
            data: is_object.iter().map(|&o| if o { 255 } else { 0 }).collect(),
        };
        let view = PackedView::shrink(camera(2, 1), &rgb, &mask, None, None, 2).unpack();
        let (image, coverage) = (view.image, view.object);
        assert_eq!(coverage, vec![0.5, 0.0]);
        // Colour × coverage is the object alone over black: half the red, no white.
        let composite = image[0].map(|c| c * coverage[0]);
        for (c, o) in composite.iter().zip(object) {
            assert!((c - 0.5 * o as f32 / 255.0).abs() < 1e-6, "{composite:?}");
        }
        // A block without object keeps the photo's mean.
        assert!(image[1].iter().all(|&c| (c - 250.0 / 255.0).abs() < 1e-6));
    }

    /// Unpacking into buffers another view left behind (a larger one, with
    /// depth) gives what a fresh unpack does.
    #[test]
    fn unpacking_into_used_buffers_leaves_nothing_of_their_last_view() {
        let photo = |width: u32, height: u32, seed: u64| {
            let mut lcg = Lcg(seed);
            let n = (width * height) as usize;
            let rgb = RgbImage {
                width,
                height,
                data: (0..n * 3).map(|_| (lcg.next() * 256.0) as u8).collect(),
            };
            let mask = Mask {
                width,
                height,
                data: (0..n).map(|i| if i % 3 == 0 { 0 } else { 255 }).collect(),
            };
            (rgb, mask)
        };
        let (big, big_mask) = photo(40, 34, 1);
        let depth = DepthMm {
            width: 40,
            height: 34,
            data: vec![700; 40 * 34],
        };
        let (small, small_mask) = photo(32, 16, 2);
        for block in [1, 2, 16] {
            let first = PackedView::shrink(
                camera(40, 34),
                &big,
                &big_mask,
                Some(&big_mask),
                Some(&depth),
                1,
            );
            let second = PackedView::shrink(
                camera(32 / block, 16 / block),
                &small,
                &small_mask,
                None,
                None,
                block,
            );
            let mut buffers = first.unpack();
            second.unpack_into(&mut buffers);
            let fresh = second.unpack();
            assert_eq!(buffers.image, fresh.image);
            assert_eq!(
                (&buffers.object, &buffers.excluded, &buffers.depth),
                (&fresh.object, &fresh.excluded, &fresh.depth)
            );
            assert!(buffers.depth.is_empty());
            assert_eq!(buffers.camera, fresh.camera);
        }
    }

    #[test]
    fn nothing_excluded_and_no_depth_unpack_to_zeros_and_nothing() {
        let rgb = RgbImage {
            width: 4,
            height: 2,
            data: vec![9; 24],
        };
        let object = Mask {
            width: 4,
            height: 2,
            data: vec![255; 8],
        };
        let packed = PackedView::shrink(camera(2, 1), &rgb, &object, None, None, 2);
        let view = packed.unpack();
        assert_eq!(view.excluded, vec![0.0, 0.0]);
        assert!(view.depth.is_empty());
        assert_eq!(
            packed.pixel_bytes(),
            2 * PackedView::bytes_per_pixel(2, false)
        );
        assert_eq!(view.object, vec![1.0, 1.0]);
    }
}
