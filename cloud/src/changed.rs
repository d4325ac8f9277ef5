//! Where a point set changed between two revisions: what lets a step that looks only at each
//! point's neighbourhood (covariances, normals, descriptors) redo only the points near a change.
//!
//! A robot's map grows a keyframe at a time: most of its points are where they were, and a point
//! whose neighbourhood holds none of the new, moved or removed points gets the same result as
//! before. Points are matched by their exact coordinates, so the comparison needs no promise about
//! how the map was built: any change, anywhere, shows as the points around it.

use nalgebra::Point3;
use rayon::prelude::*;
use rustc_hash::FxHashMap;

use crate::kdtree::KdTree;

/// The points of the newer revision, each with its twin in the older one (the same coordinates)
/// and its distance to the nearest change.
pub struct ChangedPoints {
    /// Per newer point, the index of the older point at the same coordinates, if any.
    twins: Vec<Option<u32>>,
    /// Per newer point, the distance to the nearest point that was added, moved or removed
    /// (infinite when nothing changed); 0 for a point that is itself new.
    distance: Vec<f32>,
    /// Points added, moved or removed.
    changes: usize,
}

impl ChangedPoints {
    /// Compares `newer` with `older`.
    pub fn between(older: &[Point3<f32>], newer: &[Point3<f32>]) -> Self {
        let key = |p: &Point3<f32>| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
        let mut index: FxHashMap<[u32; 3], u32> = FxHashMap::default();
        index.reserve(older.len());
        for (i, p) in older.iter().enumerate() {
            // A duplicate keeps the first: the second, unmatched, counts as removed (a change
            // at a point that still exists only makes its neighbourhood be redone).
            index.entry(key(p)).or_insert(i as u32);
        }
        let mut matched = vec![false; older.len()];
        let twins: Vec<Option<u32>> = newer
            .iter()
            .map(|p| index.get(&key(p)).copied().filter(|&i| !std::mem::replace(&mut matched[i as usize], true)))
            .collect();
        let added = newer.iter().zip(&twins).filter(|(_, t)| t.is_none()).map(|(p, _)| *p);
        let removed = older.iter().zip(&matched).filter(|(_, m)| !**m).map(|(p, _)| *p);
        let changed: Vec<Point3<f32>> = added.chain(removed).collect();
        let tree = KdTree::from_points(&changed);
        let distance = newer
            .par_iter()
            .zip(&twins)
            .map(|(p, twin)| match twin {
                None => 0.0,
                Some(_) => tree.nearest(&[p.x, p.y, p.z]).map_or(f32::INFINITY, |n| n.dist_sq.sqrt()),
            })
            .collect();
        Self { twins, distance, changes: changed.len() }
    }

    /// The older point at the coordinates of newer point `i`, if one was there.
    pub fn twin(&self, i: usize) -> Option<usize> {
        self.twins[i].map(|t| t as usize)
    }

    /// The older twin of newer point `i` when no change lies within `radius` of it (inclusive):
    /// what it computed over a neighbourhood of that radius holds as it was.
    pub fn unchanged_within(&self, i: usize, radius: f32) -> Option<usize> {
        self.twin(i).filter(|_| self.distance[i] > radius)
    }

    /// Distance from newer point `i` to the nearest change, metres (0 for a new point).
    pub fn distance(&self, i: usize) -> f32 {
        self.distance[i]
    }

    /// Points added, moved (counted twice: gone from one place, new at another) or removed.
    pub fn changes(&self) -> usize {
        self.changes
    }

    /// Points of the newer revision.
    pub fn len(&self) -> usize {
        self.twins.len()
    }

    /// True when the newer revision has no point.
    pub fn is_empty(&self) -> bool {
        self.twins.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(x: f32, y: f32, z: f32) -> Point3<f32> {
        Point3::new(x, y, z)
    }

    #[test]
    fn twins_and_distances_to_the_nearest_change() {
        let older = vec![p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0), p(2.0, 0.0, 0.0), p(10.0, 0.0, 0.0)];
        // Point 1 moved a little, point 3 removed, one point added at x = 5; order shuffled.
        let newer = vec![p(2.0, 0.0, 0.0), p(0.0, 0.0, 0.0), p(1.0, 0.1, 0.0), p(5.0, 0.0, 0.0)];
        let c = ChangedPoints::between(&older, &newer);
        assert_eq!((0..4).map(|i| c.twin(i)).collect::<Vec<_>>(), vec![Some(2), Some(0), None, None]);
        assert_eq!(c.changes(), 4);
        // Nearest changes: the old place of point 1 (x = 1) and its new place.
        assert!((c.distance(0) - 1.0).abs() < 1e-6);
        assert!((c.distance(1) - 1.0).abs() < 1e-6);
        assert_eq!((c.distance(2), c.distance(3)), (0.0, 0.0));
        assert_eq!(c.unchanged_within(0, 0.99), Some(2));
        assert_eq!(c.unchanged_within(0, 1.0), None, "a change at exactly the radius counts");
        assert_eq!(c.unchanged_within(2, 0.0), None);
    }

    #[test]
    fn nothing_changed_is_infinitely_far_and_a_duplicate_is_matched_once() {
        let same = vec![p(0.0, 0.0, 0.0), p(1.0, 2.0, 3.0)];
        let c = ChangedPoints::between(&same, &same);
        assert_eq!(c.changes(), 0);
        assert!(c.distance(0).is_infinite() && c.distance(1).is_infinite());
        let doubled = vec![p(0.0, 0.0, 0.0), p(0.0, 0.0, 0.0)];
        let c = ChangedPoints::between(&same[..1], &doubled);
        assert_eq!((c.twin(0), c.twin(1), c.changes()), (Some(0), None, 1));
        assert_eq!(c.unchanged_within(0, 0.5), None);
    }
}
