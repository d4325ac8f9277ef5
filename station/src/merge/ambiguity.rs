//! Perceptual aliasing: is there a second, different transform that the features support almost as
//! well as the chosen one?
//!
//! Repetitive places (identical rack rows, identical corridors) make the overlap and the inlier
//! ratio of a *wrong* transform look as good as those of a right one: two sealed halls of the same
//! racks align "perfectly" one row off. What gives them away is that the evidence is not unique:
//! the features support several distinct transforms. After the chosen model, RANSAC runs again on
//! the correspondences that disagree with it; if the best such model lies far from the chosen one
//! and gathers a large share of its inliers, the pair is ambiguous and refused.

use nalgebra::{Isometry3, Point3};

use crate::pairwise::{MapFeatures, PairwiseConfig, matching, ransac};

/// The strongest hypothesis distinct from the chosen one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RunnerUp {
    /// Maps source points into the target frame.
    pub transform: Isometry3<f64>,
    /// Its RANSAC inliers.
    pub inliers: usize,
}

/// Correspondences farther than this many RANSAC inlier distances from the chosen model count as
/// disagreeing with it (the margin keeps near-inliers of the chosen model out of the rerun).
const EXCLUSION: f64 = 3.0;

/// The best RANSAC model on the correspondences that disagree with `chosen`, if one exists and lies
/// at least `min_distance` metres from `chosen` (at the source keypoints).
pub fn runner_up(
    source: &MapFeatures,
    target: &MapFeatures,
    chosen: &Isometry3<f64>,
    min_distance: f64,
    config: &PairwiseConfig,
) -> Option<RunnerUp> {
    let matches = matching::reciprocal_matches(&source.descriptors, &target.descriptors, config.matching.k);
    let limit = EXCLUSION * config.ransac.inlier_distance;
    let (src, tgt): (Vec<Point3<f64>>, Vec<Point3<f64>>) = matches
        .iter()
        .map(|c| (source.keypoint(c.source).cast::<f64>(), target.keypoint(c.target).cast::<f64>()))
        .filter(|(s, t)| (chosen * s - t).norm() > limit)
        .unzip();
    let model = ransac::ransac(&src, &tgt, &config.ransac)?;
    let keypoints = source.keypoint_positions();
    let distinct = mean_displacement(&keypoints, chosen, &model.transform) >= min_distance;
    distinct.then_some(RunnerUp { transform: model.transform, inliers: model.inliers.len() })
}

/// Mean distance between where two transforms put the same points: how different they are on the
/// map itself (a rotation about a far-away origin is not "small").
pub fn mean_displacement(points: &[Point3<f32>], a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let sum: f64 = points.iter().map(|p| (a * p.cast::<f64>() - b * p.cast::<f64>()).norm()).sum();
    sum / points.len() as f64
}
