//! Scan Context (Kim & Kim, IROS 2018): a place descriptor of one scan, and the distance between two.
//!
//! The plane around the sensor is cut into `rings` annuli out to `max_range` and `sectors` equal
//! azimuth wedges; a cell holds the highest point that falls in it (eq. 1), an empty cell 0. A
//! revisit seen from another heading shifts the columns, so the distance (eq. 5) is the smallest
//! over column shifts of one minus the mean cosine similarity of the columns that both scans see
//! (eq. 4); the shift is the yaw between the two scans. Two cheaper keys find candidates first: the
//! ring key (eq. 7, a ring's mean, invariant to yaw) for the k-d tree, and the sector key (a
//! sector's mean) for aligning the columns before the fine shift search (as the authors' code does).
//!
//! Both sides use it: a robot to find its own loops, the station to find where two robots' maps
//! may overlap.

use std::f64::consts::TAU;
use std::num::NonZero;

use kiddo::{MutableKdTree, SquaredEuclidean};
use serde::{Deserialize, Serialize};

use crate::PointCloud;
use crate::memory::{HeapSize, vec_bytes};

/// How descriptors are made and compared.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ScanContextConfig {
    /// Azimuth wedges. Default 60 (the paper's N_s: 6° each).
    pub sectors: usize,
    /// Radius covered, metres. Default 80 m (the paper's L_max; the indoor preset uses 40 m, where
    /// a hall's walls are the structure worth describing).
    pub max_range: f64,
    /// Added to every height so that the ground and what stands on it are positive, metres.
    /// Default 2 m (the authors' LIDAR_HEIGHT): a cell's value is the height above a plane 2 m
    /// below the sensor, and a cell whose points all lie lower keeps 0, like an empty one.
    pub height_offset: f64,
    /// Columns searched either side of the sector-key alignment. Default 3 (the authors' 10 % of 60
    /// sectors, halved).
    pub shift_window: usize,
}

impl Default for ScanContextConfig {
    fn default() -> Self {
        ScanContextConfig { sectors: 60, max_range: 80.0, height_offset: 2.0, shift_window: 3 }
    }
}

/// Annuli (the paper's N_r): fixed, because the ring key is a point of a k-d tree whose dimension is
/// a type parameter.
pub const RINGS: usize = 20;

/// A scan's descriptor: `rings` x `sectors` cells, ring-major.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanContext {
    /// Annuli (rows).
    pub rings: usize,
    /// Wedges (columns).
    pub sectors: usize,
    /// Radius covered, metres.
    pub max_range: f64,
    /// `rings * sectors` heights, ring-major.
    pub cells: Vec<f32>,
}

/// How close two descriptors are, and at which column shift.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Match {
    /// Eq. (5): in [0, 1], 0 for identical descriptors; 1 when no column is seen by both.
    pub distance: f64,
    /// Columns `b` is rolled by to line up with `a`: column `j` of `a` matches column
    /// `(j + shift) mod sectors` of `b`.
    pub shift: usize,
    /// The yaw of scan `b`'s frame in scan `a`'s frame that the shift implies, radians in (−π, π].
    pub yaw: f64,
}

impl HeapSize for ScanContext {
    fn heap_bytes(&self) -> usize {
        vec_bytes(&self.cells)
    }
}

impl ScanContext {
    /// The descriptor of `scan` (sensor frame, z up), eq. (1): the maximum height per cell.
    pub fn new(scan: &PointCloud, config: &ScanContextConfig) -> Self {
        let (rings, sectors) = (RINGS, config.sectors.max(1));
        let mut cells = vec![0.0f32; rings * sectors];
        for p in &scan.points {
            let (x, y, z) = (f64::from(p.x), f64::from(p.y), f64::from(p.z));
            let range = x.hypot(y);
            if !range.is_finite() || range >= config.max_range || !z.is_finite() {
                continue;
            }
            let ring = ((range / config.max_range) * rings as f64) as usize;
            let sector = (azimuth(x, y) / TAU * sectors as f64) as usize;
            let cell = &mut cells[ring.min(rings - 1) * sectors + sector.min(sectors - 1)];
            *cell = cell.max((z + config.height_offset) as f32);
        }
        ScanContext { rings, sectors, max_range: config.max_range, cells }
    }

    /// Eq. (7): each ring's mean height, invariant to the sensor's yaw.
    pub fn ring_key(&self) -> [f32; RINGS] {
        let mut key = [0.0; RINGS];
        for (k, ring) in key.iter_mut().zip(self.cells.chunks(self.sectors)) {
            *k = ring.iter().sum::<f32>() / self.sectors as f32;
        }
        key
    }

