//! Nearest-neighbour search in 3-D over a k-d tree (kiddo), with the query
//! kinds Open3D's registration uses: nearest, k nearest, radius, and hybrid
//! (at most k within a radius).

use std::num::NonZero;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::Point3;

/// A k-d tree over a set of points; results are (index, squared distance),
/// nearest first.
pub struct Neighbors {
    tree: Option<ImmutableKdTree<f64, 3>>,
}

impl Neighbors {
    pub fn new(points: &[Point3<f64>]) -> Neighbors {
        if points.is_empty() {
            return Neighbors { tree: None };
        }
        let coords: Vec<[f64; 3]> = points.iter().map(|p| [p.x, p.y, p.z]).collect();
        Neighbors {
            tree: ImmutableKdTree::new_from_slice(&coords).ok(),
        }
    }

    /// The nearest point, if any.
    pub fn nearest(&self, p: &Point3<f64>) -> Option<(usize, f64)> {
        let tree = self.tree.as_ref()?;
        let r = tree
            .query(&[p.x, p.y, p.z])
            .nearest_one::<SquaredEuclidean<f64>>()
            .execute();
        Some((r.item as usize, r.distance))
    }

    /// The nearest point within `radius` (not squared).
    pub fn nearest_within(&self, p: &Point3<f64>, radius: f64) -> Option<(usize, f64)> {
        self.nearest(p).filter(|&(_, d2)| d2 <= radius * radius)
    }

    /// The `k` nearest points.
    pub fn knn(&self, p: &Point3<f64>, k: usize) -> Vec<(usize, f64)> {
        let (Some(tree), Some(k)) = (self.tree.as_ref(), NonZero::new(k)) else {
            return Vec::new();
        };
        tree.query(&[p.x, p.y, p.z])
            .nearest_n::<SquaredEuclidean<f64>>(k)
            .execute()
            .into_iter()
            .map(|r| (r.item as usize, r.distance))
            .collect()
    }

    /// At most `max_nn` nearest points within `radius` (Open3D's hybrid search).
    pub fn hybrid(&self, p: &Point3<f64>, radius: f64, max_nn: usize) -> Vec<(usize, f64)> {
        let (Some(tree), Some(k)) = (self.tree.as_ref(), NonZero::new(max_nn)) else {
            return Vec::new();
        };
        tree.query(&[p.x, p.y, p.z])
            .nearest_n::<SquaredEuclidean<f64>>(k)
            .within(radius * radius)
            .execute()
            .into_iter()
            .map(|r| (r.item as usize, r.distance))
            .collect()
    }

    /// All points within `radius`.
    pub fn within(&self, p: &Point3<f64>, radius: f64) -> Vec<(usize, f64)> {
        let Some(tree) = self.tree.as_ref() else {
            return Vec::new();
        };
        tree.query(&[p.x, p.y, p.z])
            .within::<SquaredEuclidean<f64>>(radius * radius)
            .execute()
            .into_iter()
            .map(|r| (r.item as usize, r.distance))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn queries_agree_with_brute_force() {
        let pts: Vec<Point3<f64>> = (0..500)
            .map(|i| {
                let f = i as f64;
                Point3::new((f * 0.37).sin(), (f * 0.91).cos(), (f * 0.13).sin() * 0.5)
            })
            .collect();
        let nn = Neighbors::new(&pts);
        let q = Point3::new(0.1, -0.2, 0.05);
        let mut brute: Vec<(usize, f64)> = pts
            .iter()
            .enumerate()
            .map(|(i, p)| (i, (p - q).norm_squared()))
            .collect();
        brute.sort_by(|a, b| a.1.total_cmp(&b.1));
        assert_eq!(nn.nearest(&q).unwrap().0, brute[0].0);
        let k: Vec<usize> = nn.knn(&q, 7).iter().map(|r| r.0).collect();
        assert_eq!(k, brute.iter().take(7).map(|r| r.0).collect::<Vec<_>>());
        let r = 0.3;
        assert_eq!(
            nn.within(&q, r).len(),
            brute.iter().filter(|b| b.1 <= r * r).count()
        );
        assert!(nn.hybrid(&q, r, 3).len() <= 3);
        assert!(Neighbors::new(&[]).nearest(&q).is_none());
    }
}
