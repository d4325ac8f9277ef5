//! The free space a robot's sensor saw, and whether another map placed in its frame contradicts it.
//!
//! Two maps can agree where they overlap and still be placed wrongly: look-alike streets, a hall
//! turned by 180°. What gives such a placement away is the space one robot saw *through*: the other
//! map puts a wall where its rays passed. This is Birk & Carpin's acceptance index for merging
//! occupancy grids (Birk & Carpin, "Merging occupancy grid maps from multiple robots", Proc. IEEE
//! 94(7), 2006), `ω = agr / (agr + dis)`, counted in 3D on the keyframes the robots sent instead of
//! on grids:
//!
//! - each keyframe becomes a [`View`]: its sensor pose and a [`RangeImage`], the nearest return per
//!   azimuth x elevation bin (its free space is everything nearer along the bin's rays);
//! - a point of the other map, moved into this map's frame, is looked up in the nearest views
//!   ([`Views::classify`]): a view with a return within [`VisibilityConfig::margin`] of it *agrees*;
//!   a view whose nearest return in its direction, and in the directions around it, lies farther
//!   than the margin beyond it saw through it: a *conflict*; anything else (behind a surface, out of
//!   range, a direction with no return) is unknown and counts for neither;
//! - [`acceptance`] tallies a sample of points both ways.
//!
//! The rules lean to "unknown": a conflict needs every return around the point's direction to lie
//! past it, so that grazing rays and bin edges do not invent free space.

use std::f32::consts::PI;
use std::sync::Arc;

use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

use crate::kdtree::KdTree;
use crate::memory::{HeapSize, vec_bytes};

/// How range images are made and points judged against them.
#[derive(Clone, Debug, PartialEq)]
pub struct VisibilityConfig {
    /// Azimuth bins of a range image (default 360: 1° each, about a LiDAR's horizontal spacing
    /// after a keyframe's 0.1-0.2 m voxels at 10 m).
    pub azimuth_bins: usize,
    /// Elevation bin, degrees (default 1: a 16-beam sensor's 2° rings leave every other row
    /// empty, which only makes more directions unknown).
    pub elevation_bin_deg: f32,
    /// How far a point may lie from a view's return and still agree with it, and how far short of
    /// every return around its direction it must lie to conflict, metres (outdoor 1.0, indoor 0.5:
    /// odometry drift and the keyframe voxel must not make a true placement conflict).
    pub margin: f32,
    /// Widest gap between a sensor's rings looked across for the neighbouring ring, degrees
    /// (default 3: a VLP-16's 2° with room; denser sensors find theirs in the next row).
    pub ring_gap_deg: f32,
    /// Views consulted per point: the nearest ones (default 4).
    pub views_per_point: usize,
    /// Views whose sensor lies farther than this from a point are not consulted, metres (outdoor
    /// 60, indoor 30: a far point's bin spans metres).
    pub max_range: f32,
}

impl VisibilityConfig {
    /// Streets, campuses.
    pub fn outdoor() -> Self {
        Self {
            azimuth_bins: 360,
            elevation_bin_deg: 1.0,
            ring_gap_deg: 3.0,
            margin: 1.0,
            views_per_point: 4,
            max_range: 60.0,
        }
    }

    /// Halls, warehouses.
    pub fn indoor() -> Self {
        Self { margin: 0.5, max_range: 30.0, ..Self::outdoor() }
    }

    /// Checks every setting: counts positive, angles and distances positive and finite.
    pub fn validate(&self) -> Result<(), &'static str> {
        let positive = |v: f32| v > 0.0 && v.is_finite();
        let ok = self.azimuth_bins > 0
            && self.views_per_point > 0
            && positive(self.elevation_bin_deg)
            && self.ring_gap_deg >= 0.0
            && self.ring_gap_deg.is_finite()
            && positive(self.margin)
            && positive(self.max_range);
        if ok {
            Ok(())
        } else {
            Err(
                "visibility: azimuth_bins and views_per_point must be positive, elevation_bin_deg, margin and max_range positive and finite, ring_gap_deg finite and not negative",
            )
        }
    }
}

impl Default for VisibilityConfig {
    fn default() -> Self {
        Self::outdoor()
    }
}

/// Ranges are stored in centimetres; 0 marks a bin with no return.
const EMPTY: u16 = 0;
const CM_PER_M: f32 = 100.0;