    /// Each sector's mean height: rolls with the yaw, so it aligns columns cheaply.
    pub fn sector_key(&self) -> Vec<f32> {
        (0..self.sectors).map(|s| self.column(s).sum::<f32>() / self.rings as f32).collect()
    }

    /// Eq. (5): the distance to `other` at the best column shift near the sector-key alignment.
    pub fn distance(&self, other: &ScanContext, window: usize) -> Match {
        Comparable::new(self).distance(&Comparable::new(other), window)
    }

    /// The cells of sector `s`, ring by ring.
    fn column(&self, s: usize) -> impl Iterator<Item = f32> + '_ {
        self.cells.iter().skip(s).step_by(self.sectors).copied()
    }
}

/// A descriptor laid out for many comparisons: each column contiguous and scaled to unit length
/// (eq. 4's cosine is then a dot product), with its keys. Comparing two takes a few microseconds,
/// where the cells as they are (ring-major: a column is strided) took several times that.
#[derive(Clone, Debug, PartialEq)]
pub struct Comparable {
    /// Annuli, wedges and radius of the descriptor.
    pub rings: usize,
    /// Wedges.
    pub sectors: usize,
    /// Radius, metres.
    pub max_range: f64,
    /// Eq. (7).
    pub ring_key: [f32; RINGS],
    sector_key: Vec<f32>,
    /// Unit columns, sector-major; an empty column stays zero.
    unit: Vec<f32>,
    /// Whether each column saw anything.
    seen: Vec<bool>,
}

impl Comparable {
    /// Bytes it holds: its keys, unit columns and flags.
    pub fn bytes(&self) -> usize {
        std::mem::size_of_val(&self.ring_key)
            + std::mem::size_of_val(self.sector_key.as_slice())
            + std::mem::size_of_val(self.unit.as_slice())
            + std::mem::size_of_val(self.seen.as_slice())
    }

    /// The layout of `context`.
    pub fn new(context: &ScanContext) -> Self {
        let (rings, sectors) = (context.rings, context.sectors);
        let mut unit = Vec::with_capacity(rings * sectors);
        let mut seen = Vec::with_capacity(sectors);
        for s in 0..sectors {
            let norm = context.column(s).map(|x| f64::from(x) * f64::from(x)).sum::<f64>().sqrt();
            seen.push(norm > 0.0);
            unit.extend(context.column(s).map(|x| if norm > 0.0 { (f64::from(x) / norm) as f32 } else { 0.0 }));
        }
        let (ring_key, sector_key) = (context.ring_key(), context.sector_key());
        Self { rings, sectors, max_range: context.max_range, ring_key, sector_key, unit, seen }
    }

    /// Eq. (5): the distance to `other` at the best column shift near the sector-key alignment.
    pub fn distance(&self, other: &Comparable, window: usize) -> Match {
        let no_match = Match { distance: 1.0, shift: 0, yaw: 0.0 };
        if self.rings != other.rings || self.sectors != other.sectors {
            return no_match;
        }
        let n = self.sectors;
        let start = key_alignment(&self.sector_key, &other.sector_key);
        let window = window.min(n / 2) as isize;
        (-window..=window)
            .map(|d| (start as isize + d).rem_euclid(n as isize) as usize)
            .map(|shift| Match { distance: self.column_distance(other, shift), shift, yaw: shift_yaw(shift, n) })
            .min_by(|a, b| a.distance.total_cmp(&b.distance))
            .unwrap_or(no_match)
    }

    /// Eq. (4) at one shift: one minus the mean cosine similarity of the columns both scans see.
    ///
    /// Column `j` meets column `j + shift` of `other`, so the sum of the columns' dot products is
    /// two dot products of contiguous runs (before and after the wrap); an empty column is zero
    /// and adds nothing, so only the count of columns both see needs the masks.
    fn column_distance(&self, other: &Comparable, shift: usize) -> f64 {
        let (n, r) = (self.sectors, self.rings);
        let seen = (0..n).filter(|&j| self.seen[j] && other.seen[(j + shift) % n]).count();
        if seen == 0 {
            return 1.0;
        }
        let split = (n - shift) * r;
        let sum =
            dot(&self.unit[..split], &other.unit[shift * r..]) + dot(&self.unit[split..], &other.unit[..shift * r]);
        1.0 - sum / seen as f64
    }
}

