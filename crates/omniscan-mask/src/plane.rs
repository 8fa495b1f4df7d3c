//! Single-channel images (grey levels, depth, flow components, masks) and the
//! few filters the masking stage needs. Kept here rather than pulling in an
//! image-processing crate: the stage needs a box filter, a 2x pyramid,
//! bilinear sampling, binary dilation and connected components, each a few
//! lines, on plain `Vec`s that the rest of the stage indexes directly.

use omniscan_core::image_io::{DepthMm, Mask, RgbImage};

/// A row-major single-channel image.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane<T> {
    pub width: usize,
    pub height: usize,
    pub data: Vec<T>,
}

impl<T: Copy> Plane<T> {
    pub fn filled(width: usize, height: usize, value: T) -> Self {
        Plane {
            width,
            height,
            data: vec![value; width * height],
        }
    }

    #[inline]
    pub fn at(&self, x: usize, y: usize) -> T {
        self.data[y * self.width + x]
    }

    pub fn len(&self) -> usize {
        self.data.len()
    }

    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
}

impl Plane<f32> {
    /// Luminance in 0..1 of an 8-bit RGB image.
    pub fn luminance(image: &RgbImage) -> Self {
        let data = image
            .data
            .chunks_exact(3)
            .map(|p| (0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32) / 255.0)
            .collect();
        Plane {
            width: image.width as usize,
            height: image.height as usize,
            data,
        }
    }

    /// Depth in metres, 0 where the sensor has no measurement.
    pub fn depth_metres(depth: &DepthMm) -> Self {
        let scale = omniscan_core::image_io::DEPTH_METRES_PER_UNIT as f32;
        Plane {
            width: depth.width as usize,
            height: depth.height as usize,
            data: depth.data.iter().map(|&d| d as f32 * scale).collect(),
        }
    }

    /// Mean over a (2r+1)² window, clamped at the borders (separable running sums).
    pub fn box_mean(&self, radius: usize) -> Plane<f32> {
        let (w, h) = (self.width, self.height);
        let mut tmp = vec![0f32; w * h];
        for y in 0..h {
            let row = &self.data[y * w..(y + 1) * w];
            running_mean(row, radius, &mut tmp[y * w..(y + 1) * w]);
        }
        let mut out = vec![0f32; w * h];
        let mut column = vec![0f32; h];
        let mut column_out = vec![0f32; h];
        for x in 0..w {
            for y in 0..h {
                column[y] = tmp[y * w + x];
            }
            running_mean(&column, radius, &mut column_out);
            for y in 0..h {
                out[y * w + x] = column_out[y];
            }
        }
        Plane {
            width: w,
            height: h,
            data: out,
        }
    }

    /// Half-size image: 2x2 means (odd trailing rows/columns are dropped).
    pub fn half(&self) -> Plane<f32> {
        let (w, h) = ((self.width / 2).max(1), (self.height / 2).max(1));
        let mut data = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let (x0, y0) = ((2 * x).min(self.width - 1), (2 * y).min(self.height - 1));
                let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
                data.push(
                    0.25 * (self.at(x0, y0) + self.at(x1, y0) + self.at(x0, y1) + self.at(x1, y1)),
                );
            }
        }
        Plane {
            width: w,
            height: h,
            data,
        }
    }

    /// Bilinear sample at continuous pixel coordinates (pixel centres at
    /// integers), clamped at the borders.
    #[inline]
    pub fn sample(&self, x: f32, y: f32) -> f32 {
        let x = x.clamp(0.0, (self.width - 1) as f32);
        let y = y.clamp(0.0, (self.height - 1) as f32);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let top = self.at(x0, y0) * (1.0 - fx) + self.at(x1, y0) * fx;
        let bottom = self.at(x0, y1) * (1.0 - fx) + self.at(x1, y1) * fx;
        top * (1.0 - fy) + bottom * fy
    }
}