/// The nearest return per azimuth x elevation bin of one scan, in its sensor frame.
///
/// Only the elevation band the scan's points span is stored: 360 x 30 cells of 2 bytes for a
/// 30° field of view, 21 KB per keyframe.
#[derive(Clone, Debug, PartialEq)]
pub struct RangeImage {
    azimuth_bins: usize,
    /// Elevation bin, radians.
    elevation_bin: f32,
    /// Elevation of row 0's lower edge, radians.
    min_elevation: f32,
    rows: usize,
    /// Rows searched above and below for the neighbouring ring.
    ring_gap: usize,
    /// Nearest return per cell, centimetres, row-major; [`EMPTY`] where none.
    cells: Vec<u16>,
}

impl HeapSize for RangeImage {
    fn heap_bytes(&self) -> usize {
        vec_bytes(&self.cells)
    }
}

impl RangeImage {
    /// The image of `points` (sensor frame); points at the origin or not finite are skipped. A
    /// configuration that fails [`VisibilityConfig::validate`] gives an image that sees nothing (no
    /// rows: no bin is ever looked up).
    pub fn new(points: &[Point3<f32>], config: &VisibilityConfig) -> Self {
        let points = if config.validate().is_ok() { points } else { &[] };
        let elevation_bin = config.elevation_bin_deg.to_radians();
        let polar: Vec<(f32, f32, f32)> = points.iter().filter_map(polar).collect();
        let min_elevation = polar.iter().map(|p| p.1).fold(f32::INFINITY, f32::min);
        let max_elevation = polar.iter().map(|p| p.1).fold(f32::NEG_INFINITY, f32::max);
        let rows = if polar.is_empty() { 0 } else { ((max_elevation - min_elevation) / elevation_bin) as usize + 1 };
        let mut image = Self {
            azimuth_bins: config.azimuth_bins,
            elevation_bin,
            min_elevation: if polar.is_empty() { 0.0 } else { min_elevation },
            rows,
            ring_gap: (config.ring_gap_deg / config.elevation_bin_deg).ceil() as usize,
            cells: vec![EMPTY; rows * config.azimuth_bins],
        };
        for &(azimuth, elevation, range) in &polar {
            let Some(cell) = image.cell(azimuth, elevation) else { continue };
            let cm = (range * CM_PER_M).clamp(1.0, f32::from(u16::MAX)) as u16;
            let held = &mut image.cells[cell];
            if *held == EMPTY || cm < *held {
                *held = cm;
            }
        }
        image
    }

    /// Bytes the image holds.
    pub fn bytes(&self) -> usize {
        self.cells.len() * std::mem::size_of::<u16>()
    }

    fn column(&self, azimuth: f32) -> usize {
        let a = (azimuth + PI) / (2.0 * PI) * self.azimuth_bins as f32;
        (a as usize).min(self.azimuth_bins - 1)
    }

    fn row(&self, elevation: f32) -> Option<usize> {
        let r = (elevation - self.min_elevation) / self.elevation_bin;
        (r >= 0.0 && (r as usize) < self.rows).then_some(r as usize)
    }

    fn cell(&self, azimuth: f32, elevation: f32) -> Option<usize> {
        Some(self.row(elevation)? * self.azimuth_bins + self.column(azimuth))
    }

    /// The return in the direction of `p` (sensor frame) and the nearest return around it, metres:
    /// over its row and the nearest ring above and below (the first row within
    /// [`VisibilityConfig::ring_gap_deg`] with a return in these columns), the bin's column and
    /// the two beside it. `None` when the bin itself has no return. Looking to the next *ring*
    /// rather than the next row matters for sparse sensors: a wall's top edge lies above a 2°
    /// ring's beam, and only the ring below shows that the wall is there.
    fn returns_around(&self, azimuth: f32, elevation: f32) -> Option<(f32, f32)> {
        let row = self.row(elevation)?;
        let column = self.column(azimuth);
        let own = self.cells[row * self.azimuth_bins + column];
        if own == EMPTY {
            return None;
        }
        let nearest_in = |r: usize| {
            [self.azimuth_bins - 1, 0, 1]
                .into_iter()
                .map(|dc| self.cells[r * self.azimuth_bins + (column + dc) % self.azimuth_bins])
                .filter(|&cm| cm != EMPTY)
                .min()
        };
        let below = (1..=self.ring_gap).filter_map(|d| row.checked_sub(d)).find_map(nearest_in);
        let above = (1..=self.ring_gap).map(|d| row + d).take_while(|&r| r < self.rows).find_map(nearest_in);
        let nearest = [nearest_in(row), below, above].into_iter().flatten().min().unwrap_or(own);
        Some((f32::from(own) / CM_PER_M, f32::from(nearest) / CM_PER_M))
    }

