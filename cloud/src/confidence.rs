//! Confidence of an alignment: map_merge_3d's score and an overlap-aware one. The station scores
//! map merges with it, the robots their loop closures.
//!
//! - **Fitness** (map_merge_3d, `transformScore` via PCL's `TransformationValidationEuclidean`):
//!   `1 / mean(d²)` over the source points whose nearest target point, after the transform, is
//!   within `max_correspondence_distance` (`d² ≤ max²`); 0 when no point qualifies. It measures how
//!   tight the overlapping part is, not how much overlaps: two unrelated maps whose ground planes
//!   coincide still score well, which is why it is not used alone.
//! - **Overlap** `o`: the share of source points with a target point within `overlap_distance`.
//! - **Score** `s = √(o · r)`, the geometric mean of the overlap and the RANSAC inlier ratio `r`
//!   (inliers / correspondences). Both factors lie in [0, 1] and each catches what the other misses:
//!   a wrong transform that lines up a few planes has overlap but few feature inliers; a handful of
//!   consistent matches on a small common part has inliers but little overlap. The geometric mean
//!   makes the score low as soon as either is, and keeps it in [0, 1].

use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

use crate::global::FeatureError;
use crate::kdtree::{KdTree, gate_radius};

/// Settings of the confidence scores and of the acceptance test.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConfidenceConfig {
    /// Cut-off of the fitness score, metres (default 2.0; map_merge_3d: 2 × inlier threshold).
    pub max_correspondence_distance: f32,
    /// A source point overlaps when a target point lies within this distance, metres (default 0.6
    /// = 1.5 × voxel).
    pub overlap_distance: f32,
    /// Fewer RANSAC inliers than this means no reliable alignment (default 15).
    pub min_inliers: usize,
    /// A smaller overlap share means no reliable alignment (default 0.1).
    pub min_overlap: f64,
    /// A lower combined score means no reliable alignment (default 0.12: on synthetic streets the
    /// true pair scores 0.19, an unrelated but similar-looking street 0.06-0.08; the KITTI revisit
    /// scores 0.44).
    pub min_score: f64,
}

impl Default for ConfidenceConfig {
    fn default() -> Self {
        Self {
            max_correspondence_distance: 2.0,
            overlap_distance: 0.6,
            min_inliers: 15,
            min_overlap: 0.1,
            min_score: 0.12,
        }
    }
}

impl ConfidenceConfig {
    /// Checks the distances.
    pub fn validate(&self) -> Result<(), FeatureError> {
        let ok = |d: f32| d > 0.0 && d.is_finite();
        if !ok(self.max_correspondence_distance)
            || !ok(self.overlap_distance)
            || !self.min_overlap.is_finite()
            || !self.min_score.is_finite()
        {
            return Err(FeatureError::InvalidConfig("confidence distances must be positive and finite"));
        }
        Ok(())
    }
}

/// The confidence scores of one alignment.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Confidence {
    /// map_merge_3d's `1 / mean(d²)` over source points within the correspondence distance, 1/m².
    pub fitness: f64,
    /// Share of source points with a target point within the overlap distance, in [0, 1].
    pub overlap: f64,
    /// `√(overlap · inlier_ratio)`, in [0, 1].
    pub score: f64,
}

/// Both scores for `transform` (source → target) over the preprocessed clouds.
pub fn confidence(
    source: &[Point3<f32>],
    target: &KdTree,
    transform: &Isometry3<f64>,
    inlier_ratio: f64,
    config: &ConfidenceConfig,
) -> Confidence {
    let t = transform.cast::<f32>();
    let max_sq = config.max_correspondence_distance.powi(2);
    let overlap_sq = config.overlap_distance.powi(2);
    // Nothing farther than both distances counts: the search need not look farther.
    let reach = gate_radius(config.max_correspondence_distance.max(config.overlap_distance));
    // Per point: (d² if within the fitness cut-off, overlapping?).
    let (sum, count, overlapping) = source
        .par_iter()
        .map(|p| {
            let q = t * p;
            let Some(nn) = target.nearest_within(&[q.x, q.y, q.z], reach) else { return (0.0, 0, 0) };
            let within = nn.dist_sq <= max_sq;
            (
                if within { f64::from(nn.dist_sq) } else { 0.0 },
                usize::from(within),
                usize::from(nn.dist_sq <= overlap_sq),
            )
        })
        .reduce(|| (0.0, 0, 0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
    // A perfect fit (mean d² = 0) would give infinity; 1e-12 m² is far below any sensor's noise.
    let fitness = if count == 0 { 0.0 } else { 1.0 / (sum / count as f64).max(1e-12) };
    let overlap = if source.is_empty() { 0.0 } else { overlapping as f64 / source.len() as f64 };
    let score = (overlap * inlier_ratio.clamp(0.0, 1.0)).sqrt();
    Confidence { fitness, overlap, score }
}