/// Running mean of `input` over a window of `radius`, clamped at the ends.
fn running_mean(input: &[f32], radius: usize, out: &mut [f32]) {
    let n = input.len();
    if n == 0 {
        return;
    }
    let mut prefix = Vec::with_capacity(n + 1);
    prefix.push(0f64);
    let mut sum = 0f64;
    for &v in input {
        sum += v as f64;
        prefix.push(sum);
    }
    for (i, o) in out.iter_mut().enumerate() {
        let lo = i.saturating_sub(radius);
        let hi = (i + radius + 1).min(n);
        *o = ((prefix[hi] - prefix[lo]) / (hi - lo) as f64) as f32;
    }
}

impl Plane<bool> {
    pub fn from_mask(mask: &Mask) -> Self {
        Plane {
            width: mask.width as usize,
            height: mask.height as usize,
            data: mask.data.iter().map(|&v| v >= 128).collect(),
        }
    }

    pub fn to_mask(&self) -> Mask {
        Mask {
            width: self.width as u32,
            height: self.height as u32,
            data: self.data.iter().map(|&v| if v { 255 } else { 0 }).collect(),
        }
    }

    pub fn count(&self) -> usize {
        self.data.iter().filter(|&&v| v).count()
    }

    /// Binary dilation by a square of half-size `radius`.
    pub fn dilate(&self, radius: usize) -> Plane<bool> {
        self.morph(radius, true)
    }

    /// Binary erosion by a square of half-size `radius` (outside counts as set).
    pub fn erode(&self, radius: usize) -> Plane<bool> {
        self.morph(radius, false)
    }

    fn morph(&self, radius: usize, dilate: bool) -> Plane<bool> {
        if radius == 0 {
            return self.clone();
        }
        let (w, h) = (self.width, self.height);
        // A square structuring element is separable: rows, then columns.
        let pass =
            |src: &[bool], len: usize, lines: usize, index: &dyn Fn(usize, usize) -> usize| {
                let mut out = vec![!dilate; src.len()];
                for line in 0..lines {
                    // Distance to the nearest "hit" (set for dilation, unset for erosion) seen so far.
                    let mut last_hit: Option<usize> = None;
                    let mut next_hit = vec![usize::MAX; len];
                    let mut upcoming = usize::MAX;
                    for i in (0..len).rev() {
                        if src[index(line, i)] == dilate {
                            upcoming = i;
                        }
                        next_hit[i] = upcoming;
                    }
                    for i in 0..len {
                        if src[index(line, i)] == dilate {
                            last_hit = Some(i);
                        }
                        let near_before = last_hit.is_some_and(|j| i - j <= radius);
                        let near_after = next_hit[i] != usize::MAX && next_hit[i] - i <= radius;
                        out[index(line, i)] = if near_before || near_after {
                            dilate
                        } else {
                            !dilate
                        };
                    }
                }
                out
            };
        let rows = pass(&self.data, w, h, &|y, x| y * w + x);
        let data = pass(&rows, h, w, &|x, y| y * w + x);
        Plane {
            width: w,
            height: h,
            data,
        }
    }

    /// 4-connected components of set pixels: a label per pixel (`u32::MAX`
    /// for unset pixels) and the size of each component.
    pub fn components(&self) -> (Plane<u32>, Vec<usize>) {
        self.components_joined_by(|_, _| true)
    }

    /// 4-connected components of set pixels where neighbours `i` and `j`
    /// (pixel indices) belong together only when `joins(i, j)`.
    pub fn components_joined_by(
        &self,
        joins: impl Fn(usize, usize) -> bool,
    ) -> (Plane<u32>, Vec<usize>) {
        let (w, h) = (self.width, self.height);
        let mut labels = vec![u32::MAX; w * h];
        let mut sizes = Vec::new();
        let mut stack = Vec::new();
        for start in 0..w * h {
            if !self.data[start] || labels[start] != u32::MAX {
                continue;
            }
            let label = sizes.len() as u32;
            let mut size = 0;
            labels[start] = label;
            stack.push(start);
            while let Some(i) = stack.pop() {
                size += 1;
                let (x, y) = (i % w, i / w);
                let mut visit = |j: usize| {
                    if self.data[j] && labels[j] == u32::MAX && joins(i, j) {
                        labels[j] = label;
                        stack.push(j);
                    }
                };
                if x > 0 {
                    visit(i - 1);
                }
                if x + 1 < w {
                    visit(i + 1);
                }
                if y > 0 {
                    visit(i - w);
                }
                if y + 1 < h {
                    visit(i + w);
                }
            }
            sizes.push(size);
        }
        (
            Plane {
                width: w,
                height: h,
                data: labels,
            },
            sizes,
        )
    }