    /// What this image says of `p` (sensor frame).
    pub fn classify(&self, p: &Point3<f32>, margin: f32) -> Seen {
        let Some((azimuth, elevation, range)) = polar(p) else { return Seen::Unknown };
        match self.returns_around(azimuth, elevation) {
            None => Seen::Unknown,
            Some((own, _)) if (range - own).abs() <= margin => Seen::Surface,
            Some((_, nearest)) if range + margin < nearest => Seen::Free,
            Some(_) => Seen::Unknown,
        }
    }
}

/// Azimuth, elevation (radians) and range of a point in the sensor frame; `None` at the origin or
/// when not finite.
fn polar(p: &Point3<f32>) -> Option<(f32, f32, f32)> {
    let range = p.coords.norm();
    (range.is_finite() && range > 1e-3).then(|| (p.y.atan2(p.x), (p.z / range).clamp(-1.0, 1.0).asin(), range))
}

/// What a view says of a point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Seen {
    /// The view has a return at the point: it agrees something is there.
    Surface,
    /// The view's rays passed beyond the point: it saw that nothing is there.
    Free,
    /// Behind a surface, out of range, or in a direction without returns.
    Unknown,
}

/// One keyframe as the sensor saw it: where it was and its range image.
#[derive(Clone, Debug)]
pub struct View {
    /// Sensor pose in the map's frame.
    pub pose: Isometry3<f32>,
    /// The keyframe's range image (shared: a view is re-posed when the robot's poses change).
    pub image: Arc<RangeImage>,
}

/// A map's views, indexed by sensor position.
pub struct Views {
    views: Vec<View>,
    /// Inverse poses: map frame to each sensor frame.
    to_sensor: Vec<Isometry3<f32>>,
    tree: KdTree,
}

impl Views {
    /// Indexes `views`.
    pub fn new(views: Vec<View>) -> Self {
        let origins: Vec<[f32; 3]> = views.iter().map(|v| v.pose.translation.vector.into()).collect();
        let to_sensor = views.iter().map(|v| v.pose.inverse()).collect();
        Self { tree: KdTree::new(&origins), to_sensor, views }
    }

    /// Number of views.
    pub fn len(&self) -> usize {
        self.views.len()
    }

    /// True when there are no views.
    pub fn is_empty(&self) -> bool {
        self.views.is_empty()
    }

    /// Bytes of the range images.
    pub fn bytes(&self) -> usize {
        self.views.iter().map(|v| v.image.bytes()).sum()
    }

    /// What the nearest views say of `p` (map frame): [`Seen::Surface`] if any view has a return
    /// there, else [`Seen::Free`] if any saw through it, else [`Seen::Unknown`].
    pub fn classify(&self, p: &Point3<f32>, config: &VisibilityConfig) -> Seen {
        let near = self.tree.knn_within(&p.coords.into(), config.views_per_point, config.max_range);
        let mut seen = Seen::Unknown;
        for n in near {
            match self.views[n.index].image.classify(&(self.to_sensor[n.index] * p), config.margin) {
                Seen::Surface => return Seen::Surface,
                Seen::Free => seen = Seen::Free,
                Seen::Unknown => {}
            }
        }
        seen
    }
}

/// Agreements and conflicts of one map's points with another map's views.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Acceptance {
    /// Points some view has a return at.
    pub agree: usize,
    /// Points no view has a return at and some view saw through.
    pub conflict: usize,
}

impl Acceptance {
    /// Birk & Carpin's `ω = agr / (agr + dis)`; 1 when no point was decided (no evidence against).
    pub fn index(&self) -> f64 {
        let decided = self.agree + self.conflict;
        if decided == 0 { 1.0 } else { self.agree as f64 / decided as f64 }
    }
}

