//! Features for scans without usable rings (solid-state sensors, shuffled or re-ordered files):
//! the shape of each voxel's points (local PCA) stands in for the ring smoothness of eq. 1. A
//! voxel whose points are flat gives a plane feature, one whose points run along a line gives an
//! edge feature; each is the voxel's point nearest its centroid, so it keeps its measurement time.
//!
//! One voxel grid, one pass: the cost is a hash insert per point and a 3x3 eigen-decomposition
//! per voxel, a few milliseconds for a 120k-point scan, where deriving rings by clustering
//! elevations costs ~100 ms.

use cloud::PointCloud;
use cloud::eigen3::symmetric_eigen3;
use cloud::moments::mean_covariance;
use cloud::voxel::VoxelKey;
use nalgebra::Point3;
use rayon::prelude::*;
use rustc_hash::FxHashMap;

use super::FeatureConfig;
use super::feature_points::{Feature, Features};

/// Fewest points a voxel needs for its shape to mean anything.
const MIN_POINTS: usize = 6;
/// A voxel is flat when its smallest eigenvalue is below this share of their sum (surface
/// variation, Pauly 2002): a clean plane sampled with 1-3 cm noise over 0.6 m measures < 0.005.
const MAX_SURFACE_VARIATION: f64 = 0.01;
/// ... and spread in two directions: the middle eigenvalue at least this share of the largest.
const MIN_SPREAD: f64 = 0.05;
/// A voxel is a line when its largest eigenvalue exceeds this many times the middle one (as the
/// solver's line test, F-LOAM's 3, made stricter: a voxel sees a line only over its own width).
const LINE_RATIO: f64 = 10.0;

/// Plane and edge features of `scan` from the shape of its points per voxel of
/// `config.plane_voxel`; `period` turns point times into sweep phases (phase 1, the sweep end,
/// when the scan has no time channel: nothing to compensate with).
pub fn extract(scan: &PointCloud, period: f32, config: &FeatureConfig) -> Features {
    let times = scan.time.as_deref();
    let inv = 1.0 / config.plane_voxel;
    let mut voxels: FxHashMap<VoxelKey, Vec<u32>> = FxHashMap::default();
    for (i, p) in scan.points.iter().enumerate() {
        let r = p.coords.norm();
        if r >= config.min_range && r <= config.max_range {
            voxels.entry(VoxelKey::of(p, inv)).or_default().push(i as u32);
        }
    }
    let mut cells: Vec<(VoxelKey, Vec<u32>)> = voxels.into_iter().filter(|(_, v)| v.len() >= MIN_POINTS).collect();
    // The hash map's order is arbitrary: sort, so that the features come out the same every run.
    cells.sort_unstable_by_key(|(k, _)| k.0);
    let shaped: Vec<(Shape, u32, f32)> = cells.par_iter().filter_map(|(_, idx)| classify(&scan.points, idx)).collect();
    let mut out = Features::default();
    for (n, (shape, i, smoothness)) in shaped.into_iter().enumerate() {
        let phase = times.map_or(1.0, |t| (t[i as usize] / period).clamp(0.0, 1.0));
        // No scan lines: every feature is its own "line", so the solver's check that a
        // neighbourhood spans several scan lines always passes.
        let feature = Feature { point: scan.points[i as usize], phase, smoothness, ring: n as u16 };
        match shape {
            Shape::Plane => out.planes.push(feature),
            Shape::Line => out.edges.push(feature),
        }
    }
    out
}

/// What a voxel's points look like.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Shape {
    Plane,
    Line,
}

/// The voxel's shape, the index of its point nearest the centroid and a smoothness for the
/// solver's weights (planes: their surface variation, near 0, full weight; lines: 1, the weight a
/// sharp ring edge gets).
fn classify(points: &[Point3<f32>], idx: &[u32]) -> Option<(Shape, u32, f32)> {
    let (mean, cov) = mean_covariance(idx.iter().map(|&i| points[i as usize].coords.cast::<f64>()));
    let e = symmetric_eigen3(&cov);
    let [l0, l1, l2] = [e.values[0], e.values[1], e.values[2]];
    let sum = l0 + l1 + l2;
    // Also refuses NaN sums.
    if sum.is_nan() || sum <= 0.0 {
        return None;
    }
    let (shape, smoothness) = if l0 <= MAX_SURFACE_VARIATION * sum && l1 >= MIN_SPREAD * l2 {
        (Shape::Plane, (l0 / sum) as f32)
    } else if l2 > LINE_RATIO * l1 {
        (Shape::Line, 1.0)
    } else {
        return None;
    };
    let centre = mean.cast::<f32>();
    let nearest = idx.iter().copied().min_by(|&a, &b| {
        let d = |i: u32| (points[i as usize].coords - centre).norm_squared();
        d(a).total_cmp(&d(b))
    })?;
    Some((shape, nearest, smoothness))
}

#[cfg(test)]
mod tests {
    use super::*;
    use cloud::Channels;

    #[test]
    fn walls_give_planes_and_a_pole_gives_edges_whatever_the_point_order() {
        // A floor patch, a wall and a thin pole, points in a scrambled order, no ring channel.
        let mut points = Vec::new();
        for i in 0..40 {
            for j in 0..40 {
                let (a, b) = (i as f32 * 0.05, j as f32 * 0.05);
                points.push(Point3::new(3.0 + a, -1.0 + b, -0.5));
                points.push(Point3::new(6.0, -1.0 + a, -0.5 + b));
            }
        }
        for i in 0..200 {
            points.push(Point3::new(4.5, 3.0, -0.5 + i as f32 * 0.01));
        }
        let mut rng = testkit::Rng::new(7);
        for i in (1..points.len()).rev() {
            points.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
        }
        let mut scan = PointCloud::with_capacity(points.len(), Channels::default());
        scan.points = points;
        let config = FeatureConfig { plane_voxel: 0.6, min_range: 0.5, ..FeatureConfig::default() };
        let f = extract(&scan, 0.1, &config);
        assert!(f.planes.len() >= 8, "{} planes", f.planes.len());
        for p in &f.planes {
            assert!((p.point.z + 0.5).abs() < 1e-6 || (p.point.x - 6.0).abs() < 1e-6, "{:?}", p.point);
            assert_eq!(p.phase, 1.0);
        }
        assert!(!f.edges.is_empty());
        assert!(f.edges.iter().all(|e| (e.point.x - 4.5).abs() < 1e-6 && (e.point.y - 3.0).abs() < 1e-6));
    }
}
