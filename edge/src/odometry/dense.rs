//! Dense registration of a whole scan, after KISS-ICP (Vizzo et al., RA-L 2023, section III):
//! the scan thinned on a voxel grid, fitted point to point against a hashed local map of points
//! under a Geman-McClure kernel whose reach follows the prediction's observed error (the adaptive
//! threshold, [`super::motion_model`]).
//!
//! The fit for scans whose features are too few for the feature fit: a solid-state sensor's
//! narrow view with no scan lines, a sparse scan in an open space. It needs no rings, no per-point
//! times and no setting: its voxel is derived from the ranges the sensor sees.

use cloud::se3;
use cloud::voxel::VoxelKey;
use nalgebra::{Isometry3, Matrix3, Matrix3x6, Matrix6, Point3, Vector3, Vector6};
use rayon::prelude::*;
use rustc_hash::FxHashMap;

/// Points a map voxel keeps: KISS-ICP's `max_points_per_voxel`, enough to describe the surface
/// through it, few enough that a search of 27 voxels stays cheap.
const POINTS_PER_VOXEL: usize = 20;
/// The map voxel as a share of the sensor's far range: KISS-ICP's `max_range / 100`.
const VOXEL_PER_RANGE: f64 = 0.01;
/// The smallest map voxel (m): below it a scan of a room would keep every return.
const MIN_VOXEL_M: f64 = 0.05;
/// The far range is this quantile of a scan's ranges: a few spurious far returns do not set it.
const FAR_RANGE_QUANTILE: f64 = 0.99;
/// Scans enter the map thinned at this share of its voxel, and are registered thinned at
/// [`SOURCE_PER_VOXEL`]: KISS-ICP's 0.5 and 1.5 (section III-B).
const MAP_PER_VOXEL: f64 = 0.5;
/// See [`MAP_PER_VOXEL`].
const SOURCE_PER_VOXEL: f64 = 1.5;
/// Gauss-Newton iterations at most, and the step size (m and rad together) below which the fit has
/// converged: KISS-ICP's `max_num_iterations` and `convergence_criterion`.
const MAX_ITERATIONS: usize = 500;
/// See [`MAX_ITERATIONS`].
const CONVERGED: f64 = 1e-4;
/// Fewest correspondences that determine a pose: three would, but a handful of points matched
/// by chance also would.
pub const MIN_CORRESPONDENCES: usize = 30;

/// The scale of a sensor as a scan shows it: how far it sees, and the voxels that follow.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scale {
    /// The far range, m ([`FAR_RANGE_QUANTILE`] of the ranges).
    pub far_range: f64,
    /// The map's voxel edge, m.
    pub voxel: f64,
}

impl Scale {
    /// The scale of `points` (sensor frame), or `None` for a scan without a point off the origin.
    pub fn of(points: &[Point3<f32>]) -> Option<Self> {
        let mut ranges: Vec<f32> = points.iter().map(|p| p.coords.norm()).filter(|r| *r > 0.0).collect();
        if ranges.is_empty() {
            return None;
        }
        let at = ((ranges.len() - 1) as f64 * FAR_RANGE_QUANTILE).round() as usize;
        let (_, far, _) = ranges.select_nth_unstable_by(at, f32::total_cmp);
        let far_range = f64::from(*far);
        Some(Scale { far_range, voxel: (far_range * VOXEL_PER_RANGE).max(MIN_VOXEL_M) })
    }

    /// The grid a scan is thinned on before it enters the map, m.
    pub fn map_grid(&self) -> f32 {
        (self.voxel * MAP_PER_VOXEL) as f32
    }

    /// The grid a scan is thinned on before it is registered, m.
    pub fn source_grid(&self) -> f32 {
        (self.voxel * SOURCE_PER_VOXEL) as f32
    }
}

/// A local map of points hashed by voxel, at most [`POINTS_PER_VOXEL`] each, in the odometry frame.
#[derive(Clone, Debug)]
pub struct PointMap {
    scale: Scale,
    inverse: f32,
    /// Squared distance a new point keeps from those of its voxel: the spacing of
    /// [`POINTS_PER_VOXEL`] points spread over a voxel's face, so that a full voxel samples its
    /// surface rather than the first sweep across it (KISS-ICP's map resolution).
    spacing_sq: f32,
    voxels: FxHashMap<VoxelKey, Vec<Point3<f32>>>,
}

