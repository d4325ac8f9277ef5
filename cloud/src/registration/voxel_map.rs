//! A hashed voxel map of Gaussians, the VGICP target (Koide et al., "Voxelized GICP", 2021).

use nalgebra::{Matrix3, Vector3};
use rustc_hash::FxHashMap;

use super::target::{GaussianCloud, Target};

/// Which voxels a point is matched against: its own, or also its face (7) or full (27) neighbours.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum VoxelSearch {
    /// Only the voxel containing the point (small_gicp's default, `DIRECT1`).
    #[default]
    Direct1,
    /// That voxel and its six face neighbours (`DIRECT7`).
    Direct7,
    /// That voxel and all 26 neighbours (`DIRECT27`).
    Direct27,
}

impl VoxelSearch {
    /// The key offsets searched.
    fn offsets(self) -> &'static [[i32; 3]] {
        const DIRECT7: [[i32; 3]; 7] = [[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]];
        static DIRECT27: [[i32; 3]; 27] = {
            let mut all = [[0; 3]; 27];
            let mut i = 0;
            while i < 27 {
                all[i] = [(i % 3) as i32 - 1, ((i / 3) % 3) as i32 - 1, (i / 9) as i32 - 1];
                i += 1;
            }
            all
        };
        match self {
            VoxelSearch::Direct1 => &DIRECT7[..1],
            VoxelSearch::Direct7 => &DIRECT7,
            VoxelSearch::Direct27 => &DIRECT27,
        }
    }
}

/// One voxel: the mean of its points and the mean of their covariances.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GaussianVoxel {
    /// Mean of the points that fell in the voxel.
    pub mean: Vector3<f64>,
    /// Mean of their regularised covariances (VGICP's distribution-to-multi-distribution model:
    /// the voxel stands for all its points' surface patches, not for the spread of their centres).
    pub covariance: Matrix3<f64>,
    /// Number of points merged.
    pub count: u32,
}

/// Gaussian voxels in a hash map keyed by integer voxel coordinates.
pub struct GaussianVoxelMap {
    resolution: f64,
    inv_resolution: f64,
    search: VoxelSearch,
    index: FxHashMap<Key, u32>,
    voxels: Vec<GaussianVoxel>,
}

impl GaussianVoxelMap {
    /// Merges the points and covariances of `cloud` into voxels of edge `resolution` (metres).
    pub fn new(cloud: &GaussianCloud, resolution: f64, search: VoxelSearch) -> Self {
        let gaussians = (0..cloud.len()).map(|i| (cloud.point(i), cloud.covariance_of(i)));
        Self::merge(gaussians, resolution, search)
    }

    /// Merges point Gaussians (equal-length slices) into voxels of edge `resolution` (metres).
    pub fn from_gaussians(
        points: &[Vector3<f64>],
        covariances: &[Matrix3<f64>],
        resolution: f64,
        search: VoxelSearch,
    ) -> Self {
        Self::merge(points.iter().copied().zip(covariances.iter().copied()), resolution, search)
    }

    /// Merges point Gaussians (mean, covariance) into voxels of edge `resolution` (metres).
    fn merge(
        gaussians: impl Iterator<Item = (Vector3<f64>, Matrix3<f64>)>,
        resolution: f64,
        search: VoxelSearch,
    ) -> Self {
        let inv_resolution = 1.0 / resolution;
        let mut index: FxHashMap<Key, u32> = FxHashMap::default();
        let mut voxels: Vec<GaussianVoxel> = Vec::new();
        for (p, c) in gaussians {
            let next = voxels.len() as u32;
            let slot = *index.entry(key_of(&p, inv_resolution)).or_insert(next);
            if slot == next {
                voxels.push(GaussianVoxel { mean: Vector3::zeros(), covariance: Matrix3::zeros(), count: 0 });
            }
            let v = &mut voxels[slot as usize];
            v.mean += p;
            v.covariance += c;
            v.count += 1;
        }
        for v in &mut voxels {
            let n = f64::from(v.count);
            v.mean /= n;
            v.covariance /= n;
        }
        GaussianVoxelMap { resolution, inv_resolution, search, index, voxels }
    }

