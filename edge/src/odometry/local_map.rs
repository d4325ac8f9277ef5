//! The local feature maps (F-LOAM section III-D): hashed voxels cropped around the robot, searched
//! through k-d trees.
//!
//! Rebuilding one tree over the whole map after every scan grows with the map (12 ms per VLP-16
//! scan once a warehouse is mapped). The map is searched instead through two trees: a large one
//! over everything up to the last full rebuild, rebuilt (and cropped) every
//! [`MapConfig::rebuild_every`] scans, and a small one over the points added since, rebuilt after
//! every scan. A query merges the two answers, so every point is searchable from the next scan on.
//!
//! Memory is a budget fixed at construction: the voxel table, the points, the large tree
//! ([`OrderedKdTree`], which orders the map's own points rather than copying them) and the scratch
//! space of the crop are allocated (and written once, so that the pages are resident) for
//! [`MapConfig::max_voxels`] voxels of [`MapConfig::points_per_voxel`] points. A run never grows
//! them; when the budget is full, new voxels wait until the next rebuild drops the voxels farthest
//! from the robot. Only the small tree of recent points follows the map's size (a quarter of it
//! at most).

use cloud::kdtree::{KdTree, Neighbour};
use cloud::ordered_tree::OrderedKdTree;
use cloud::voxel::VoxelKey;
use nalgebra::{Isometry3, Point3};
use rustc_hash::FxHashMap;

use super::MapConfig;

/// Most points a voxel can hold ([`MapConfig::points_per_voxel`] is at most this): the point
/// indices of a voxel live inline in its table entry, so no voxel allocates.
pub const MAX_POINTS_PER_VOXEL: usize = 4;

/// One feature map (edges or planes) in the odometry frame.
pub struct FeatureMap {
    config: MapConfig,
    voxels: FxHashMap<VoxelKey, VoxelPoints>,
    /// Points of the last full rebuild in the large tree's order, then the points added since
    /// (indices continue).
    points: Vec<Point3<f32>>,
    lines: Vec<ScanLine>,
    /// Scratch of the rebuild: each point's index after compaction, then in the tree's order.
    moved_to: Vec<u32>,
    /// Tree over `points[..base]`.
    tree: OrderedKdTree,
    base: usize,
    /// Tree over `points[base..]` (indices relative to `base`).
    recent: KdTree,
    scans_since_rebuild: usize,
}

/// The indices (into the map's points) of one voxel's points.
#[derive(Clone, Copy, Debug, Default)]
struct VoxelPoints {
    len: u32,
    index: [u32; MAX_POINTS_PER_VOXEL],
}

impl VoxelPoints {
    fn indices(&self) -> &[u32] {
        &self.index[..self.len as usize]
    }
}

/// Marks a point dropped by the crop in [`FeatureMap::moved_to`].
const DROPPED: u32 = u32::MAX;

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

/// A vector of `capacity` elements' storage, written once so that its pages are resident, and empty.
fn reserved<T: Clone>(capacity: usize, fill: T) -> Vec<T> {
    let mut v = vec![fill; capacity];
    v.clear();
    v
}

