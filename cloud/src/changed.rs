//! Where a point set changed between two revisions: what lets a step that looks only at each
//! point's neighbourhood (covariances, normals, descriptors) redo only the points near a change.
//!
//! A robot's map grows a keyframe at a time: most of its points are where they were, and a point
//! whose neighbourhood holds none of the new, moved or removed points gets the same result as
//! before. Points are matched by their exact coordinates, so the comparison needs no promise about
//! how the map was built: any change, anywhere, shows as the points around it.

use nalgebra::Point3;
use rustc_hash::FxHashMap;

use crate::kdtree::{KdTree, gate_radius};

/// The points of the newer revision, each with its twin in the older one (the same coordinates),
/// and where the points that changed are.
pub struct ChangedPoints {
    /// Per newer point, the index of the older point at the same coordinates, if any.
    twins: Vec<Option<u32>>,
    /// Points added, moved (at both places) or removed.
    changed: KdTree,
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
        Self { twins, changed: KdTree::from_points(&changed) }
    }

    /// The older point at the coordinates of newer point `i`, if one was there.
    pub fn twin(&self, i: usize) -> Option<usize> {
        self.twins[i].map(|t| t as usize)
    }

    /// The older twin of newer point `i` (at `at`) when no change lies within `radius_sq` (a
    /// squared distance, inclusive) of it: what it computed over that neighbourhood holds as it was.
    /// A bounded search: most points ask about a few decimetres.
    pub fn unchanged_within(&self, i: usize, at: &Point3<f32>, radius_sq: f32) -> Option<usize> {
        let twin = self.twin(i)?;
        let q = [at.x, at.y, at.z];
        let near = self.changed.nearest_within(&q, gate_radius(radius_sq.sqrt())).filter(|n| n.dist_sq <= radius_sq);
        near.is_none().then_some(twin)
    }

    /// Points added, moved (counted twice: gone from one place, new at another) or removed.
    pub fn changes(&self) -> usize {
        self.changed.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(x: f32, y: f32, z: f32) -> Point3<f32> {
        Point3::new(x, y, z)
    }

    #[test]
    fn twins_and_the_nearest_change() {
        let older = vec![p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0), p(2.0, 0.0, 0.0), p(10.0, 0.0, 0.0)];
        // Point 1 moved a little, point 3 removed, one point added at x = 5; order shuffled.
        let newer = vec![p(2.0, 0.0, 0.0), p(0.0, 0.0, 0.0), p(1.0, 0.1, 0.0), p(5.0, 0.0, 0.0)];
        let c = ChangedPoints::between(&older, &newer);
        assert_eq!((0..4).map(|i| c.twin(i)).collect::<Vec<_>>(), vec![Some(2), Some(0), None, None]);
        assert_eq!(c.changes(), 4);
        // The nearest changes to x = 2 and x = 0: the old place of point 1 (x = 1), 1 m away.
        assert_eq!(c.unchanged_within(0, &newer[0], 0.99), Some(2));
        assert_eq!(c.unchanged_within(0, &newer[0], 1.0), None, "a change at exactly the radius counts");
        assert_eq!(c.unchanged_within(1, &newer[1], 0.98), Some(0));
        assert_eq!(c.unchanged_within(2, &newer[2], 0.0), None, "a new point has no twin");
    }

    #[test]
    fn nothing_changed_is_unchanged_everywhere_and_a_duplicate_is_matched_once() {
        let same = vec![p(0.0, 0.0, 0.0), p(1.0, 2.0, 3.0)];
        let c = ChangedPoints::between(&same, &same);
        assert_eq!(c.changes(), 0);
        assert_eq!(c.unchanged_within(1, &same[1], f32::INFINITY), Some(1));
        let doubled = vec![p(0.0, 0.0, 0.0), p(0.0, 0.0, 0.0)];
        let c = ChangedPoints::between(&same[..1], &doubled);
        assert_eq!((c.twin(0), c.twin(1), c.changes()), (Some(0), None, 1));
        assert_eq!(c.unchanged_within(0, &doubled[0], 0.25), None);
    }
}