/// Σ aᵢ bᵢ over two slices of the same length: eight single-precision partial sums (independent,
/// so they vectorise) per block of 64 products, each block's added in double precision, so the
/// rounding of a whole descriptor's 1200 products stays that of one column's.
fn dot(a: &[f32], b: &[f32]) -> f64 {
    const LANES: usize = 8;
    const BLOCK: usize = 64;
    let mut total = 0.0f64;
    for (a, b) in a.chunks(BLOCK).zip(b.chunks(BLOCK)) {
        let mut lanes = [0.0f32; LANES];
        let (a8, a_rest) = a.as_chunks::<LANES>();
        let (b8, b_rest) = b.as_chunks::<LANES>();
        for (x, y) in a8.iter().zip(b8) {
            for l in 0..LANES {
                lanes[l] += x[l] * y[l];
            }
        }
        let rest: f32 = a_rest.iter().zip(b_rest).map(|(x, y)| x * y).sum();
        total += lanes.iter().map(|&l| f64::from(l)).sum::<f64>() + f64::from(rest);
    }
    total
}

impl HeapSize for Comparable {
    fn heap_bytes(&self) -> usize {
        vec_bytes(&self.sector_key) + vec_bytes(&self.unit) + vec_bytes(&self.seen)
    }
}

/// Azimuth in [0, 2π), counter-clockwise from +x.
fn azimuth(x: f64, y: f64) -> f64 {
    y.atan2(x).rem_euclid(TAU)
}

/// The roll of `b`'s sector key that best matches `a`'s (least squared difference).
fn key_alignment(a: &[f32], b: &[f32]) -> usize {
    let n = a.len();
    // `b` twice over: each roll is then a contiguous window, whose sum vectorises.
    let twice: Vec<f32> = b.iter().chain(b).copied().collect();
    (0..n)
        .map(|shift| (shift, squared_difference(a, &twice[shift..shift + n])))
        .min_by(|x, y| x.1.total_cmp(&y.1))
        .map_or(0, |(shift, _)| shift)
}

/// Σ (aᵢ − bᵢ)² over two slices of the same length, in eight partial sums.
fn squared_difference(a: &[f32], b: &[f32]) -> f32 {
    const LANES: usize = 8;
    let mut lanes = [0.0f32; LANES];
    let (a8, a_rest) = a.as_chunks::<LANES>();
    let (b8, b_rest) = b.as_chunks::<LANES>();
    for (x, y) in a8.iter().zip(b8) {
        for l in 0..LANES {
            lanes[l] += (x[l] - y[l]).powi(2);
        }
    }
    lanes.iter().sum::<f32>() + a_rest.iter().zip(b_rest).map(|(x, y)| (x - y).powi(2)).sum::<f32>()
}

/// The yaw of `b` in `a`'s frame when column `j` of `a` sees what column `j + shift` of `b` sees:
/// a direction at azimuth α in `a` is at α − yaw in `b`, so `yaw = −shift · 2π / sectors`.
fn shift_yaw(shift: usize, sectors: usize) -> f64 {
    let yaw = -(shift as f64) * TAU / sectors as f64;
    // Into (−π, π].
    let wrapped = yaw.rem_euclid(TAU);
    if wrapped > std::f64::consts::PI { wrapped - TAU } else { wrapped }
}

/// Ring keys by keyframe index, for the nearest-neighbour query of Scan Context's first stage (a
/// kiddo k-d tree that grows as keyframes are added).
#[derive(Default)]
pub struct RingKeyIndex {
    tree: MutableKdTree<f32, RINGS>,
    len: usize,
}

impl RingKeyIndex {
    /// Adds keyframe `index`'s ring key.
    pub fn add(&mut self, key: &[f32; RINGS], index: usize) {
        // Only fails when the index overflows u32: four billion keyframes.
        if let Ok(item) = u32::try_from(index)
            && self.tree.add(key, item).is_ok()
        {
            self.len += 1;
        }
    }

    /// Keyframes in the index.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether no keyframe is indexed yet.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The `n` keyframes whose ring keys are nearest to `key`, nearest first.
    pub fn nearest(&self, key: &[f32; RINGS], n: usize) -> Vec<usize> {
        let Some(n) = NonZero::new(n.min(self.len)) else { return Vec::new() };
        let found = self.tree.query(key).nearest_n::<SquaredEuclidean<f32>>(n).execute();
        found.into_iter().map(|r| r.item as usize).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Isometry3, Point3, Vector3};

    /// A scene of boxes and walls at irregular places, seen from the origin.
    fn scene() -> PointCloud {
        PointCloud::from_points(testkit::boxes_around(7))
    }