impl PointMap {
    /// An empty map at `scale`.
    pub fn new(scale: Scale) -> Self {
        let spacing_sq = (scale.voxel * scale.voxel / POINTS_PER_VOXEL as f64) as f32;
        PointMap { scale, inverse: (1.0 / scale.voxel) as f32, spacing_sq, voxels: FxHashMap::default() }
    }

    /// The scale the map was made at.
    pub fn scale(&self) -> Scale {
        self.scale
    }

    /// True when no point was inserted (or all were cropped).
    pub fn is_empty(&self) -> bool {
        self.voxels.is_empty()
    }

    /// Bytes the map's points occupy.
    pub fn bytes(&self) -> usize {
        self.voxels.values().map(|v| v.capacity() * std::mem::size_of::<Point3<f32>>()).sum()
    }

    /// Adds `points` (sensor frame) seen from `pose`; full voxels take no more, nor points closer
    /// to one already in their voxel than the map's spacing.
    pub fn insert(&mut self, points: &[Point3<f32>], pose: &Isometry3<f64>) {
        let pose = pose.cast::<f32>();
        for p in points {
            let world = pose * p;
            let voxel = self.voxels.entry(VoxelKey::of(&world, self.inverse)).or_default();
            if voxel.len() < POINTS_PER_VOXEL && voxel.iter().all(|q| (q - world).norm_squared() >= self.spacing_sq) {
                voxel.push(world);
            }
        }
    }

    /// Drops the voxels whose first point is farther than the far range from `centre`.
    pub fn crop(&mut self, centre: &Point3<f64>) {
        let centre = centre.cast::<f32>();
        let radius_sq = (self.scale.far_range * self.scale.far_range) as f32;
        self.voxels.retain(|_, points| points.first().is_some_and(|p| (p - centre).norm_squared() <= radius_sq));
    }

    /// The map point nearest to `query` within `radius` (m), searched in the 27 voxels around it
    /// (`radius` above a voxel finds only what those hold).
    fn nearest(&self, query: &Point3<f32>, radius: f32) -> Option<Point3<f32>> {
        let VoxelKey([x, y, z]) = VoxelKey::of(query, self.inverse);
        let mut best: Option<(f32, Point3<f32>)> = None;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    let Some(points) = self.voxels.get(&VoxelKey([x + dx, y + dy, z + dz])) else { continue };
                    for p in points {
                        let d = (p - query).norm_squared();
                        if best.is_none_or(|(b, _)| d < b) {
                            best = Some((d, *p));
                        }
                    }
                }
            }
        }
        best.filter(|(d, _)| *d <= radius * radius).map(|(_, p)| p)
    }
}

/// The share of `source` (sensor frame) with a map point within one map voxel at `pose`: how much
/// of a scan a pose places on the map, the measure [`DenseFit::on_map`] is of.
pub fn on_map(source: &[Point3<f32>], map: &PointMap, pose: &Isometry3<f64>) -> f64 {
    let moved = pose.cast::<f32>();
    let radius = map.scale.voxel as f32;
    let close = source.par_iter().filter(|p| map.nearest(&(moved * *p), radius).is_some()).count();
    close as f64 / source.len().max(1) as f64
}

/// A dense fit's outcome.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DenseFit {
    /// The sensor pose in the odometry frame.
    pub pose: Isometry3<f64>,
    /// Points that found a map point within the threshold in the last iteration.
    pub correspondences: usize,
    /// The share of the source points with a map point within one map voxel at the fitted pose:
    /// how much of the scan lies on the map, what the odometry's health judges.
    pub on_map: f64,
    /// Gauss-Newton iterations run.
    pub iterations: usize,
}

/// One iteration's normal equations, summed per rayon task and reduced once.
#[derive(Clone, Copy)]
struct Normal {
    h: Matrix6<f64>,
    b: Vector6<f64>,
    n: usize,
    /// Of `n`, those within a map voxel.
    close: usize,
}

impl Normal {
    fn zero() -> Self {
        Normal { h: Matrix6::zeros(), b: Vector6::zeros(), n: 0, close: 0 }
    }

    fn add(mut self, other: Normal) -> Self {
        self.h += other.h;
        self.b += other.b;
        self.n += other.n;
        self.close += other.close;
        self
    }

