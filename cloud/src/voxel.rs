//! Voxel grids: integer cell keys and centroid-per-voxel downsampling.

use nalgebra::Point3;
use rustc_hash::FxHashMap;

use crate::PointCloud;
use crate::memory::{HeapSize, map_bytes, vec_bytes};

/// Integer coordinates of a cubic cell: `floor(p / size)` per axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct VoxelKey(pub [i32; 3]);

impl VoxelKey {
    /// The cell holding `p` in a grid of cells `inv_size` = 1 / edge length.
    ///
    /// Coordinates beyond the i32 range of cells saturate: such points are far outside any map and
    /// share the border cell rather than wrapping onto the other side.
    pub fn of(p: &Point3<f32>, inv_size: f32) -> Self {
        VoxelKey([(p.x * inv_size).floor() as i32, (p.y * inv_size).floor() as i32, (p.z * inv_size).floor() as i32])
    }
}

/// A voxel edge length that is not a positive finite number.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("voxel size must be positive and finite, got {0}")]
pub struct InvalidVoxelSize(pub f32);

/// Numbers the cells of a grid in the order points first fall in them (0, 1, 2, ...): what makes
/// the output of a voxel grid deterministic for a given input.
///
/// Cells are found through blocks of [`BLOCK_EDGE`]³ neighbouring cells: one hash lookup per block
/// (none while points stay in the last block), then a dense table. A hash lookup per point missed
/// the cache at almost every point of a map of a few hundred thousand voxels (a station merge
/// spent most of its time there); points of one scan come in sweep order, and neighbours in a
/// sweep mostly share a block.
#[derive(Clone, Debug, Default)]
pub struct CellIndex {
    /// Block coordinates (cell coordinates shifted by [`BLOCK_BITS`]) to an index into `tables`.
    blocks: FxHashMap<[i32; 3], u32>,
    /// Per block, each cell's number, or [`EMPTY`].
    tables: Vec<[u32; BLOCK_CELLS]>,
    /// Cells numbered so far.
    len: u32,
    /// The block of the last lookup.
    last: Option<([i32; 3], u32)>,
}

/// log2 of a block's edge in cells.
const BLOCK_BITS: u32 = 2;
/// A block's edge in cells.
const BLOCK_EDGE: i32 = 1 << BLOCK_BITS;
const BLOCK_CELLS: usize = 1 << (3 * BLOCK_BITS);
/// An unoccupied cell of a block's table.
const EMPTY: u32 = u32::MAX;

impl HeapSize for CellIndex {
    fn heap_bytes(&self) -> usize {
        map_bytes::<[i32; 3], u32>(self.blocks.capacity()) + vec_bytes(&self.tables)
    }
}

impl CellIndex {
    /// The number of `key`'s cell, and whether the cell is new (then its number is the count of
    /// cells before it).
    pub fn number(&mut self, VoxelKey(key): VoxelKey) -> (u32, bool) {
        // Arithmetic shifts floor negative coordinates too: cell -1 is in block -1.
        let block = key.map(|c| c >> BLOCK_BITS);
        let table = match self.last {
            Some((b, t)) if b == block => t,
            _ => {
                let fresh = self.tables.len() as u32;
                let t = *self.blocks.entry(block).or_insert(fresh);
                if t == fresh {
                    self.tables.push([EMPTY; BLOCK_CELLS]);
                }
                self.last = Some((block, t));
                t
            }
        };
        let [x, y, z] = key.map(|c| (c & (BLOCK_EDGE - 1)) as usize);
        let slot = &mut self.tables[table as usize][x | y << BLOCK_BITS | z << (2 * BLOCK_BITS)];
        if *slot != EMPTY {
            return (*slot, false);
        }
        // Cell numbers fit u32: a grid of 4 billion cells would not fit in memory.
        *slot = self.len;
        self.len += 1;
        (*slot, true)
    }

    /// Forgets every cell (keeping the memory of the block list).
    pub fn clear(&mut self) {
        self.blocks.clear();
        self.tables.clear();
        self.len = 0;
        self.last = None;
    }
}

/// Cells of a grid with a value each, in the order of [`CellIndex`].
#[derive(Clone, Debug, Default)]
struct Cells<T> {
    index: CellIndex,
    cells: Vec<T>,
}

impl<T> HeapSize for Cells<T> {
    fn heap_bytes(&self) -> usize {
        self.index.heap_bytes() + vec_bytes(&self.cells)
    }
}

impl<T: Default> Cells<T> {
    /// The cell of `key`, created empty if it is new.
    fn at(&mut self, key: VoxelKey) -> &mut T {
        let (n, new) = self.index.number(key);
        if new {
            self.cells.push(T::default());
        }
        &mut self.cells[n as usize]
    }
}

/// Running sum of one voxel's positions.
#[derive(Clone, Copy, Debug, Default)]
struct PositionSum {
    /// f64 sums: thousands of f32 points at 100 m would lose millimetres in f32.
    sum: [f64; 3],
    count: u32,
}

