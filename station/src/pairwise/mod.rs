//! Pairwise global registration of two robot maps without an initial guess (paper §4; the pipeline
//! of map_merge_3d, Hörner 2016, made faster and more robust).
//!
//! The steps that do not depend on what the clouds are live in [`cloud::global`], shared with the
//! robots' re-localisation: features of one map (steps 1-4: preprocess, normals, Harris keypoints,
//! FPFH; [`Features::compute`]), then matching, RANSAC and a point-to-plane polish (steps 5-7;
//! [`cloud::global::estimate()`]). What is about merging maps is here: [`confidence`] (in `cloud`,
//! shared with the robots' loop closure) scores the result and decides whether it is reliable;
//! [`align`] and [`register`] put the two together, and [`bench`](mod@bench) times them. The output transform maps SOURCE points into the TARGET frame; fine
//! registration (VGICP) is left to the caller.
//!
//! A station merging many maps computes each map's features once and calls [`align`] per pair;
//! [`register`] does both for a single pair. Bad input (empty clouds, a few points, NaN, identical
//! points) gives an error or [`PairwiseOutcome::NotAligned`], never a panic.

pub use cloud::confidence;

use std::time::Duration;

use cloud::PointCloud;
use cloud::global::{EstimateTiming, NoModel, estimate_excluding};
use cloud::stopwatch::{Stopwatch, timed};
use nalgebra::{Isometry3, Point3};

pub use cloud::global::{Around, Correspondence, FeatureError, FeatureTiming, Features, GlobalConfig};
pub use confidence::{Confidence, ConfidenceConfig};

/// Why a pair of maps could not be processed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PairwiseError {
    /// The source map's features failed.
    #[error("source map: {0}")]
    Source(FeatureError),
    /// The target map's features failed.
    #[error("target map: {0}")]
    Target(FeatureError),
    /// A setting is out of range.
    #[error("{0}")]
    Config(FeatureError),
}

/// Settings of the registration steps and of the acceptance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PairwiseConfig {
    /// Steps 1-7.
    pub global: GlobalConfig,
    /// Scores and acceptance.
    pub confidence: ConfidenceConfig,
}

impl Default for PairwiseConfig {
    fn default() -> Self {
        Self::outdoor()
    }
}

impl PairwiseConfig {
    /// Every radius scaled from the voxel size `v` ([`GlobalConfig::for_resolution`]).
    pub fn for_resolution(v: f32) -> Self {
        Self {
            global: GlobalConfig::for_resolution(v),
            confidence: ConfidenceConfig {
                max_correspondence_distance: 5.0 * v,
                overlap_distance: 1.5 * v,
                ..ConfidenceConfig::default()
            },
        }
    }

    /// Streets, campuses, outdoor LiDAR maps: 0.4 m voxels (the defaults of every step).
    pub fn outdoor() -> Self {
        Self::for_resolution(0.4)
    }

    /// Rooms, corridors, warehouses: 0.1 m voxels.
    pub fn indoor() -> Self {
        Self::for_resolution(0.1)
    }

    /// Checks every step's settings.
    pub fn validate(&self) -> Result<(), FeatureError> {
        self.global.validate()?;
        self.confidence.validate()
    }
}

/// Wall time of every step of one registration.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepTiming {
    /// Steps 1-4 on the source map.
    pub source: FeatureTiming,
    /// Steps 1-4 on the target map.
    pub target: FeatureTiming,
    /// Steps 5-7.
    pub estimate: EstimateTiming,
    /// Confidence scores.
    pub confidence: Duration,
    /// End to end ([`register`] computes both maps' features concurrently, so this is less than
    /// the sum of the steps).
    pub total: Duration,
}

/// A transform between two maps with its evidence.
#[derive(Clone, Debug, PartialEq)]
pub struct PairwiseResult {
    /// Maps SOURCE points into the TARGET frame (after step 7).
    pub transform: Isometry3<f64>,
    /// The RANSAC + Umeyama transform before the polish.
    pub coarse_transform: Isometry3<f64>,
    /// The RANSAC inliers among the correspondences (indices into the keypoint lists).
    pub inliers: Vec<Correspondence>,
    /// Number of reciprocal correspondences RANSAC started from.
    pub correspondences: usize,
    /// `inliers.len() / correspondences`.
    pub inlier_ratio: f64,
    /// Keypoint positions of the source and of the target map (each in its own frame).
    pub keypoints: (Vec<Point3<f32>>, Vec<Point3<f32>>),
    /// Samples RANSAC drew.
    pub ransac_iterations: usize,
    /// Fitness, overlap and combined score.
    pub confidence: Confidence,
    /// Time per step.
    pub timing: StepTiming,
}

/// Why the best transform was not trusted.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum Rejection {
    /// RANSAC found no model (fewer than 3 correspondences, or no sample passed the checks).
    #[error("no transform: {correspondences} correspondences and no consistent sample")]
    NoModel {
        /// Reciprocal correspondences found.
        correspondences: usize,
    },
    /// Too few correspondences agree with the transform.
    #[error("{inliers} inliers, need {needed}")]
    TooFewInliers {
        /// Inliers of the best model.
        inliers: usize,
        /// Minimum required.
        needed: usize,
    },
    /// Too little of the source map lands on the target map.
    #[error("overlap {overlap:.3}, need {needed:.3}")]
    LowOverlap {
        /// Overlap share of the best model.
        overlap: f64,
        /// Minimum required.
        needed: f64,
    },
    /// The combined confidence score is too low.
    #[error("score {score:.3}, need {needed:.3}")]
    LowScore {
        /// Score of the best model.
        score: f64,
        /// Minimum required.
        needed: f64,
    },
}

