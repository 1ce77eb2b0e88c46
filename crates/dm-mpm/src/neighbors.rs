//! Nearest-neighbour queries over point clouds (kiddo k-d trees), kept in
//! one place so the rest of the crate does not depend on kiddo's API.

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use std::num::NonZeroUsize;

/// A k-d tree over 3D points, answering with point indices.
#[derive(Debug)]
pub struct PointIndex {
    /// `None` for an empty cloud (kiddo refuses to build one).
    tree: Option<ImmutableKdTree<f64, 3>>,
    len: usize,
}

impl PointIndex {
    pub fn new(points: &[[f64; 3]]) -> Self {
        let tree = if points.is_empty() {
            None
        } else {
            ImmutableKdTree::new_from_slice(points).ok()
        };
        Self {
            tree,
            len: points.len(),
        }
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Up to `k` nearest points as `(index, distance)`, nearest first; ties
    /// broken by index so results never depend on insertion details.
    pub fn nearest(&self, query: &[f64; 3], k: usize) -> Vec<(usize, f64)> {
        let (Some(k), Some(tree)) = (NonZeroUsize::new(k.min(self.len)), &self.tree) else {
            return Vec::new();
        };
        let mut found: Vec<(usize, f64)> = tree
            .query(query)
            .nearest_n::<SquaredEuclidean<f64>>(k)
            .execute()
            .into_iter()
            .map(|n| (n.item as usize, n.distance.sqrt()))
            .collect();
        found.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
        found
    }

    /// All points within `radius`, sorted by index.
    pub fn within(&self, query: &[f64; 3], radius: f64) -> Vec<(usize, f64)> {
        let Some(tree) = &self.tree else {
            return Vec::new();
        };
        let mut found: Vec<(usize, f64)> = tree
            .query(query)
            .within::<SquaredEuclidean<f64>>(radius * radius)
            .execute()
            .into_iter()
            .map(|n| (n.item as usize, n.distance.sqrt()))
            .collect();
        found.sort_by_key(|a| a.0);
        found
    }
}

/// Farthest-point sampling: `count` indices, starting from the point
/// nearest the centroid so the choice does not depend on input order
/// beyond ties (broken by lowest index).
pub fn farthest_point_sampling(points: &[[f64; 3]], count: usize) -> Vec<usize> {
    let n = points.len();
    let count = count.min(n);
    if count == 0 {
        return Vec::new();
    }
    let mut centroid = [0.0; 3];
    for p in points {
        for a in 0..3 {
            centroid[a] += p[a] / n as f64;
        }
    }
    let dist2 = |p: &[f64; 3], q: &[f64; 3]| {
        (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)
    };
    let first = argmax(points.iter().map(|p| -dist2(p, &centroid)));
    let mut chosen = vec![first];
    let mut nearest: Vec<f64> = points.iter().map(|p| dist2(p, &points[first])).collect();
    while chosen.len() < count {
        let next = argmax(nearest.iter().copied());
        chosen.push(next);
        for (d, p) in nearest.iter_mut().zip(points) {
            *d = d.min(dist2(p, &points[next]));
        }
    }
    chosen
}

fn argmax(values: impl Iterator<Item = f64>) -> usize {
    let mut best = (0usize, f64::NEG_INFINITY);
    for (i, v) in values.enumerate() {
        if v > best.1 {
            best = (i, v);
        }
    }
    best.0
}