    #[test]
    fn a_turned_scan_matches_at_the_yaw_it_was_turned_by() {
        let config = ScanContextConfig::default();
        let world = scene();
        let a = ScanContext::new(&world, &config);
        for yaw_deg in [0.0f64, 30.0, -90.0, 174.0, -138.0] {
            // Scan b is taken by a sensor turned by `yaw` in a's frame: b's points are the world's
            // seen through the inverse turn.
            let b_in_a = Isometry3::rotation(Vector3::z() * yaw_deg.to_radians());
            let b = ScanContext::new(&world.transformed(&b_in_a.inverse().cast()), &config);
            let m = a.distance(&b, config.shift_window);
            assert!(m.distance < 0.05, "yaw {yaw_deg}: distance {}", m.distance);
            let err = (m.yaw - yaw_deg.to_radians() + std::f64::consts::PI).rem_euclid(TAU) - std::f64::consts::PI;
            // One sector is 6°: the shift is right to a sector.
            assert!(err.abs().to_degrees() <= 6.0, "yaw {yaw_deg}: found {}", m.yaw.to_degrees());
            let ring_a = a.ring_key();
            let ring_b = b.ring_key();
            let d: f32 = ring_a.iter().zip(&ring_b).map(|(x, y)| (x - y).abs()).sum();
            assert!(d < 0.5, "ring keys differ by {d} at yaw {yaw_deg}");
        }
    }

    #[test]
    fn another_place_is_far() {
        let config = ScanContextConfig::default();
        let world = scene();
        let a = ScanContext::new(&world, &config);
        let moved = Isometry3::translation(25.0, -18.0, 0.0);
        let b = ScanContext::new(&world.transformed(&moved.cast()), &config);
        let m = a.distance(&b, config.shift_window);
        assert!(m.distance > 0.2, "distance {}", m.distance);
    }

    #[test]
    fn empty_and_mismatched_descriptors_are_far_not_a_panic() {
        let config = ScanContextConfig::default();
        let empty = ScanContext::new(&PointCloud::default(), &config);
        assert_eq!(empty.distance(&empty, 3).distance, 1.0);
        let other = ScanContext::new(&scene(), &ScanContextConfig { sectors: 30, ..config.clone() });
        assert_eq!(ScanContext::new(&scene(), &config).distance(&other, 3).distance, 1.0);
        let nan = PointCloud::from_points(vec![Point3::new(f32::NAN, 0.0, 0.0), Point3::new(1.0, 1.0, f32::INFINITY)]);
        assert!(ScanContext::new(&nan, &config).cells.iter().all(|c| *c == 0.0));
    }

    #[test]
    fn finds_the_nearest_keys_first_and_nothing_when_empty() {
        let mut index = RingKeyIndex::default();
        assert!(index.nearest(&[0.0; RINGS], 3).is_empty());
        for i in 0..100 {
            index.add(&[i as f32; RINGS], i);
        }
        assert_eq!(index.len(), 100);
        assert_eq!(index.nearest(&[41.2; RINGS], 3), vec![41, 42, 40]);
        assert_eq!(index.nearest(&[0.0; RINGS], 500).len(), 100);
    }

    /// Eq. (4) as written, in double precision: the mean over the columns both see of their cosine.
    fn textbook_column_distance(a: &Comparable, b: &Comparable, shift: usize) -> f64 {
        let (n, r) = (a.sectors, a.rings);
        let (mut sum, mut seen) = (0.0, 0usize);
        for j in 0..n {
            let k = (j + shift) % n;
            if a.seen[j] && b.seen[k] {
                sum += (0..r).map(|i| f64::from(a.unit[j * r + i]) * f64::from(b.unit[k * r + i])).sum::<f64>();
                seen += 1;
            }
        }
        if seen == 0 { 1.0 } else { 1.0 - sum / seen as f64 }
    }

    #[test]
    fn the_vectorised_comparison_is_eq_4_at_every_shift() {
        let config = ScanContextConfig::default();
        let scans: Vec<Comparable> = (1..7)
            .map(|seed| {
                let cloud = PointCloud::from_points(testkit::boxes_around(seed));
                let moved = Isometry3::translation(seed as f32 * 3.0, 0.0, 0.0);
                Comparable::new(&ScanContext::new(&cloud.transformed(&moved), &config))
            })
            .collect();
        for a in &scans {
            for b in &scans {
                for shift in 0..a.sectors {
                    let (fast, textbook) = (a.column_distance(b, shift), textbook_column_distance(a, b, shift));
                    assert!((fast - textbook).abs() < 1e-6, "shift {shift}: {fast} vs {textbook}");
                }
                // The key alignment: the roll of least squared difference, as written.
                let n = a.sectors;
                let textbook = (0..n)
                    .min_by(|&x, &y| {
                        let d = |s: usize| {
                            (0..n).map(|j| f64::from(a.sector_key[j] - b.sector_key[(j + s) % n]).powi(2)).sum::<f64>()
                        };
                        d(x).total_cmp(&d(y))
                    })
                    .unwrap();
                assert_eq!(key_alignment(&a.sector_key, &b.sector_key), textbook);
            }
        }
    }
}
