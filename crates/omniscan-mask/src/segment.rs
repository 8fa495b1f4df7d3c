//! Candidate segments, the weight-free backend of the paper's SAM role: the
//! object mask is a union of candidates, so candidates must follow the
//! object's outline.
//!
//! Algorithm: Felzenszwalb and Huttenlocher, "Efficient Graph-Based Image
//! Segmentation" (IJCV 2004), on an 8-connected pixel graph whose edge weight
//! is the colour difference plus a depth term, with two changes for in-hand
//! scans: edges across a depth jump are cut (the sensor's depth separates the
//! object from what is behind it far better than colour does), and edges
//! across the gripper mask's boundary are cut, so a candidate is never half
//! finger and half object. Written here because the only crate with this
//! algorithm wraps OpenCV (`../shared/notes/masking.md`).

use omniscan_core::image_io::RgbImage;

use crate::plane::Plane;

/// Settings of the graph segmentation.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SegmentSettings {
    /// Felzenszwalb's k: larger gives larger segments (colour units 0..1 per channel).
    pub scale: f32,
    /// Segments smaller than this are merged into a neighbour, pixels.
    pub min_pixels: usize,
    /// Weight of a depth step between neighbours, per metre.
    pub depth_weight_per_m: f32,
    /// Neighbours further apart in depth are never joined, metres.
    pub depth_jump_m: f32,
}

impl Default for SegmentSettings {
    fn default() -> Self {
        SegmentSettings {
            scale: 1.0,
            min_pixels: 40,
            depth_weight_per_m: 40.0,
            depth_jump_m: 0.012,
        }
    }
}

/// Non-overlapping candidate segments.
#[derive(Debug, Clone, PartialEq)]
pub struct Segmentation {
    /// Segment of each pixel; `u32::MAX` outside the segmented region.
    pub labels: Plane<u32>,
    /// Pixels per segment.
    pub sizes: Vec<usize>,
}

/// The candidate-segment role: a weight-free method or a learned one.
pub trait CandidateProposer: Send + Sync {
    fn name(&self) -> &str;
    /// Segments the pixels of `region`; no segment crosses the boundary of `barrier`.
    fn propose(
        &self,
        image: &RgbImage,
        depth_m: &Plane<f32>,
        region: &Plane<bool>,
        barrier: &Plane<bool>,
    ) -> crate::Result<Segmentation>;
}

/// Checks that every input of [`CandidateProposer::propose`] covers the image.
pub(crate) fn check_sizes(
    image: &RgbImage,
    depth_m: &Plane<f32>,
    region: &Plane<bool>,
    barrier: &Plane<bool>,
) -> crate::Result<()> {
    let n = (image.width * image.height) as usize;
    if depth_m.len() != n || region.len() != n || barrier.len() != n {
        return Err(crate::MaskError::Invalid(
            "segmentation inputs of different sizes".into(),
        ));
    }
    Ok(())
}

/// Felzenszwalb-Huttenlocher segmentation on colour and depth.
#[derive(Debug, Clone, Default)]
pub struct GraphSegmenter {
    pub settings: SegmentSettings,
}

impl CandidateProposer for GraphSegmenter {
    fn name(&self) -> &str {
        "graph"
    }

    fn propose(
        &self,
        image: &RgbImage,
        depth_m: &Plane<f32>,
        region: &Plane<bool>,
        barrier: &Plane<bool>,
    ) -> crate::Result<Segmentation> {
        check_sizes(image, depth_m, region, barrier)?;
        Ok(segment(image, depth_m, region, barrier, &self.settings))
    }
}

const BINS: usize = 2048;
const MAX_WEIGHT: f32 = 2.0;

struct Forest {
    parent: Vec<u32>,
    size: Vec<u32>,
    internal: Vec<f32>,
}

impl Forest {
    fn find(&mut self, mut i: u32) -> u32 {
        while self.parent[i as usize] != i {
            let p = self.parent[i as usize];
            self.parent[i as usize] = self.parent[p as usize];
            i = p;
        }
        i
    }
    fn union(&mut self, a: u32, b: u32, weight: f32) {
        let (big, small) = if self.size[a as usize] >= self.size[b as usize] {
            (a, b)
        } else {
            (b, a)
        };
        self.parent[small as usize] = big;
        self.size[big as usize] += self.size[small as usize];
        self.internal[big as usize] = weight
            .max(self.internal[big as usize])
            .max(self.internal[small as usize]);
    }
}

