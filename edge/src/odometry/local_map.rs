//! The local feature maps (F-LOAM section III-D): hashed voxels cropped around the robot, searched
//! through a k-d tree rebuilt after each update.

use cloud::kdtree::{KdTree, Neighbour};
use cloud::voxel::VoxelKey;
use nalgebra::{Isometry3, Point3};
use rustc_hash::FxHashMap;

use super::MapConfig;

/// One feature map (edges or planes) in the odometry frame.
pub struct FeatureMap {
    config: MapConfig,
    voxels: FxHashMap<VoxelKey, Vec<Point3<f32>>>,
    points: Vec<Point3<f32>>,
    tree: KdTree,
}

impl FeatureMap {
    /// An empty map.
    pub fn new(config: MapConfig) -> Self {
        FeatureMap { config, voxels: FxHashMap::default(), points: Vec::new(), tree: KdTree::new(&[]) }
    }

    /// Number of points in the map.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True when the map holds no point.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Adds points (sensor frame at the sweep end) placed by `pose`; a voxel keeps at most
    /// `points_per_voxel` points, so revisited places do not grow the map.
    pub fn insert(&mut self, points: impl IntoIterator<Item = Point3<f32>>, pose: &Isometry3<f64>) {
        let pose = pose.cast::<f32>();
        let inv = 1.0 / self.config.voxel_size;
        let min_d2 = self.config.min_point_distance * self.config.min_point_distance;
        for p in points {
            let w = pose * p;
            let voxel = self.voxels.entry(VoxelKey::of(&w, inv)).or_default();
            // Spread the points of a voxel out: a near-duplicate adds cost but no information.
            if voxel.len() < self.config.points_per_voxel && voxel.iter().all(|q| (q - w).norm_squared() >= min_d2) {
                voxel.push(w);
            }
        }
    }

    /// Drops voxels farther than the map radius from `centre`, then rebuilds the search tree.
    pub fn crop_and_rebuild(&mut self, centre: &Point3<f64>) {
        let c = centre.cast::<f32>();
        let r2 = self.config.radius * self.config.radius;
        let size = self.config.voxel_size;
        self.voxels.retain(|k, _| {
            let mid =
                Point3::new((k.0[0] as f32 + 0.5) * size, (k.0[1] as f32 + 0.5) * size, (k.0[2] as f32 + 0.5) * size);
            (mid - c).norm_squared() <= r2
        });
        self.points.clear();
        self.points.extend(self.voxels.values().flatten());
        self.tree = KdTree::from_points(&self.points);
    }

    /// The `k` nearest map points to `q`, closest first.
    pub fn knn(&self, q: &Point3<f32>, k: usize) -> Vec<Neighbour> {
        self.tree.knn(&[q.x, q.y, q.z], k)
    }

    /// The map point with the given index (from a search result).
    pub fn point(&self, index: usize) -> Point3<f32> {
        self.points[index]
    }

    /// All map points (for inspection and tests).
    pub fn points(&self) -> &[Point3<f32>] {
        &self.points
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn voxels_cap_points_and_crop_by_distance() {
        let config = MapConfig { voxel_size: 1.0, points_per_voxel: 2, min_point_distance: 0.1, radius: 10.0 };
        let mut map = FeatureMap::new(config);
        let pts = [
            Point3::new(0.1, 0.1, 0.1),
            Point3::new(0.15, 0.1, 0.1),
            Point3::new(0.5, 0.5, 0.5),
            Point3::new(0.9, 0.9, 0.9),
            Point3::new(20.0, 0.0, 0.0),
        ];
        map.insert(pts, &Isometry3::identity());
        map.crop_and_rebuild(&Point3::origin());
        // (0.15,..) is too close to the first; (0.9,..) exceeds the cap of two; (20,..) is cropped.
        let mut got: Vec<_> = map.points().to_vec();
        got.sort_by(|a, b| a.x.total_cmp(&b.x));
        assert_eq!(got, vec![Point3::new(0.1, 0.1, 0.1), Point3::new(0.5, 0.5, 0.5)]);
        assert_eq!(
            map.knn(&Point3::new(0.45, 0.5, 0.5), 1)[0].index,
            map.points().iter().position(|p| p.x == 0.5).unwrap()
        );
    }

    #[test]
    fn insertion_applies_the_pose() {
        let mut map =
            FeatureMap::new(MapConfig { voxel_size: 0.5, points_per_voxel: 5, min_point_distance: 0.0, radius: 100.0 });
        map.insert([Point3::new(1.0, 0.0, 0.0)], &Isometry3::translation(0.0, 2.0, 0.0));
        map.crop_and_rebuild(&Point3::origin());
        assert_eq!(map.points(), &[Point3::new(1.0, 2.0, 0.0)]);
    }
}
