//! The local feature maps (F-LOAM section III-D): hashed voxels cropped around the robot, searched
//! through k-d trees.
//!
//! Rebuilding one tree over the whole map after every scan grows with the map (12 ms per VLP-16
//! scan once a warehouse is mapped). The map is searched instead through two trees: a large one
//! over everything up to the last full rebuild, rebuilt (and cropped) every
//! [`MapConfig::rebuild_every`] scans, and a small one over the points added since, rebuilt after
//! every scan. A query merges the two answers, so every point is searchable from the next scan on.

use cloud::kdtree::{KdTree, Neighbour};
use cloud::voxel::VoxelKey;
use nalgebra::{Isometry3, Point3};
use rustc_hash::FxHashMap;

use super::MapConfig;

/// One feature map (edges or planes) in the odometry frame.
pub struct FeatureMap {
    config: MapConfig,
    voxels: FxHashMap<VoxelKey, Vec<(Point3<f32>, ScanLine)>>,
    /// Points of the last full rebuild, then the points added since (indices continue).
    points: Vec<Point3<f32>>,
    lines: Vec<ScanLine>,
    /// Tree over `points[..base]`.
    tree: KdTree,
    base: usize,
    /// Tree over `points[base..]` (indices relative to `base`).
    recent: KdTree,
    scans_since_rebuild: usize,
}

/// The scan line (one ring of one scan) a map point was measured on. Neighbourhoods drawn from a
/// single scan line are degenerate: a ring's trace around a box corner or along a pillar is flat
/// in the horizontal plane, whatever the surfaces it crosses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ScanLine(pub u64);

impl ScanLine {
    /// The line of `ring` in scan number `scan`.
    pub fn new(scan: usize, ring: u16) -> Self {
        ScanLine(((scan as u64) << 16) | u64::from(ring))
    }
}

impl FeatureMap {
    /// An empty map.
    pub fn new(config: MapConfig) -> Self {
        FeatureMap {
            config,
            voxels: FxHashMap::default(),
            points: Vec::new(),
            lines: Vec::new(),
            tree: KdTree::new(&[]),
            base: 0,
            recent: KdTree::new(&[]),
            scans_since_rebuild: 0,
        }
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
    pub fn insert(&mut self, points: impl IntoIterator<Item = (Point3<f32>, ScanLine)>, pose: &Isometry3<f64>) {
        let pose = pose.cast::<f32>();
        let inv = 1.0 / self.config.voxel_size;
        let min_d2 = self.config.min_point_distance * self.config.min_point_distance;
        for (p, line) in points {
            let w = pose * p;
            let voxel = self.voxels.entry(VoxelKey::of(&w, inv)).or_default();
            // Spread the points of a voxel out: a near-duplicate adds cost but no information.
            if voxel.len() < self.config.points_per_voxel && voxel.iter().all(|(q, _)| (q - w).norm_squared() >= min_d2)
            {
                voxel.push((w, line));
                self.points.push(w);
                self.lines.push(line);
            }
        }
    }

    /// Makes the points added so far searchable: every `rebuild_every` scans (or when the recent
    /// points outgrow a quarter of the map) voxels farther than the map radius from `centre` are
    /// dropped and the large tree is rebuilt; otherwise only the small tree of recent points.
    pub fn crop_and_rebuild(&mut self, centre: &Point3<f64>) {
        self.scans_since_rebuild += 1;
        let recent = self.points.len() - self.base;
        if self.scans_since_rebuild >= self.config.rebuild_every.max(1) || recent * 4 > self.base {
            self.rebuild(centre);
        } else {
            self.recent = KdTree::from_points(&self.points[self.base..]);
        }
    }

    /// Crops the voxels around `centre` and rebuilds the large tree over all of them.
    fn rebuild(&mut self, centre: &Point3<f64>) {
        let c = centre.cast::<f32>();
        let r2 = self.config.radius * self.config.radius;
        let size = self.config.voxel_size;
        self.voxels.retain(|k, _| {
            let mid =
                Point3::new((k.0[0] as f32 + 0.5) * size, (k.0[1] as f32 + 0.5) * size, (k.0[2] as f32 + 0.5) * size);
            (mid - c).norm_squared() <= r2
        });
        self.points.clear();
        self.lines.clear();
        for (p, line) in self.voxels.values().flatten() {
            self.points.push(*p);
            self.lines.push(*line);
        }
        self.tree = KdTree::from_points(&self.points);
        self.base = self.points.len();
        self.recent = KdTree::new(&[]);
        self.scans_since_rebuild = 0;
    }

    /// The `k` nearest map points to `q` within `radius`, closest first.
    pub fn knn(&self, q: &Point3<f32>, k: usize, radius: f32) -> Vec<Neighbour> {
        let q = [q.x, q.y, q.z];
        let mut found = self.tree.knn_within(&q, k, radius);
        if !self.recent.is_empty() {
            let recent = self.recent.knn_within(&q, k, radius);
            found.extend(recent.into_iter().map(|n| Neighbour { index: n.index + self.base, ..n }));
            found.sort_by(|a, b| a.dist_sq.total_cmp(&b.dist_sq));
            found.truncate(k);
        }
        found
    }

    /// The map point with the given index (from a search result).
    pub fn point(&self, index: usize) -> Point3<f32> {
        self.points[index]
    }

    /// The scan line of the map point with the given index.
    pub fn line(&self, index: usize) -> ScanLine {
        self.lines[index]
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
        let config =
            MapConfig { voxel_size: 1.0, points_per_voxel: 2, min_point_distance: 0.1, radius: 10.0, rebuild_every: 1 };
        let mut map = FeatureMap::new(config);
        let pts = [
            Point3::new(0.1, 0.1, 0.1),
            Point3::new(0.15, 0.1, 0.1),
            Point3::new(0.5, 0.5, 0.5),
            Point3::new(0.9, 0.9, 0.9),
            Point3::new(20.0, 0.0, 0.0),
        ];
        map.insert(pts.iter().enumerate().map(|(i, p)| (*p, ScanLine::new(i, 0))), &Isometry3::identity());
        map.crop_and_rebuild(&Point3::origin());
        // (0.15,..) is too close to the first; (0.9,..) exceeds the cap of two; (20,..) is cropped.
        let mut got: Vec<_> = map.points().to_vec();
        got.sort_by(|a, b| a.x.total_cmp(&b.x));
        assert_eq!(got, vec![Point3::new(0.1, 0.1, 0.1), Point3::new(0.5, 0.5, 0.5)]);
        assert_eq!(
            map.knn(&Point3::new(0.45, 0.5, 0.5), 1, 1.0)[0].index,
            map.points().iter().position(|p| p.x == 0.5).unwrap()
        );
    }

    #[test]
    fn insertion_applies_the_pose() {
        let mut map = FeatureMap::new(MapConfig {
            voxel_size: 0.5,
            points_per_voxel: 5,
            min_point_distance: 0.0,
            radius: 100.0,
            rebuild_every: 1,
        });
        map.insert([(Point3::new(1.0, 0.0, 0.0), ScanLine::new(0, 0))], &Isometry3::translation(0.0, 2.0, 0.0));
        map.crop_and_rebuild(&Point3::origin());
        assert_eq!(map.points(), &[Point3::new(1.0, 2.0, 0.0)]);
    }
}