/// Segments `region` of an image (see the module doc).
pub fn segment(
    image: &RgbImage,
    depth_m: &Plane<f32>,
    region: &Plane<bool>,
    barrier: &Plane<bool>,
    settings: &SegmentSettings,
) -> Segmentation {
    let (w, h) = (image.width as usize, image.height as usize);
    let colour = |i: usize| -> [f32; 3] {
        let p = &image.data[3 * i..3 * i + 3];
        [
            p[0] as f32 / 255.0,
            p[1] as f32 / 255.0,
            p[2] as f32 / 255.0,
        ]
    };
    // Edges bucketed by quantised weight: a counting sort in O(edges).
    let mut buckets: Vec<Vec<(u32, u32)>> = vec![Vec::new(); BINS];
    let edge_weight = |i: usize, j: usize| -> Option<f32> {
        if !region.data[j] || barrier.data[i] != barrier.data[j] {
            return None;
        }
        let (di, dj) = (depth_m.data[i], depth_m.data[j]);
        let depth_step = if di > 0.0 && dj > 0.0 {
            (di - dj).abs()
        } else {
            0.0
        };
        if depth_step > settings.depth_jump_m {
            return None;
        }
        let (a, b) = (colour(i), colour(j));
        let c = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
        Some(c + settings.depth_weight_per_m * depth_step)
    };
    let push = |i: usize, j: usize, buckets: &mut Vec<Vec<(u32, u32)>>| {
        if let Some(weight) = edge_weight(i, j) {
            let bin = ((weight / MAX_WEIGHT) * (BINS - 1) as f32).min((BINS - 1) as f32) as usize;
            buckets[bin].push((i as u32, j as u32));
        }
    };
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if !region.data[i] {
                continue;
            }
            if x + 1 < w {
                push(i, i + 1, &mut buckets);
            }
            if y + 1 < h {
                push(i, i + w, &mut buckets);
                if x + 1 < w {
                    push(i, i + w + 1, &mut buckets);
                }
                if x > 0 {
                    push(i, i + w - 1, &mut buckets);
                }
            }
        }
    }
    let mut forest = Forest {
        parent: (0..(w * h) as u32).collect(),
        size: vec![1; w * h],
        internal: vec![0.0; w * h],
    };
    let bin_weight = |bin: usize| bin as f32 * MAX_WEIGHT / (BINS - 1) as f32;
    for (bin, edges) in buckets.iter().enumerate() {
        let weight = bin_weight(bin);
        for &(i, j) in edges {
            let (a, b) = (forest.find(i), forest.find(j));
            if a == b {
                continue;
            }
            let threshold_a =
                forest.internal[a as usize] + settings.scale / forest.size[a as usize] as f32;
            let threshold_b =
                forest.internal[b as usize] + settings.scale / forest.size[b as usize] as f32;
            if weight <= threshold_a.min(threshold_b) {
                forest.union(a, b, weight);
            }
        }
    }
    // Small segments join their most similar neighbour.
    for (bin, edges) in buckets.iter().enumerate() {
        let weight = bin_weight(bin);
        for &(i, j) in edges {
            let (a, b) = (forest.find(i), forest.find(j));
            let small = (forest.size[a as usize].min(forest.size[b as usize]) as usize)
                < settings.min_pixels;
            if a != b && small {
                forest.union(a, b, weight);
            }
        }
    }
    let mut labels = vec![u32::MAX; w * h];
    let mut root_label = vec![u32::MAX; w * h];
    let mut sizes = Vec::new();
    for i in 0..w * h {
        if !region.data[i] {
            continue;
        }
        let root = forest.find(i as u32) as usize;
        if root_label[root] == u32::MAX {
            root_label[root] = sizes.len() as u32;
            sizes.push(0);
        }
        labels[i] = root_label[root];
        sizes[root_label[root] as usize] += 1;
    }
    Segmentation {
        labels: Plane {
            width: w,
            height: h,
            data: labels,
        },
        sizes,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(w: usize, h: usize, colour: impl Fn(usize, usize) -> [u8; 3]) -> RgbImage {
        let mut data = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                data.extend_from_slice(&colour(x, y));
            }
        }
        RgbImage {
            width: w as u32,
            height: h as u32,
            data,
        }
    }

    #[test]
    fn two_colours_give_two_segments() {
        let img = image(
            40,
            30,
            |x, _| if x < 20 { [200, 30, 30] } else { [30, 30, 200] },
        );
        let depth = Plane::filled(40, 30, 0.5f32);
        let all = Plane::filled(40, 30, true);
        let none = Plane::filled(40, 30, false);
        let s = segment(&img, &depth, &all, &none, &SegmentSettings::default());
        assert_eq!(s.sizes.len(), 2);
        assert_ne!(s.labels.at(5, 5), s.labels.at(35, 5));
        assert_eq!(s.labels.at(5, 5), s.labels.at(19, 29));
    }

    #[test]
    fn depth_jumps_and_the_barrier_cut_a_uniform_image() {
        let img = image(40, 30, |_, _| [120, 120, 120]);
        let depth = Plane {
            width: 40,
            height: 30,
            data: (0..1200)
                .map(|i| if i % 40 < 10 { 0.3 } else { 0.8 })
                .collect(),
        };
        let all = Plane::filled(40, 30, true);
        let barrier = Plane {
            width: 40,
            height: 30,
            data: (0..1200).map(|i| i / 40 >= 20).collect(),
        };
        let s = segment(&img, &depth, &all, &barrier, &SegmentSettings::default());
        assert_eq!(s.sizes.len(), 4, "{:?}", s.sizes);
        let region = Plane {
            width: 40,
            height: 30,
            data: (0..1200).map(|i| i % 40 >= 30).collect(),
        };
        let s = segment(
            &img,
            &depth,
            &region,
            &Plane::filled(40, 30, false),
            &SegmentSettings::default(),
        );
        assert_eq!(s.sizes, vec![300]);
        assert_eq!(s.labels.at(0, 0), u32::MAX);
    }
}