impl std::fmt::Display for Acceptance {
    /// `0.97 (1200 agree, 37 conflict)`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.2} ({} agree, {} conflict)", self.index(), self.agree, self.conflict)
    }
}

impl std::ops::Add for Acceptance {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        Self { agree: self.agree + o.agree, conflict: self.conflict + o.conflict }
    }
}

/// Tallies at most `samples` of `points` (evenly spread), moved by `transform` into the frame of
/// `views`.
pub fn acceptance(
    points: &[Point3<f32>],
    transform: &Isometry3<f32>,
    views: &Views,
    samples: usize,
    config: &VisibilityConfig,
) -> Acceptance {
    let stride = (points.len() / samples.max(1)).max(1);
    points
        .par_iter()
        .step_by(stride)
        .map(|p| match views.classify(&(transform * p), config) {
            Seen::Surface => Acceptance { agree: 1, conflict: 0 },
            Seen::Free => Acceptance { agree: 0, conflict: 1 },
            Seen::Unknown => Acceptance::default(),
        })
        .reduce(Acceptance::default, |a, b| a + b)
}

#[cfg(test)]
mod tests {
    use nalgebra::{Translation3, UnitQuaternion};

    use super::*;

    /// A sensor at the origin inside a box room 20 x 20 x 6 m (walls at ±10 m, floor at -1.5 m,
    /// ceiling at +4.5 m), scanned on a 0.5° x 0.5° grid.
    fn room_scan() -> Vec<Point3<f32>> {
        let mut points = Vec::new();
        for i in 0..720 {
            for j in 0..120 {
                let azimuth = (i as f32 * 0.5).to_radians() - PI;
                let elevation = (j as f32 * 0.5 - 30.0).to_radians();
                let d = nalgebra::Vector3::new(
                    elevation.cos() * azimuth.cos(),
                    elevation.cos() * azimuth.sin(),
                    elevation.sin(),
                );
                // Distance to the first face hit along d.
                let walls = [10.0 / d.x.abs(), 10.0 / d.y.abs(), if d.z < 0.0 { -1.5 / d.z } else { 4.5 / d.z }];
                let t = walls.into_iter().fold(f32::INFINITY, f32::min);
                points.push(Point3::from(d * t));
            }
        }
        points
    }

    #[test]
    fn a_point_on_a_wall_agrees_one_in_the_room_conflicts_one_behind_is_unknown() {
        let config = VisibilityConfig::indoor();
        let image = RangeImage::new(&room_scan(), &config);
        assert_eq!(image.classify(&Point3::new(10.0, 2.0, 0.5), config.margin), Seen::Surface);
        assert_eq!(image.classify(&Point3::new(5.0, 2.0, 0.5), config.margin), Seen::Free);
        assert_eq!(image.classify(&Point3::new(13.0, 2.0, 0.5), config.margin), Seen::Unknown);
        // Above the scanned band (elevation > 30°) nothing was seen.
        assert_eq!(image.classify(&Point3::new(1.0, 0.0, 4.0), config.margin), Seen::Unknown);
        // Within the margin of the wall is still the wall.
        assert_eq!(image.classify(&Point3::new(9.6, -3.0, 0.0), config.margin), Seen::Surface);
    }

    #[test]
    fn a_point_just_before_an_edge_is_not_free_when_a_neighbouring_bin_returns_nearer() {
        // Two returns: a near post at 3 m in one direction, a far wall at 20 m beside it.
        let config = VisibilityConfig::indoor();
        let post = Point3::new(3.0, 0.0, 0.0);
        let beside = Point3::new(20.0 * 0.9998, 20.0 * (1.0f32.to_radians()).sin(), 0.0);
        let image = RangeImage::new(&[post, beside], &config);
        // 10 m in the far wall's bin: its neighbour (the post's bin) reaches only 3 m.
        let probe = Point3::new(10.0 * 0.9998, 10.0 * (1.0f32.to_radians()).sin(), 0.0);
        assert_eq!(image.classify(&probe, config.margin), Seen::Unknown);
    }

