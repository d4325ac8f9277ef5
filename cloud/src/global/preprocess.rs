//! Step 1 — preprocessing: drop invalid points, voxel-grid downsampling, outlier removal.
//!
//! Follows map_merge_3d (paper §4, "downSample" then "removeOutliers"): a voxel grid brings both maps
//! to the registration resolution, then an outlier filter drops isolated returns that would
//! otherwise produce unstable normals and spurious keypoints. Downsampling comes first on purpose:
//! afterwards the density is bounded, so neighbour counts and mean neighbour distances mean the same
//! thing everywhere in the map, and the filter runs on far fewer points. Unlike map_merge_3d, a cloud
//! that the filters empty (or nearly) is reported as an error instead of crashing a later step.

use rayon::prelude::*;
use rustc_hash::FxHashMap;

use super::error::FeatureError;
use crate::PointCloud;
use crate::kdtree::KdTree;
use crate::voxel::VoxelKey;

/// How isolated points are recognised and removed after downsampling.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum OutlierFilter {
    /// Keep every point.
    None,
    /// PCL's StatisticalOutlierRemoval: drop points whose mean distance to their `k` nearest
    /// neighbours exceeds the mean of that quantity over the cloud by more than `std_ratio` standard
    /// deviations. Scale-free, so one setting suits indoor and outdoor maps.
    Statistical {
        /// Neighbours averaged per point.
        k: usize,
        /// Allowed deviation above the mean, in standard deviations.
        std_ratio: f32,
    },
    /// PCL's RadiusOutlierRemoval (map_merge_3d's choice): drop points with fewer than
    /// `min_neighbours` other points within `radius` metres.
    Radius {
        /// Search radius, metres.
        radius: f32,
        /// Other points required within the radius.
        min_neighbours: usize,
    },
}

/// Settings of step 1.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PreprocessConfig {
    /// Voxel edge, metres: the registration resolution (outdoor 0.4, indoor 0.1).
    pub voxel_size: f32,
    /// After the voxel grid, points closer than this to an earlier kept point are dropped, metres
    /// (default 0.2 = voxel / 2; 0 disables). A surface lying on a grid boundary (a floor at z = 0)
    /// is otherwise split into two layers of centroids a centimetre apart, doubling its weight in
    /// every histogram; the thinning makes the density independent of where the grid falls.
    pub min_spacing: f32,
    /// Outlier filter applied to the downsampled cloud (default: statistical, k = 8, 2.5 σ).
    pub outliers: OutlierFilter,
    /// Fewer points than this after filtering is an error (default 50): nothing reliable can be
    /// matched on a handful of points.
    pub min_points: usize,
}

impl Default for PreprocessConfig {
    fn default() -> Self {
        Self {
            voxel_size: 0.4,
            min_spacing: 0.2,
            outliers: OutlierFilter::Statistical { k: 8, std_ratio: 2.5 },
            min_points: 50,
        }
    }
}

impl PreprocessConfig {
    /// Checks that the sizes are positive and finite.
    pub fn validate(&self) -> Result<(), FeatureError> {
        if !(self.voxel_size > 0.0 && self.voxel_size.is_finite()) {
            return Err(FeatureError::InvalidConfig("preprocess.voxel_size must be positive and finite"));
        }
        if !(self.min_spacing >= 0.0 && self.min_spacing.is_finite()) {
            return Err(FeatureError::InvalidConfig("preprocess.min_spacing must be non-negative and finite"));
        }
        match self.outliers {
            OutlierFilter::Statistical { k, std_ratio } if k == 0 || !std_ratio.is_finite() => {
                Err(FeatureError::InvalidConfig("statistical outlier filter needs k > 0 and a finite std_ratio"))
            }
            OutlierFilter::Radius { radius, .. } if !(radius > 0.0 && radius.is_finite()) => {
                Err(FeatureError::InvalidConfig("radius outlier filter needs a positive finite radius"))
            }
            _ => Ok(()),
        }
    }
}

/// Step 1: finite points only, downsampled to `voxel_size`, isolated points removed.
pub fn preprocess(cloud: &PointCloud, config: &PreprocessConfig) -> Result<PointCloud, FeatureError> {
    config.validate()?;
    let mut finite = PointCloud::from_points(cloud.points.clone());
    finite.retain_finite();
    check_size(&finite, "dropping non-finite points", config.min_points)?;
    let down = crate::voxel::downsample(&finite, config.voxel_size)
        .map_err(|_| FeatureError::InvalidConfig("preprocess.voxel_size must be positive and finite"))?;
    let thinned = thin(&down, config.min_spacing);
    check_size(&thinned, "voxel downsampling", config.min_points)?;
    let kept = remove_outliers(&thinned, &config.outliers);
    check_size(&kept, "outlier removal", config.min_points)?;
    Ok(kept)
}