impl PositionSum {
    fn add(&mut self, p: &Point3<f32>) {
        self.sum[0] += f64::from(p.x);
        self.sum[1] += f64::from(p.y);
        self.sum[2] += f64::from(p.z);
        self.count += 1;
    }

    fn mean(&self) -> Point3<f32> {
        let n = f64::from(self.count);
        Point3::new((self.sum[0] / n) as f32, (self.sum[1] / n) as f32, (self.sum[2] / n) as f32)
    }
}

/// Running sums of one voxel's points.
#[derive(Clone, Copy, Default)]
struct Centroid {
    position: PositionSum,
    intensity: f64,
    time: f64,
    ring: u16,
}

impl Centroid {
    fn add(&mut self, cloud: &PointCloud, i: usize) {
        if self.position.count == 0 {
            self.ring = cloud.ring.as_ref().map_or(0, |v| v[i]);
        }
        self.position.add(&cloud.points[i]);
        self.intensity += cloud.intensity.as_ref().map_or(0.0, |v| f64::from(v[i]));
        self.time += cloud.time.as_ref().map_or(0.0, |v| f64::from(v[i]));
    }
}

/// Replaces the points in each cubic voxel of edge `size` by their centroid.
///
/// Intensity and time are averaged per voxel; a voxel keeps the ring of its first point (a mean ring
/// index means nothing). Voxels come out in the order of their first point, so the result is
/// deterministic for a given input.
pub fn downsample(cloud: &PointCloud, size: f32) -> Result<PointCloud, InvalidVoxelSize> {
    if !(size > 0.0 && size.is_finite()) {
        return Err(InvalidVoxelSize(size));
    }
    let inv = 1.0 / size;
    let mut voxels: Cells<Centroid> = Cells::default();
    for (i, p) in cloud.points.iter().enumerate() {
        voxels.at(VoxelKey::of(p, inv)).add(cloud, i);
    }
    let mut out = PointCloud::with_capacity(voxels.cells.len(), cloud.channels());
    for v in &voxels.cells {
        let n = f64::from(v.position.count);
        out.points.push(v.position.mean());
        if let Some(c) = &mut out.intensity {
            c.push((v.intensity / n) as f32);
        }
        if let Some(c) = &mut out.time {
            c.push((v.time / n) as f32);
        }
        if let Some(c) = &mut out.ring {
            c.push(v.ring);
        }
    }
    Ok(out)
}

/// A centroid-per-voxel grid that grows point by point: what [`downsample`] gives for the union of
/// everything inserted (positions only; same voxels, same order, the same centroids up to the
/// rounding of the running sums), without keeping or revisiting the inserted points.
///
/// A map that grows by a keyframe at a time costs the new keyframe's points, not the whole map.
#[derive(Clone, Debug)]
pub struct VoxelMap {
    inv_size: f32,
    voxels: Cells<PositionSum>,
}

impl HeapSize for VoxelMap {
    fn heap_bytes(&self) -> usize {
        self.voxels.heap_bytes()
    }
}

impl VoxelMap {
    /// An empty grid of cubic voxels of edge `size`.
    pub fn new(size: f32) -> Result<Self, InvalidVoxelSize> {
        if !(size > 0.0 && size.is_finite()) {
            return Err(InvalidVoxelSize(size));
        }
        Ok(Self { inv_size: 1.0 / size, voxels: Cells::default() })
    }

    /// Adds `points`; non-finite points are skipped (they have no cell).
    pub fn insert(&mut self, points: impl IntoIterator<Item = Point3<f32>>) {
        for p in points.into_iter().filter(|p| p.coords.iter().all(|c| c.is_finite())) {
            self.voxels.at(VoxelKey::of(&p, self.inv_size)).add(&p);
        }
    }

    /// Occupied voxels.
    pub fn len(&self) -> usize {
        self.voxels.cells.len()
    }

    /// True when nothing was inserted.
    pub fn is_empty(&self) -> bool {
        self.voxels.cells.is_empty()
    }

