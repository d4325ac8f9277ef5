//! Step 6 — RANSAC over 3-point samples with pre-rejection, then an SVD (Umeyama) refit.
//!
//! Fischler & Bolles' RANSAC on the putative correspondences, with the two accelerations of Open3D's
//! `registration_ransac_based_on_feature_matching`: a sample of three correspondences is rejected
//! before any model is fitted unless its source and target triangles have similar edge lengths
//! (a rigid motion preserves them; `CorrespondenceCheckerBasedOnEdgeLength`, similarity 0.9), and
//! the number of iterations adapts to the best inlier ratio `w` found so far,
//! `N = log(1 − p) / log(1 − w³)`. Each surviving sample is fitted with Umeyama's closed form and
//! scored by its inlier count (sum of squared residuals breaks ties). The winner is refitted on all
//! its inliers, re-scored, and refitted again until the inlier set stops changing.
//!
//! Iterations run in rounds of independent chunks, each with its own SplitMix64 stream derived from
//! the seed and the chunk number, so the result is reproducible whatever the thread count.

use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

use super::error::FeatureError;
use crate::alignment::umeyama;

/// Settings of step 6.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RansacConfig {
    /// A correspondence is an inlier when the transformed source keypoint lies within this distance
    /// of its target keypoint, metres (default 1.0 = 2.5 × voxel; keypoints are voxel centroids
    /// picked independently in each map, so the same corner can sit a voxel apart).
    pub inlier_distance: f64,
    /// Minimum ratio shorter/longer of matching triangle edges (default 0.9, Open3D's).
    pub edge_similarity: f64,
    /// Samples with an edge shorter than this are skipped, metres (default 1.0): a tiny triangle
    /// fixes the rotation poorly.
    pub min_edge: f64,
    /// Probability of drawing at least one all-inlier sample (default 0.999).
    pub confidence: f64,
    /// Iteration cap (default 200 000).
    pub max_iterations: usize,
    /// Seed of the sampler (default 0x5EED).
    pub seed: u64,
}

impl Default for RansacConfig {
    fn default() -> Self {
        Self {
            inlier_distance: 1.0,
            edge_similarity: 0.9,
            min_edge: 1.0,
            confidence: 0.999,
            max_iterations: 200_000,
            seed: 0x5EED,
        }
    }
}

impl RansacConfig {
    /// Checks distances and probabilities.
    pub fn validate(&self) -> Result<(), FeatureError> {
        let ok = self.inlier_distance > 0.0
            && self.inlier_distance.is_finite()
            && self.edge_similarity > 0.0
            && self.edge_similarity <= 1.0
            && self.min_edge >= 0.0
            && self.confidence > 0.0
            && self.confidence < 1.0
            && self.max_iterations > 0;
        if !ok {
            return Err(FeatureError::InvalidConfig(
                "ransac needs inlier_distance > 0, edge_similarity in (0, 1], confidence in (0, 1), max_iterations > 0",
            ));
        }
        Ok(())
    }
}

/// The best model: transform (source → target), inlier indices into the correspondences, iterations.
#[derive(Clone, Debug, PartialEq)]
pub struct RansacModel {
    /// Maps source points into the target frame.
    pub transform: Isometry3<f64>,
    /// Indices of the inlier correspondences.
    pub inliers: Vec<usize>,
    /// Samples drawn.
    pub iterations: usize,
}

/// A scored hypothesis: inlier count, sum of squared inlier residuals, transform.
#[derive(Clone, Copy)]
struct Hypothesis {
    inliers: usize,
    sse: f64,
    transform: Isometry3<f64>,
}

impl Hypothesis {
    fn beats(&self, other: &Option<Hypothesis>) -> bool {
        other.is_none_or(|o| self.inliers > o.inliers || (self.inliers == o.inliers && self.sse < o.sse))
    }
}

/// SplitMix64 (Steele, Lea & Flood 2014): tiny, fast, and good enough to draw samples.
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `0..n` (Lemire's multiply-shift; the bias is below 2⁻³² for our sizes).
    fn below(&mut self, n: usize) -> usize {
        (((self.next_u64() >> 32) * n as u64) >> 32) as usize
    }
}

/// Step 6: the rigid transform best supported by the pairs `(source[i], target[i])`, or `None`
/// when no sample passes the checks.
pub fn ransac(source: &[Point3<f64>], target: &[Point3<f64>], config: &RansacConfig) -> Option<RansacModel> {
    const CHUNKS_PER_ROUND: usize = 16;
    const SAMPLES_PER_CHUNK: usize = 512;
    let n = source.len().min(target.len());
    if n < 3 {
        return None;
    }
    let mut best: Option<Hypothesis> = None;
    let mut iterations = 0;
    let mut round = 0u64;
    while iterations < required_iterations(best.map_or(0, |b| b.inliers), n, config) {
        let found = (0..CHUNKS_PER_ROUND as u64)
            .into_par_iter()
            .map(|c| {
                let mut rng = SplitMix64(
                    config.seed ^ (round * CHUNKS_PER_ROUND as u64 + c + 1).wrapping_mul(0xD1B5_4A32_D192_ED03),
                );
                run_chunk(source, target, config, &mut rng, SAMPLES_PER_CHUNK)
            })
            .collect::<Vec<_>>();
        for h in found.into_iter().flatten() {
            if h.beats(&best) {
                best = Some(h);
            }
        }
        iterations += CHUNKS_PER_ROUND * SAMPLES_PER_CHUNK;
        round += 1;
    }
    let best = best?;
    let (transform, inliers) = refit(source, target, best.transform, config.inlier_distance);
    Some(RansacModel { transform, inliers, iterations })
}