    #[test]
    fn a_canopy_between_two_rings_of_a_sparse_sensor_is_not_free_space() {
        // A VLP-16's rings every 2°; a canopy 10 m ahead whose lower edge lies between the 5° and
        // 7° rings: the 5° ring passes under it to a wall 40 m away, the 7° ring hits it.
        let config = VisibilityConfig::outdoor();
        let ring = |deg: f32, range: f32| {
            let e = deg.to_radians();
            (-20..=20).map(move |a| {
                let a = (a as f32 * 0.2).to_radians();
                Point3::new(range * e.cos() * a.cos(), range * e.cos() * a.sin(), range * e.sin())
            })
        };
        let mut points: Vec<Point3<f32>> = Vec::new();
        for deg in [-15.0, -13.0, -11.0, -9.0, -7.0, -5.0, -3.0, -1.0, 1.0, 3.0, 5.0] {
            points.extend(ring(deg, 40.0));
        }
        points.extend(ring(7.0, 10.0 / 7.0f32.to_radians().cos()));
        let image = RangeImage::new(&points, &config);
        // On the canopy's edge, at 5.5°: in the 5° ring's bin, whose return is the far wall.
        let e = 5.5f32.to_radians();
        let edge = Point3::new(10.0, 0.0, 10.0 * e.tan());
        assert_eq!(image.classify(&edge, config.margin), Seen::Unknown);
        // 20 m out on the 1° ring, whose neighbouring rings also reach the far wall: seen through.
        let open = Point3::new(20.0 * 1.0f32.to_radians().cos(), 0.0, 20.0 * 1.0f32.to_radians().sin());
        assert_eq!(image.classify(&open, config.margin), Seen::Free);
        // The same under the canopy, on the 5° ring: the 7° ring's canopy return is its neighbour's,
        // so it stays unknown (a ring's free space is not claimed next to a nearer ring's return).
        let under = Point3::new(20.0 * 5.0f32.to_radians().cos(), 0.0, 20.0 * 5.0f32.to_radians().sin());
        assert_eq!(image.classify(&under, config.margin), Seen::Unknown);
    }

    #[test]
    fn the_acceptance_of_a_room_placed_rightly_is_high_and_wrongly_low() {
        let config = VisibilityConfig::indoor();
        let scan = room_scan();
        let image = Arc::new(RangeImage::new(&scan, &config));
        let pose =
            Isometry3::from_parts(Translation3::new(3.0, -2.0, 0.0), UnitQuaternion::from_euler_angles(0.0, 0.0, 0.7));
        let views = Views::new(vec![View { pose, image }]);
        // The room's points in the map frame, as another robot would have mapped them.
        let map: Vec<Point3<f32>> = scan.iter().map(|p| pose * p).collect();
        let right = acceptance(&map, &Isometry3::identity(), &views, 5_000, &config);
        assert!(right.index() > 0.99 && right.agree > 1_000, "{right:?}");
        // Shifted 4 m along the room's x axis: its -x wall (about 14 % of the points) lands inside
        // the room the sensor saw through, the +x wall behind it (unknown), the rest slides along
        // itself (agrees where it stays inside): ω ≈ 0.8.
        let along_x = pose.rotation * nalgebra::Vector3::new(4.0, 0.0, 0.0);
        let shifted = Isometry3::from_parts(Translation3::from(along_x), UnitQuaternion::identity());
        let wrong = acceptance(&map, &shifted, &views, 5_000, &config);
        assert!(wrong.index() < 0.9 && wrong.conflict > 400, "{wrong:?}");
    }

    #[test]
    fn no_views_or_no_points_decide_nothing() {
        let config = VisibilityConfig::default();
        let none = Views::new(Vec::new());
        let a = acceptance(&[Point3::new(1.0, 2.0, 3.0)], &Isometry3::identity(), &none, 10, &config);
        assert_eq!(a, Acceptance::default());
        assert_eq!(a.index(), 1.0);
        let empty = RangeImage::new(&[], &config);
        assert_eq!(empty.classify(&Point3::new(1.0, 0.0, 0.0), 0.5), Seen::Unknown);
        assert_eq!(empty.bytes(), 0);
        // An invalid configuration is refused by validate and sees nothing, without a panic.
        let bad = VisibilityConfig { azimuth_bins: 0, elevation_bin_deg: 0.0, ..config };
        assert!(bad.validate().is_err());
        let blind = RangeImage::new(&[Point3::new(5.0, 0.0, 0.0)], &bad);
        assert_eq!(blind.classify(&Point3::new(1.0, 0.0, 0.0), 0.5), Seen::Unknown);
    }
}