    /// Voxel edge length, metres.
    pub fn resolution(&self) -> f64 {
        self.resolution
    }

    /// Number of occupied voxels.
    pub fn len(&self) -> usize {
        self.voxels.len()
    }

    /// True when no voxel is occupied.
    pub fn is_empty(&self) -> bool {
        self.voxels.is_empty()
    }

    /// All voxels, in the order of their first point.
    pub fn voxels(&self) -> &[GaussianVoxel] {
        &self.voxels
    }

    /// The voxel containing `p`, if occupied.
    pub fn lookup(&self, p: &Vector3<f64>) -> Option<&GaussianVoxel> {
        self.index.get(&key_of(p, self.inv_resolution)).map(|&i| &self.voxels[i as usize])
    }
}

impl Target for GaussianVoxelMap {
    fn nearest(&self, p: &Vector3<f64>, max_dist_sq: f64) -> Option<u32> {
        let Key([x, y, z]) = key_of(p, self.inv_resolution);
        let mut best: Option<(u32, f64)> = None;
        for [dx, dy, dz] in self.search.offsets() {
            let Some(&i) = self.index.get(&Key([x + dx, y + dy, z + dz])) else { continue };
            let d = (self.voxels[i as usize].mean - p).norm_squared();
            if d <= max_dist_sq && best.is_none_or(|(_, b)| d < b) {
                best = Some((i, d));
            }
        }
        best.map(|(i, _)| i)
    }

    fn mean(&self, i: u32) -> Vector3<f64> {
        self.voxels[i as usize].mean
    }

    fn covariance(&self, i: u32) -> Matrix3<f64> {
        self.voxels[i as usize].covariance
    }
}

/// The voxel of `p`; coordinates beyond the i32 range saturate (as in [`crate::voxel::VoxelKey::of`]).
fn key_of(p: &Vector3<f64>, inv_resolution: f64) -> Key {
    Key([floor(p.x * inv_resolution), floor(p.y * inv_resolution), floor(p.z * inv_resolution)])
}

/// `x.floor() as i32` without the libm call that `floor` compiles to on baseline x86-64.
#[inline(always)]
fn floor(x: f64) -> i32 {
    let i = x as i32;
    i - i32::from(x < f64::from(i))
}

/// A voxel's integer coordinates, hashed as one word: the derived hash of `[i32; 3]` feeds four
/// words (length included) through the hasher, and the lookup is VGICP's inner loop.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Key([i32; 3]);

impl std::hash::Hash for Key {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        let [x, y, z] = self.0.map(|v| u64::from(v as u32));
        // Collisions only cost a probe: equality still compares all three coordinates.
        state.write_u64((x << 42) ^ (y << 21) ^ z);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn voxels_hold_means_of_points_and_covariances() {
        let pts = [Vector3::new(0.1, 0.1, 0.1), Vector3::new(0.3, 0.5, 0.7), Vector3::new(-0.05, 0.2, 0.2)];
        let covs = [Matrix3::identity(), Matrix3::identity() * 3.0, Matrix3::identity()];
        let map = GaussianVoxelMap::from_gaussians(&pts, &covs, 1.0, VoxelSearch::Direct1);
        assert_eq!(map.len(), 2);
        let v = map.lookup(&Vector3::new(0.9, 0.9, 0.9)).unwrap();
        assert!((v.mean - Vector3::new(0.2, 0.3, 0.4)).norm() < 1e-12);
        assert_eq!(v.covariance, Matrix3::identity() * 2.0);
        assert_eq!(v.count, 2);
        assert!(map.lookup(&Vector3::new(1.5, 0.0, 0.0)).is_none());
        // Direct1 only sees the containing voxel; Direct7 also the nearer mean in the face neighbour at x = -1.
        let q = Vector3::new(0.02, 0.2, 0.2);
        assert_eq!(map.nearest(&q, 10.0), Some(0));
        let map7 = GaussianVoxelMap::from_gaussians(&pts, &covs, 1.0, VoxelSearch::Direct7);
        assert_eq!(map7.nearest(&q, 10.0), Some(1));
        assert_eq!(map7.nearest(&q, 0.001), None);
        assert_eq!(VoxelSearch::Direct27.offsets().len(), 27);
    }
}