/// What the registration concluded.
#[derive(Clone, Debug, PartialEq)]
pub enum PairwiseOutcome {
    /// A transform passed the reliability checks.
    Aligned(Box<PairwiseResult>),
    /// No reliable alignment; the best hypothesis, if any, is kept for inspection.
    NotAligned {
        /// The check that failed.
        reason: Rejection,
        /// RANSAC's best model and its scores.
        best: Option<Box<PairwiseResult>>,
    },
}

impl PairwiseOutcome {
    /// The result if the alignment is reliable.
    pub fn aligned(&self) -> Option<&PairwiseResult> {
        match self {
            PairwiseOutcome::Aligned(r) => Some(r),
            PairwiseOutcome::NotAligned { .. } => None,
        }
    }

    /// The best hypothesis whether or not it was accepted.
    pub fn best(&self) -> Option<&PairwiseResult> {
        match self {
            PairwiseOutcome::Aligned(r) => Some(r),
            PairwiseOutcome::NotAligned { best, .. } => best.as_deref(),
        }
    }

    fn best_mut(&mut self) -> Option<&mut PairwiseResult> {
        match self {
            PairwiseOutcome::Aligned(r) => Some(r),
            PairwiseOutcome::NotAligned { best, .. } => best.as_deref_mut(),
        }
    }
}

/// Registers `source` onto `target`: the transform mapping source points into the target frame.
pub fn register(
    source: &PointCloud,
    target: &PointCloud,
    config: &PairwiseConfig,
) -> Result<PairwiseOutcome, PairwiseError> {
    config.validate().map_err(PairwiseError::Config)?;
    let watch = Stopwatch::start();
    let features = |cloud| Features::compute(cloud, &config.global);
    let (s, t) = rayon::join(|| features(source), || features(target));
    let (s, t) = (s.map_err(PairwiseError::Source)?, t.map_err(PairwiseError::Target)?);
    let mut outcome = align(&s, &t, config);
    if let Some(r) = outcome.best_mut() {
        r.timing.total = watch.elapsed();
    }
    Ok(outcome)
}

/// Steps 5-7 and the scores for two maps' features (`total` timing: features plus this call).
pub fn align(source: &Features, target: &Features, config: &PairwiseConfig) -> PairwiseOutcome {
    align_excluding(source, target, config, &[], None)
}

/// Correspondences farther than this many RANSAC inlier distances from a transform count as
/// disagreeing with it (the margin keeps its near-inliers out of a search for another).
pub const EXCLUSION: f64 = 3.0;

/// [`align`] on the correspondences that disagree with every transform of `excluded` (beyond
/// [`EXCLUSION`] inlier distances): the next distinct hypothesis after transforms found wrong;
/// with `around`, on those near a place both maps seem to share only (the inlier ratio is then
/// theirs, see [`Around`]).
pub fn align_excluding(
    source: &Features,
    target: &Features,
    config: &PairwiseConfig,
    excluded: &[Isometry3<f64>],
    around: Option<&Around>,
) -> PairwiseOutcome {
    let margin = EXCLUSION * config.global.ransac.inlier_distance;
    let found = match estimate_excluding(source, target, &config.global, excluded, margin, around) {
        Ok(found) => found,
        Err(NoModel { correspondences }) => {
            return PairwiseOutcome::NotAligned { reason: Rejection::NoModel { correspondences }, best: None };
        }
    };
    let (scores, took) = timed(|| {
        confidence::confidence(
            &source.surfels.points,
            &target.surfels.tree,
            &found.transform,
            found.inlier_ratio(),
            &config.confidence,
        )
    });
    let result = PairwiseResult {
        transform: found.transform,
        coarse_transform: found.coarse_transform,
        inliers: found.inlier_matches(),
        correspondences: found.matches.len(),
        inlier_ratio: found.inlier_ratio(),
        keypoints: (source.keypoint_positions(), target.keypoint_positions()),
        ransac_iterations: found.ransac_iterations,
        confidence: scores,
        timing: StepTiming::of(source, target, found.timing, took),
    };
    accept(result, &config.confidence)
}

impl StepTiming {
    /// The steps' times of one [`align`] whose confidence scores took `confidence`.
    fn of(source: &Features, target: &Features, estimate: EstimateTiming, confidence: Duration) -> Self {
        let total = source.timing.total() + target.timing.total() + estimate.total() + confidence;
        Self { source: source.timing, target: target.timing, estimate, confidence, total }
    }
}

/// The outcome of the reliability checks on a result.
pub(crate) fn accept(result: PairwiseResult, config: &ConfidenceConfig) -> PairwiseOutcome {
    let reason = if result.inliers.len() < config.min_inliers {
        Rejection::TooFewInliers { inliers: result.inliers.len(), needed: config.min_inliers }
    } else if result.confidence.overlap < config.min_overlap {
        Rejection::LowOverlap { overlap: result.confidence.overlap, needed: config.min_overlap }
    } else if result.confidence.score < config.min_score {
        Rejection::LowScore { score: result.confidence.score, needed: config.min_score }
    } else {
        return PairwiseOutcome::Aligned(Box::new(result));
    };
    PairwiseOutcome::NotAligned { reason, best: Some(Box::new(result)) }
}