    /// One point per occupied voxel, its centroid, in the order the voxels were first hit.
    pub fn cloud(&self) -> PointCloud {
        PointCloud::from_points(self.voxels.cells.iter().map(PositionSum::mean).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Channels;

    #[test]
    fn centroid_per_voxel_with_channels() {
        let mut c = PointCloud::with_capacity(4, Channels { intensity: true, ring: true, time: true });
        c.points = vec![
            Point3::new(0.1, 0.1, 0.1),
            Point3::new(0.3, 0.5, 0.9),
            Point3::new(-0.1, 0.2, 0.2), // negative x: a different cell (floor, not truncation)
            Point3::new(5.5, 5.5, 5.5),
        ];
        c.intensity = Some(vec![1.0, 3.0, 7.0, 9.0]);
        c.ring = Some(vec![4, 5, 6, 7]);
        c.time = Some(vec![0.0, 0.1, 0.2, 0.3]);
        let d = downsample(&c, 1.0).unwrap();
        assert_eq!(d.len(), 3);
        assert!((d.points[0] - Point3::new(0.2, 0.3, 0.5)).norm() < 1e-6);
        assert_eq!(d.points[1], Point3::new(-0.1, 0.2, 0.2));
        assert_eq!(d.intensity.as_ref().unwrap(), &vec![2.0, 7.0, 9.0]);
        assert_eq!(d.ring.as_ref().unwrap(), &vec![4, 6, 7]);
        assert!((d.time.as_ref().unwrap()[0] - 0.05).abs() < 1e-7);
    }

    #[test]
    fn every_output_point_is_alone_in_its_voxel_and_counts_add_up() {
        // A seeded lattice-with-jitter cloud: centroids stay inside their voxel, one per occupied voxel.
        let mut rng = testkit::Rng::new(0x9e3779b97f4a7c15);
        let mut rand = move || rng.f32();
        let pts: Vec<_> =
            (0..20_000).map(|_| Point3::new(rand() * 40.0 - 20.0, rand() * 40.0 - 20.0, rand() * 4.0)).collect();
        let c = PointCloud::from_points(pts.clone());
        let size = 0.5;
        let d = downsample(&c, size).unwrap();
        let mut occupied: Vec<VoxelKey> = pts.iter().map(|p| VoxelKey::of(p, 1.0 / size)).collect();
        occupied.sort();
        occupied.dedup();
        assert_eq!(d.len(), occupied.len());
        let mut out: Vec<VoxelKey> = d.points.iter().map(|p| VoxelKey::of(p, 1.0 / size)).collect();
        out.sort();
        assert_eq!(out, occupied);
    }

    #[test]
    fn rejects_bad_sizes() {
        let c = PointCloud::default();
        for s in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            assert!(downsample(&c, s).is_err());
        }
        assert!(downsample(&c, 0.1).unwrap().is_empty());
    }

    /// The grid as defined: a hash map from cell to the cell's place in first-hit order.
    fn reference_centroids(points: &[Point3<f32>], size: f32) -> Vec<Point3<f32>> {
        let mut slot: std::collections::HashMap<VoxelKey, usize> = std::collections::HashMap::new();
        let mut sums: Vec<PositionSum> = Vec::new();
        for p in points {
            let next = sums.len();
            let s = *slot.entry(VoxelKey::of(p, 1.0 / size)).or_insert(next);
            if s == next {
                sums.push(PositionSum::default());
            }
            sums[s].add(p);
        }
        sums.iter().map(PositionSum::mean).collect()
    }

    #[test]
    fn blocks_of_cells_give_the_cells_a_hash_map_gives_in_the_same_order() {
        // Across the origin (negative cells floor into negative blocks), block borders, far
        // coordinates and saturated cells, in sweep order and shuffled.
        let mut rng = testkit::Rng::new(0x5eed);
        let mut sweep: Vec<Point3<f32>> = (0..20_000)
            .map(|i| {
                let a = i as f32 * 0.003;
                let r = 3.0 + 20.0 * rng.f32();
                Point3::new(r * a.cos(), r * a.sin(), rng.f32() * 4.0 - 2.0)
            })
            .collect();
        sweep.extend([Point3::new(1e12, -1e12, 0.0), Point3::new(-1e12, 1e12, 1e12), Point3::new(-0.0, 0.0, -1e-9)]);
        let mut shuffled = sweep.clone();
        for i in (1..shuffled.len()).rev() {
            shuffled.swap(i, rng.below(i + 1));
        }
        for points in [&sweep, &shuffled] {
            for size in [0.1, 0.25, 1.0] {
                let expected = reference_centroids(points, size);
                let cloud = PointCloud::from_points(points.clone());
                assert_eq!(downsample(&cloud, size).unwrap().points, expected, "downsample at {size}");
                let mut map = VoxelMap::new(size).unwrap();
                for part in points.chunks(777) {
                    map.insert(part.iter().copied());
                }
                assert_eq!(map.cloud().points, expected, "voxel map at {size}");
            }
        }
    }

    #[test]
    fn voxel_map_fed_in_parts_equals_downsampling_the_union() {
        let mut rng = testkit::Rng::new(17);
        let mut rand = move || rng.f32();
        let parts: Vec<Vec<Point3<f32>>> = (0..5)
            .map(|k| {
                (0..3000).map(|_| Point3::new(rand() * 20.0 + k as f32, rand() * 20.0 - 10.0, rand() * 3.0)).collect()
            })
            .collect();
        let mut map = VoxelMap::new(0.4).unwrap();
        for part in &parts {
            map.insert(part.iter().copied());
        }
        map.insert([Point3::new(f32::NAN, 0.0, 0.0)]);
        let union = PointCloud::from_points(parts.concat());
        let whole = downsample(&union, 0.4).unwrap();
        assert_eq!(map.len(), whole.len());
        let grown = map.cloud();
        for (a, b) in grown.points.iter().zip(&whole.points) {
            assert!((a - b).norm() < 1e-5, "{a} vs {b}");
        }
        assert!(VoxelMap::new(0.0).is_err());
    }
}
