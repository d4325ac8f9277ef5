//! Steps 5-7 on two clouds' features: descriptor matches, the RANSAC transform and its polish.

use std::time::Duration;

use nalgebra::{Isometry3, Point3};

use super::config::GlobalConfig;
use super::features::Features;
use super::matching::{self, Correspondence};
use super::{polish, ransac};
use crate::stopwatch::Stopwatch;

/// RANSAC found no model: fewer than 3 correspondences, or no sample passed the checks.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
#[error("no transform: {correspondences} correspondences and no consistent sample")]
pub struct NoModel {
    /// Reciprocal correspondences found.
    pub correspondences: usize,
}

/// Wall time of steps 5-7.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct EstimateTiming {
    /// Step 5.
    pub matching: Duration,
    /// Step 6.
    pub ransac: Duration,
    /// Step 7.
    pub polish: Duration,
}

impl EstimateTiming {
    /// Sum of the three steps.
    pub fn total(&self) -> Duration {
        self.matching + self.ransac + self.polish
    }
}

/// The transform steps 5-7 found and what supports it.
#[derive(Clone, Debug, PartialEq)]
pub struct Estimate {
    /// Maps SOURCE points into the TARGET frame (after step 7).
    pub transform: Isometry3<f64>,
    /// The RANSAC + Umeyama transform before the polish.
    pub coarse_transform: Isometry3<f64>,
    /// Reciprocal descriptor correspondences RANSAC started from.
    pub matches: Vec<Correspondence>,
    /// Indices into `matches` of the RANSAC inliers.
    pub inliers: Vec<usize>,
    /// Samples RANSAC drew.
    pub ransac_iterations: usize,
    /// Time per step.
    pub timing: EstimateTiming,
}

impl Estimate {
    /// Share of the correspondences that are inliers, in [0, 1].
    pub fn inlier_ratio(&self) -> f64 {
        self.inliers.len() as f64 / self.matches.len() as f64
    }

    /// The inlier correspondences themselves.
    pub fn inlier_matches(&self) -> Vec<Correspondence> {
        self.inliers.iter().map(|&i| self.matches[i]).collect()
    }
}

/// Steps 5-7: the transform mapping `source` into the frame of `target`.
pub fn estimate(source: &Features, target: &Features, config: &GlobalConfig) -> Result<Estimate, NoModel> {
    estimate_excluding(source, target, config, &[], 0.0, None)
}

/// Steps 5-7 on the correspondences that disagree with every transform of `excluded` (the source
/// keypoint lands farther than `margin` metres from its target keypoint): the next distinct
/// hypothesis after those, when they were found wrong (sequential RANSAC). `matches` and the
/// inlier ratio still count every correspondence, so that hypotheses are scored alike.
///
/// With `around`, only the keypoints near the place the two clouds are believed to share are
/// matched (see [`Around`]); `matches` and the inlier ratio then count the correspondences there.
pub fn estimate_excluding(
    source: &Features,
    target: &Features,
    config: &GlobalConfig,
    excluded: &[Isometry3<f64>],
    margin: f64,
    around: Option<&Around>,
) -> Result<Estimate, NoModel> {
    let mut timing = EstimateTiming::default();
    let mut watch = Stopwatch::start();
    let matches = match around {
        None => matching::reciprocal_matches(&source.descriptors, &target.descriptors, config.matching.k),
        Some(around) => around.matches(source, target, config.matching.k),
    };
    timing.matching = watch.lap();
    let (src, tgt) = keypoint_pairs(source, target, &matches);
    let kept: Vec<usize> =
        (0..matches.len()).filter(|&i| excluded.iter().all(|e| (e * src[i] - tgt[i]).norm() > margin)).collect();
    let (src, tgt): (Vec<Point3<f64>>, Vec<Point3<f64>>) = kept.iter().map(|&i| (src[i], tgt[i])).unzip();
    let model = ransac::ransac(&src, &tgt, &config.ransac);
    timing.ransac = watch.lap();
    let model = model.ok_or(NoModel { correspondences: matches.len() })?;
    let transform = polish::polish(&source.surfels, &target.surfels, &model.transform, &config.polish);
    timing.polish = watch.lap();
    Ok(Estimate {
        transform,
        coarse_transform: model.transform,
        inliers: model.inliers.iter().map(|&k| kept[k]).collect(),
        matches,
        ransac_iterations: model.iterations,
        timing,
    })
}

/// Where two clouds are believed to overlap: a place each seems to share with the other (two
/// keyframes whose place descriptors look alike), in each cloud's own frame, and how far around it
/// to look.
///
/// Two large maps that share a small part (robots that meet at one door) give few correct
/// correspondences among many wrong ones, and RANSAC's best model can be a look-alike elsewhere;
/// around the shared place the correct ones are a large share. Matching there is also cheaper:
/// the descriptor distances are a product of the two keypoint counts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Around {
    /// The place in the source cloud's frame.
    pub source: Point3<f32>,
    /// The place in the target cloud's frame.
    pub target: Point3<f32>,
    /// Keypoints farther than this from the place are left out, metres (the station uses the
    /// place descriptor's range: what the two keyframes were compared on).
    pub radius: f32,
}

impl Around {
    /// Step 5 on the keypoints near the place: reciprocal matches among them only, indexed into
    /// the clouds' whole keypoint lists.
    fn matches(&self, source: &Features, target: &Features, k: usize) -> Vec<Correspondence> {
        let (s, t) = (self.keypoints_near(source, &self.source), self.keypoints_near(target, &self.target));
        let descriptors = |f: &Features, near: &[usize]| near.iter().map(|&i| f.descriptors[i]).collect::<Vec<_>>();
        matching::reciprocal_matches(&descriptors(source, &s), &descriptors(target, &t), k)
            .into_iter()
            .map(|c| Correspondence { source: s[c.source], target: t[c.target], ..c })
            .collect()
    }

    /// Positions in the keypoint list of the keypoints within the radius of `place`.
    fn keypoints_near(&self, features: &Features, place: &Point3<f32>) -> Vec<usize> {
        let r2 = self.radius * self.radius;
        (0..features.keypoints.len()).filter(|&k| (features.keypoint(k) - place).norm_squared() <= r2).collect()
    }
}

/// The keypoint positions each correspondence pairs, source and target, in double precision.
pub fn keypoint_pairs(
    source: &Features,
    target: &Features,
    matches: &[Correspondence],
) -> (Vec<Point3<f64>>, Vec<Point3<f64>>) {
    matches.iter().map(|c| (source.keypoint(c.source).cast(), target.keypoint(c.target).cast())).unzip()
}