    /// The residual of a source point moved to `world` against its nearest map point within
    /// `radius`, weighted by the Geman-McClure kernel of scale `kernel`.
    fn add_point(mut self, world: &Point3<f32>, map: &PointMap, radius: f32, kernel: f64) -> Self {
        let Some(q) = map.nearest(world, radius) else { return self };
        let w = world.cast::<f64>().coords;
        let residual: Vector3<f64> = w - q.cast::<f64>().coords;
        // The residual's Jacobian under a left perturbation exp(δ) T: [I, -[Tp]×].
        let mut jacobian = Matrix3x6::<f64>::zeros();
        jacobian.fixed_view_mut::<3, 3>(0, 0).copy_from(&Matrix3::identity());
        jacobian.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-se3::skew(&w)));
        let r2 = residual.norm_squared();
        self.close += usize::from(r2 <= map.scale.voxel * map.scale.voxel);
        let weight = kernel * kernel / ((kernel + r2) * (kernel + r2));
        self.h += weight * jacobian.transpose() * jacobian;
        self.b += weight * jacobian.transpose() * residual;
        self.n += 1;
        self
    }
}

/// Source points per block of the parallel sum.
const BLOCK: usize = 512;

/// Fits `source` (sensor frame, already thinned on [`Scale::source_grid`]) to `map` from `initial`,
/// where `sigma` (m) is the prediction's observed error: correspondences within 3σ, weighted by the
/// Geman-McClure kernel `κ² / (κ + r²)²` with κ = σ / 3 (section III-D, as KISS-ICP runs it).
/// `None` when fewer than [`MIN_CORRESPONDENCES`] points found a map point, or the system is singular.
pub fn register(source: &[Point3<f32>], map: &PointMap, initial: &Isometry3<f64>, sigma: f64) -> Option<DenseFit> {
    let kernel = sigma / 3.0;
    let radius = (3.0 * sigma) as f32;
    let mut pose = *initial;
    let mut fit = DenseFit { pose, correspondences: 0, on_map: 0.0, iterations: 0 };
    for iteration in 1..=MAX_ITERATIONS {
        let moved = pose.cast::<f32>();
        // Fixed blocks summed in order: the fit does not depend on how rayon splits the work.
        let normal = source
            .par_chunks(BLOCK)
            .map(|block| block.iter().fold(Normal::zero(), |acc, p| acc.add_point(&(moved * p), map, radius, kernel)))
            .collect::<Vec<_>>()
            .into_iter()
            .fold(Normal::zero(), Normal::add);
        fit.correspondences = normal.n;
        fit.on_map = normal.close as f64 / source.len() as f64;
        if normal.n < MIN_CORRESPONDENCES {
            return None;
        }
        let step = normal.h.cholesky().map(|c| -c.solve(&normal.b))?;
        pose = se3::exp(&step) * pose;
        fit.pose = pose;
        fit.iterations = iteration;
        if step.norm() < CONVERGED {
            break;
        }
    }
    Some(fit)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A hall's walls and floor, 36 m by 24 m, at 20,000 points drawn uniformly (seeded by
    /// `seed`) as a scan samples surfaces: nowhere on a lattice a fit could snap to.
    fn hall(seed: u64) -> Vec<Point3<f32>> {
        let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let mut uniform = move |a: f32, b: f32| {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            a + (b - a) * ((state >> 40) as f32 / (1u64 << 24) as f32)
        };
        (0..20_000)
            .map(|i| match i % 4 {
                0 => Point3::new(18.0, uniform(-18.0, 18.0), uniform(-6.0, 9.0)),
                1 => Point3::new(-18.0, uniform(-18.0, 18.0), uniform(-6.0, 9.0)),
                2 => Point3::new(uniform(-12.0, 12.0), 12.0, uniform(-6.0, 9.0)),
                _ => Point3::new(uniform(-18.0, 18.0), uniform(-12.0, 12.0), -6.0),
            })
            .collect()
    }

    /// A box room's walls and floor, 12 m by 8 m, sampled every 10 cm, seen from near its centre.
    fn room() -> Vec<Point3<f32>> {
        let mut points = Vec::new();
        let steps = |a: f32, b: f32| (0..((b - a) / 0.1) as i32).map(move |i| a + i as f32 * 0.1);
        for u in steps(-6.0, 6.0) {
            for v in steps(-2.0, 3.0) {
                points.push(Point3::new(6.0, u, v));
                points.push(Point3::new(-6.0, u, v));
                points.push(Point3::new(u * 0.7, 4.0, v));
            }
            for v in steps(-4.0, 4.0) {
                points.push(Point3::new(u, v, -2.0));
            }
        }
        points
    }

    #[test]
    fn the_scale_follows_the_far_returns() {
        let scale = Scale::of(&room()).expect("points");
        // The room's far corners are 9 m away.
        assert!(scale.far_range > 8.0 && scale.far_range < 9.1, "{scale:?}");
        assert!((scale.voxel - scale.far_range / 100.0).abs() < 1e-9, "{scale:?}");
        // A cupboard's inside: 1 % of its range is below the smallest voxel.
        let cupboard: Vec<Point3<f32>> = room().iter().map(|p| p * 0.2).collect();
        assert_eq!(Scale::of(&cupboard).expect("points").voxel, MIN_VOXEL_M);
        assert!(Scale::of(&[Point3::origin()]).is_none());
    }

    #[test]
    fn a_moved_scan_is_fitted_back_to_where_it_was_taken() {
        let points = hall(1);
        let scale = Scale::of(&points).unwrap();
        let mut map = PointMap::new(scale);
        map.insert(&points, &Isometry3::identity());
        // The prediction is 0.15 m and 0.3 deg off (a point 20 m away 0.25 m, within the voxel
        // neighbourhood of 0.22 m voxels that the search reaches): the scan samples the hall's
        // surfaces elsewhere, seen from there.
        let truth = Isometry3::new(Vector3::new(0.15, -0.05, 0.02), Vector3::new(0.0, 0.001, 0.3f64.to_radians()));
        let seen: Vec<Point3<f32>> = hall(2).iter().map(|p| truth.inverse().cast::<f32>() * p).collect();
        let fit = register(&seen, &map, &Isometry3::identity(), 0.5).expect("a fit");
        // The fit places more of the scan on the map than the prediction did, and says so alike.
        let predicted = on_map(&seen, &map, &Isometry3::identity());
        assert!(fit.on_map > predicted, "{fit:?}, {predicted} at the prediction");
        assert!((on_map(&seen, &map, &fit.pose) - fit.on_map).abs() < 0.01, "{fit:?}");
        let error = se3::pose_error(&fit.pose, &truth);
        assert!(
            error.translation_m < 0.01 && error.rotation_deg < 0.1,
            "{error:?} after {} iterations",
            fit.iterations
        );
    }

    #[test]
    fn a_scan_off_the_map_is_not_fitted() {
        let mut map = PointMap::new(Scale::of(&hall(1)).unwrap());
        map.insert(&hall(1), &Isometry3::identity());
        let elsewhere = Isometry3::translation(500.0, 0.0, 0.0);
        assert!(register(&hall(1), &map, &elsewhere, 0.5).is_none());
    }

    #[test]
    fn a_full_voxel_takes_no_more_and_the_crop_drops_far_voxels() {
        let scale = Scale { far_range: 10.0, voxel: 1.0 };
        let mut map = PointMap::new(scale);
        // A 4 x 4 x 4 lattice 0.25 m apart in one voxel, above the 0.22 m spacing: 20 are kept.
        let lattice: Vec<Point3<f32>> = (0..64)
            .map(|i| {
                Point3::new(0.1 + 0.25 * (i % 4) as f32, 0.1 + 0.25 * (i / 4 % 4) as f32, 0.1 + 0.25 * (i / 16) as f32)
            })
            .collect();
        map.insert(&lattice, &Isometry3::identity());
        assert_eq!(map.voxels.values().map(Vec::len).sum::<usize>(), POINTS_PER_VOXEL);
        map.voxels.clear();
        map.insert(&[Point3::new(0.5, 0.5, 0.5), Point3::new(0.5, 0.5, 0.51)], &Isometry3::identity());
        assert_eq!(map.voxels.values().map(Vec::len).sum::<usize>(), 1, "a point 1 cm from one kept");
        map.insert(&lattice[..POINTS_PER_VOXEL + 5], &Isometry3::identity());
        map.insert(&[Point3::new(30.5, 0.5, 0.5)], &Isometry3::identity());
        assert_eq!(map.voxels.values().map(Vec::len).sum::<usize>(), POINTS_PER_VOXEL + 1);
        map.crop(&Point3::origin());
        assert_eq!(map.voxels.len(), 1);
        assert_eq!(map.bytes(), map.voxels.values().map(|v| v.capacity() * 12).sum::<usize>());
    }
}