/// Iterations needed for `confidence` given the best inlier count so far, capped.
fn required_iterations(inliers: usize, n: usize, config: &RansacConfig) -> usize {
    let w = inliers as f64 / n as f64;
    let all_inlier = w.powi(3);
    if all_inlier <= 0.0 {
        return config.max_iterations;
    }
    if all_inlier >= 1.0 {
        return 1;
    }
    let needed = (1.0 - config.confidence).ln() / (1.0 - all_inlier).ln();
    (needed.ceil() as usize).min(config.max_iterations)
}

/// `samples` random hypotheses; returns the best one.
fn run_chunk(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    config: &RansacConfig,
    rng: &mut SplitMix64,
    samples: usize,
) -> Option<Hypothesis> {
    let n = source.len();
    let mut best = None;
    for _ in 0..samples {
        let s = [rng.below(n), rng.below(n), rng.below(n)];
        if s[0] == s[1] || s[0] == s[2] || s[1] == s[2] || !edges_consistent(source, target, &s, config) {
            continue;
        }
        let (src, tgt) = (s.map(|i| source[i]), s.map(|i| target[i]));
        let Ok(transform) = umeyama(&src, &tgt) else { continue };
        let h = score(source, target, &transform, config.inlier_distance);
        if h.beats(&best) {
            best = Some(h);
        }
    }
    best
}

/// Pre-rejection: every edge of the source triangle matches its target edge within the similarity,
/// and is long enough to constrain the rotation.
fn edges_consistent(source: &[Point3<f64>], target: &[Point3<f64>], s: &[usize; 3], config: &RansacConfig) -> bool {
    [(0, 1), (1, 2), (2, 0)].iter().all(|&(a, b)| {
        let ds = (source[s[a]] - source[s[b]]).norm();
        let dt = (target[s[a]] - target[s[b]]).norm();
        ds >= config.min_edge && dt >= config.min_edge && ds.min(dt) >= config.edge_similarity * ds.max(dt)
    })
}

/// Inlier count and squared-residual sum of a transform.
fn score(source: &[Point3<f64>], target: &[Point3<f64>], t: &Isometry3<f64>, inlier_distance: f64) -> Hypothesis {
    let limit = inlier_distance * inlier_distance;
    let (inliers, sse) = source.iter().zip(target).fold((0, 0.0), |(count, sse), (s, q)| {
        let r = (t * s - q).norm_squared();
        if r <= limit { (count + 1, sse + r) } else { (count, sse) }
    });
    Hypothesis { inliers, sse, transform: *t }
}

/// Indices of the inliers of `t`.
fn inliers_of(source: &[Point3<f64>], target: &[Point3<f64>], t: &Isometry3<f64>, inlier_distance: f64) -> Vec<usize> {
    let limit = inlier_distance * inlier_distance;
    (0..source.len()).filter(|&i| (t * source[i] - target[i]).norm_squared() <= limit).collect()
}

/// Umeyama on all inliers, repeated until the inlier set is stable (at most 10 rounds).
fn refit(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    mut transform: Isometry3<f64>,
    inlier_distance: f64,
) -> (Isometry3<f64>, Vec<usize>) {
    let mut inliers = inliers_of(source, target, &transform, inlier_distance);
    for _ in 0..10 {
        let src: Vec<Point3<f64>> = inliers.iter().map(|&i| source[i]).collect();
        let tgt: Vec<Point3<f64>> = inliers.iter().map(|&i| target[i]).collect();
        let Ok(next) = umeyama(&src, &tgt) else { break };
        let next_inliers = inliers_of(source, target, &next, inlier_distance);
        // Keep the refit only if it does not lose support.
        if next_inliers.len() < inliers.len() {
            break;
        }
        let stable = next_inliers == inliers;
        (transform, inliers) = (next, next_inliers);
        if stable {
            break;
        }
    }
    (transform, inliers)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn finds_the_motion_among_mostly_wrong_pairs() {
        let truth = Isometry3::new(Vector3::new(20.0, -3.0, 0.5), Vector3::new(0.0, 0.0, 1.4));
        let mut rng = SplitMix64(42);
        let mut unit = || (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        let mut source = Vec::new();
        let mut target = Vec::new();
        for i in 0..400 {
            let p = Point3::new(unit() * 40.0, unit() * 40.0, unit() * 5.0);
            source.push(p);
            // 10% true pairs with 5 cm noise, the rest random.
            target.push(if i % 10 == 0 {
                truth * p + Vector3::new(unit() - 0.5, unit() - 0.5, unit() - 0.5) * 0.1
            } else {
                Point3::new(unit() * 60.0, unit() * 60.0, unit() * 5.0)
            });
        }
        let model = ransac(&source, &target, &RansacConfig::default()).unwrap();
        testkit::assert_pose_close!(&model.transform, &truth, 0.05, 0.2);
        assert!(model.inliers.len() >= 40);
        assert!(model.inliers.iter().all(|i| i % 10 == 0 || model.inliers.len() < 60));
    }

    #[test]
    fn too_few_pairs_give_none() {
        let p = [Point3::origin(), Point3::new(1.0, 0.0, 0.0)];
        assert!(ransac(&p, &p, &RansacConfig::default()).is_none());
    }

    #[test]
    fn iteration_bound_follows_the_formula() {
        let c = RansacConfig::default();
        // w = 0.5: log(0.001) / log(1 - 0.125) = 51.7.
        assert_eq!(required_iterations(50, 100, &c), 52);
        assert_eq!(required_iterations(0, 100, &c), c.max_iterations);
    }
}