impl FeatureMap {
    /// An empty map with its whole budget allocated (`points_per_voxel` is clamped to
    /// [`MAX_POINTS_PER_VOXEL`]; [`super::Odometry::new`] rejects larger values).
    pub fn new(mut config: MapConfig) -> Self {
        config.points_per_voxel = config.points_per_voxel.min(MAX_POINTS_PER_VOXEL);
        let capacity = config.max_voxels * config.points_per_voxel;
        let mut voxels = FxHashMap::default();
        voxels.reserve(config.max_voxels);
        // Write every slot once: reserving allocates the table, filling makes its pages resident.
        for i in 0..config.max_voxels {
            voxels.insert(VoxelKey([i as i32, 0, 0]), VoxelPoints::default());
        }
        voxels.clear();
        FeatureMap {
            config,
            voxels,
            points: reserved(capacity, Point3::origin()),
            lines: reserved(capacity, ScanLine(0)),
            moved_to: reserved(capacity, DROPPED),
            tree: OrderedKdTree::with_capacity(capacity),
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

    /// Number of occupied voxels.
    pub fn voxel_count(&self) -> usize {
        self.voxels.len()
    }

    /// Adds points (sensor frame at the sweep end) placed by `pose`; a voxel keeps at most
    /// `points_per_voxel` points, so revisited places do not grow the map, and no voxel is added
    /// beyond `max_voxels`.
    pub fn insert(&mut self, points: impl IntoIterator<Item = (Point3<f32>, ScanLine)>, pose: &Isometry3<f64>) {
        let pose = pose.cast::<f32>();
        let inv = 1.0 / self.config.voxel_size;
        let min_d2 = self.config.min_point_distance * self.config.min_point_distance;
        for (p, line) in points {
            let w = pose * p;
            let key = VoxelKey::of(&w, inv);
            let full = self.voxels.len() >= self.config.max_voxels;
            let voxel = match self.voxels.get_mut(&key) {
                Some(v) => v,
                None if full => continue,
                None => self.voxels.entry(key).or_default(),
            };
            // Spread the points of a voxel out: a near-duplicate adds cost but no information.
            let spread = voxel.indices().iter().all(|&i| (self.points[i as usize] - w).norm_squared() >= min_d2);
            if (voxel.len as usize) < self.config.points_per_voxel && spread {
                voxel.index[voxel.len as usize] = self.points.len() as u32;
                voxel.len += 1;
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

    /// Crops the voxels around `centre` (and, with the budget nearly full, to the nearest 90 % of
    /// it), compacts the points in place and rebuilds the large tree over all of them.
    fn rebuild(&mut self, centre: &Point3<f64>) {
        let c = centre.cast::<f32>();
        let size = self.config.voxel_size;
        let distance_sq = |k: &VoxelKey| {
            let mid =
                Point3::new((k.0[0] as f32 + 0.5) * size, (k.0[1] as f32 + 0.5) * size, (k.0[2] as f32 + 0.5) * size);
            (mid - c).norm_squared()
        };
        let mut r2 = self.config.radius * self.config.radius;
        // Leave a tenth of the budget free for the voxels of the next scans.
        let keep = self.config.max_voxels - self.config.max_voxels / 10;
        if self.voxels.len() > keep {
            r2 = r2.min(nth_distance_sq(self.voxels.keys().map(distance_sq), keep - 1));
        }
        self.voxels.retain(|k, _| distance_sq(k) <= r2);
        self.compact();
        self.arrange_for_tree();
        self.base = self.points.len();
        self.recent = KdTree::new(&[]);
        self.scans_since_rebuild = 0;
    }

    /// Moves the points of the remaining voxels to the front, in their insertion order.
    fn compact(&mut self) {
        self.moved_to.clear();
        self.moved_to.resize(self.points.len(), DROPPED);
        for v in self.voxels.values() {
            for &i in v.indices() {
                self.moved_to[i as usize] = 0;
            }
        }
        let mut next = 0;
        for i in 0..self.points.len() {
            if self.moved_to[i] != DROPPED {
                self.points[next] = self.points[i];
                self.lines[next] = self.lines[i];
                self.moved_to[i] = next as u32;
                next += 1;
            }
        }
        self.points.truncate(next);
        self.lines.truncate(next);
        for v in self.voxels.values_mut() {
            for k in 0..v.len as usize {
                v.index[k] = self.moved_to[v.index[k] as usize];
            }
        }
    }

    /// Builds the large tree over all points and puts them (and their voxels' indices) in its order.
    fn arrange_for_tree(&mut self) {
        let order = self.tree.build(&self.points);
        let position = &mut self.moved_to;
        position.clear();
        position.resize(order.len(), 0);
        for (new, &old) in order.iter().enumerate() {
            position[old as usize] = new as u32;
        }
        for v in self.voxels.values_mut() {
            for k in 0..v.len as usize {
                v.index[k] = position[v.index[k] as usize];
            }
        }
        // Each swap puts one point where it belongs; `position` follows the point it displaced.
        for i in 0..position.len() {
            while position[i] as usize != i {
                let to = position[i] as usize;
                self.points.swap(i, to);
                self.lines.swap(i, to);
                position.swap(i, to);
            }
        }
    }

    /// The `k` nearest map points to `q` within `radius`, closest first.
    pub fn knn(&self, q: &Point3<f32>, k: usize, radius: f32) -> Vec<Neighbour> {
        let mut found = self.tree.knn_within(&self.points, q, k, radius);
        if !self.recent.is_empty() {
            let recent = self.recent.knn_within(&[q.x, q.y, q.z], k, radius);
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

/// The `n`-th smallest (0-based) of `values`, which holds more than `n`.
fn nth_distance_sq(values: impl Iterator<Item = f32>, n: usize) -> f32 {
    let mut all: Vec<f32> = values.collect();
    let (_, nth, _) = all.select_nth_unstable_by(n, f32::total_cmp);
    *nth
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn voxels_cap_points_and_crop_by_distance() {
        let config = MapConfig {
            voxel_size: 1.0,
            points_per_voxel: 2,
            min_point_distance: 0.1,
            radius: 10.0,
            rebuild_every: 1,
            max_voxels: 100,
        };
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
    fn a_full_budget_refuses_new_voxels_until_the_farthest_are_dropped() {
        let config = MapConfig {
            voxel_size: 1.0,
            points_per_voxel: 2,
            min_point_distance: 0.0,
            radius: 1000.0,
            rebuild_every: 1,
            max_voxels: 20,
        };
        let mut map = FeatureMap::new(config);
        // 30 voxels along x, two points each: only the first 20 voxels get in.
        let row = |from: usize, to: usize| {
            (from..to).flat_map(|i| [0.25, 0.75].map(|dy| (Point3::new(i as f32 + 0.5, dy, 0.5), ScanLine::new(i, 0))))
        };
        map.insert(row(0, 30), &Isometry3::identity());
        assert_eq!((map.voxel_count(), map.len()), (20, 40));
        // From x = 30 the rebuild keeps the nearest 18 voxels (90 %): x in [2, 20).
        map.crop_and_rebuild(&Point3::new(30.0, 0.0, 0.0));
        assert_eq!((map.voxel_count(), map.len()), (18, 36));
        assert!(map.points().iter().all(|p| p.x > 2.0 && p.x < 20.0));
        // Room for two more voxels; their points are searchable, and indices still match points.
        map.insert(row(20, 30), &Isometry3::identity());
        map.crop_and_rebuild(&Point3::new(30.0, 0.0, 0.0));
        assert_eq!(map.voxel_count(), 18);
        assert!(map.points().iter().any(|p| p.x > 20.0));
        let q = Point3::new(20.5, 0.75, 0.5);
        let nearest = map.knn(&q, 1, 0.1);
        assert_eq!(map.point(nearest[0].index), q);
        // After compaction and the tree's reordering, every voxel still names its own points.
        for (key, v) in &map.voxels {
            assert!(v.indices().iter().all(|&i| VoxelKey::of(&map.point(i as usize), 1.0) == *key));
        }
        let named: usize = map.voxels.values().map(|v| v.len as usize).sum();
        assert_eq!(named, map.len());
    }

    #[test]
    fn insertion_applies_the_pose() {
        let mut map = FeatureMap::new(MapConfig {
            voxel_size: 0.5,
            points_per_voxel: 5,
            min_point_distance: 0.0,
            radius: 100.0,
            rebuild_every: 1,
            max_voxels: 100,
        });
        map.insert([(Point3::new(1.0, 0.0, 0.0), ScanLine::new(0, 0))], &Isometry3::translation(0.0, 2.0, 0.0));
        map.crop_and_rebuild(&Point3::origin());
        assert_eq!(map.points(), &[Point3::new(1.0, 2.0, 0.0)]);
    }
}