    /// Drops set components smaller than `min_pixels` and fills unset
    /// components smaller than `max_hole_pixels` that do not touch the border.
    pub fn cleaned(&self, min_pixels: usize, max_hole_pixels: usize) -> Plane<bool> {
        let (labels, sizes) = self.components();
        let mut out = self.clone();
        for (o, &l) in out.data.iter_mut().zip(&labels.data) {
            if l != u32::MAX && sizes[l as usize] < min_pixels {
                *o = false;
            }
        }
        let holes = Plane {
            width: self.width,
            height: self.height,
            data: out.data.iter().map(|&v| !v).collect(),
        };
        let (hole_labels, hole_sizes) = holes.components();
        let mut touches_border = vec![false; hole_sizes.len()];
        let (w, h) = (self.width, self.height);
        for y in 0..h {
            for x in 0..w {
                if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                    let l = hole_labels.data[y * w + x];
                    if l != u32::MAX {
                        touches_border[l as usize] = true;
                    }
                }
            }
        }
        for (o, &l) in out.data.iter_mut().zip(&hole_labels.data) {
            if l != u32::MAX
                && !touches_border[l as usize]
                && hole_sizes[l as usize] <= max_hole_pixels
            {
                *o = true;
            }
        }
        out
    }
}

/// Intersection over union of two masks; 1 when both are empty.
pub fn iou(a: &Plane<bool>, b: &Plane<bool>) -> f64 {
    let (mut inter, mut union) = (0usize, 0usize);
    for (&x, &y) in a.data.iter().zip(&b.data) {
        inter += (x && y) as usize;
        union += (x || y) as usize;
    }
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_mean_of_a_constant_is_the_constant_and_of_an_impulse_spreads_it() {
        let p = Plane::filled(7, 5, 2.0f32);
        assert!(p.box_mean(2).data.iter().all(|&v| (v - 2.0).abs() < 1e-6));
        let mut q = Plane::filled(9, 9, 0.0f32);
        q.data[4 * 9 + 4] = 9.0;
        let m = q.box_mean(1);
        assert!((m.at(4, 4) - 1.0).abs() < 1e-6);
        assert!((m.at(3, 5) - 1.0).abs() < 1e-6);
        assert_eq!(m.at(2, 4), 0.0);
    }

    #[test]
    fn dilation_and_erosion_by_a_square() {
        let mut p = Plane::filled(9, 9, false);
        p.data[4 * 9 + 4] = true;
        let d = p.dilate(2);
        assert_eq!(d.count(), 25);
        assert!(d.at(2, 2) && d.at(6, 6) && !d.at(1, 4));
        assert_eq!(d.erode(2).count(), 1);
    }

    #[test]
    fn components_and_cleaning() {
        let mut p = Plane::filled(10, 10, false);
        for y in 1..8 {
            for x in 1..8 {
                p.data[y * 10 + x] = true;
            }
        }
        p.data[4 * 10 + 4] = false; // a one-pixel hole
        p.data[9 * 10 + 9] = true; // a speck
        let (_, sizes) = p.components();
        assert_eq!(sizes.len(), 2);
        let c = p.cleaned(2, 4);
        assert!(c.at(4, 4), "hole filled");
        assert!(!c.at(9, 9), "speck removed");
        assert_eq!(c.count(), 49);
    }

    #[test]
    fn iou_cases() {
        let a = Plane {
            width: 2,
            height: 2,
            data: vec![true, true, false, false],
        };
        let b = Plane {
            width: 2,
            height: 2,
            data: vec![true, false, true, false],
        };
        assert!((iou(&a, &b) - 1.0 / 3.0).abs() < 1e-12);
        let empty = Plane::filled(2, 2, false);
        assert_eq!(iou(&empty, &empty), 1.0);
    }
}