/// Greedy minimum-distance thinning: points in order, each kept unless a kept point lies within
/// `spacing`.
///
/// Kept points go into a hash grid of cell `2 × spacing`: a point closer than `spacing` to another
/// can only lie in the same cell or in the neighbours towards the point's nearer faces, 8 cells
/// instead of 27. Each cell chains its kept points through `next`, so no cell allocates.
pub fn thin(cloud: &PointCloud, spacing: f32) -> PointCloud {
    if spacing.is_nan() || spacing <= 0.0 {
        return cloud.clone();
    }
    let inv = 0.5 / spacing;
    let mut head: FxHashMap<VoxelKey, u32> = FxHashMap::default();
    head.reserve(cloud.len());
    let mut next = vec![u32::MAX; cloud.len()];
    let mut keep = Vec::with_capacity(cloud.len());
    for (i, p) in cloud.points.iter().enumerate() {
        let VoxelKey(cell) = VoxelKey::of(p, inv);
        // Per axis, the neighbour on the side of the nearer face (the upper half of the cell looks up).
        let side: [i32; 3] = std::array::from_fn(|a| if p[a] * inv - cell[a] as f32 >= 0.5 { 1 } else { -1 });
        let crowded = (0..8).any(|corner: usize| {
            let key = VoxelKey(std::array::from_fn(|a| cell[a] + side[a] * ((corner >> a) & 1) as i32));
            let mut j = head.get(&key).copied().unwrap_or(u32::MAX);
            while j != u32::MAX {
                if (cloud.points[j as usize] - p).norm_squared() < spacing * spacing {
                    return true;
                }
                j = next[j as usize];
            }
            false
        });
        if !crowded {
            let key = VoxelKey(cell);
            next[i] = head.insert(key, i as u32).unwrap_or(u32::MAX);
            keep.push(i);
        }
    }
    cloud.select(&keep)
}

/// The cloud without the points `filter` considers outliers.
pub fn remove_outliers(cloud: &PointCloud, filter: &OutlierFilter) -> PointCloud {
    let keep: Vec<usize> = match *filter {
        OutlierFilter::None => return cloud.clone(),
        OutlierFilter::Statistical { k, std_ratio } => statistical_inliers(cloud, k, std_ratio),
        OutlierFilter::Radius { radius, min_neighbours } => radius_inliers(cloud, radius, min_neighbours),
    };
    cloud.select(&keep)
}

/// Indices of points whose mean k-NN distance is within `std_ratio` σ of the cloud's mean.
fn statistical_inliers(cloud: &PointCloud, k: usize, std_ratio: f32) -> Vec<usize> {
    let tree = KdTree::from_points(&cloud.points);
    // k + 1: the query point finds itself first.
    let mean_dist: Vec<f64> = cloud
        .xyz()
        .par_iter()
        .map(|q| {
            let nn = tree.knn(q, k + 1);
            let others = nn.len().saturating_sub(1).max(1) as f64;
            nn.iter().skip(1).map(|n| f64::from(n.dist_sq).sqrt()).sum::<f64>() / others
        })
        .collect();
    let n = mean_dist.len().max(1) as f64;
    let mean = mean_dist.iter().sum::<f64>() / n;
    let std = (mean_dist.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / n).sqrt();
    let limit = mean + f64::from(std_ratio) * std;
    (0..mean_dist.len()).filter(|&i| mean_dist[i] <= limit).collect()
}

/// Indices of points with at least `min_neighbours` other points within `radius`.
fn radius_inliers(cloud: &PointCloud, radius: f32, min_neighbours: usize) -> Vec<usize> {
    let tree = KdTree::from_points(&cloud.points);
    let counts: Vec<usize> = cloud.xyz().par_iter().map(|q| tree.within(q, radius).len().saturating_sub(1)).collect();
    (0..counts.len()).filter(|&i| counts[i] >= min_neighbours).collect()
}

/// An error when fewer than `needed` points survived `stage`.
fn check_size(cloud: &PointCloud, stage: &'static str, needed: usize) -> Result<(), FeatureError> {
    if cloud.len() < needed.max(1) {
        return Err(FeatureError::TooFewPoints { stage, points: cloud.len(), needed: needed.max(1) });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    fn grid_with_stray() -> PointCloud {
        let mut pts: Vec<Point3<f32>> =
            (0..400).map(|i| Point3::new((i % 20) as f32 * 0.1, (i / 20) as f32 * 0.1, 0.0)).collect();
        pts.push(Point3::new(50.0, 50.0, 50.0));
        PointCloud::from_points(pts)
    }

    #[test]
    fn thinning_keeps_what_the_greedy_pairwise_rule_keeps() {
        // Points on both sides of cell boundaries and of zero, denser than the spacing.
        let mut rng = testkit::Rng::new(0x2545_f491_4f6c_dd1d);
        let mut next = move || rng.f32() * 2.0 - 1.0;
        let pts: Vec<Point3<f32>> = (0..3000).map(|_| Point3::new(next(), next(), 0.3 * next())).collect();
        let spacing = 0.07;
        let mut kept: Vec<Point3<f32>> = Vec::new();
        for p in &pts {
            if kept.iter().all(|q| (q - p).norm_squared() >= spacing * spacing) {
                kept.push(*p);
            }
        }
        let thinned = thin(&PointCloud::from_points(pts), spacing);
        assert!(kept.len() > 500 && kept.len() < 2500, "{}", kept.len());
        assert_eq!(thinned.points, kept);
    }

    #[test]
    fn both_filters_drop_the_stray_point() {
        let c = grid_with_stray();
        for f in [
            OutlierFilter::Statistical { k: 8, std_ratio: 2.0 },
            OutlierFilter::Radius { radius: 0.25, min_neighbours: 3 },
        ] {
            let kept = remove_outliers(&c, &f);
            assert_eq!(kept.len(), 400, "{f:?}");
            assert!(kept.points.iter().all(|p| p.x < 10.0));
        }
    }

    #[test]
    fn emptied_cloud_is_an_error() {
        let c = grid_with_stray();
        let config = PreprocessConfig {
            voxel_size: 0.05,
            min_spacing: 0.0,
            outliers: OutlierFilter::Radius { radius: 0.01, min_neighbours: 5 },
            min_points: 10,
        };
        assert!(matches!(preprocess(&c, &config), Err(FeatureError::TooFewPoints { stage: "outlier removal", .. })));
    }
}
