//! Pairwise global registration of two robot maps without an initial guess (paper §4; the pipeline
//! of map_merge_3d, Hörner 2016, made faster and more robust).
//!
//! 1. [`preprocess`]: finite points, voxel downsampling, outlier removal;
//! 2. [`normals`]: plane-fit normals with a frame-independent orientation;
//! 3. [`harris`]: Harris 3D keypoints with an adaptive count;
//! 4. [`fpfh`]: FPFH descriptors at the keypoints, over the whole downsampled map;
//! 5. [`matching`]: reciprocal k-nearest matching in descriptor space;
//! 6. [`ransac`]: RANSAC with edge-length pre-rejection and an adaptive iteration bound, Umeyama
//!    refit on all inliers;
//! 7. [`polish`]: a few point-to-plane steps on the downsampled maps (decimetres to centimetres);
//!
//! then [`confidence`] scores the result and decides whether it is reliable. The output transform
//! maps SOURCE points into the TARGET frame; fine registration (VGICP) is left to the caller.
//!
//! Steps 1-4 depend on one map only: [`MapFeatures::compute`] runs them once per map so that a
//! station merging many maps computes each map's features once and calls [`align`] per pair;
//! [`register`] does both for a single pair. Bad input (empty clouds, a few points, NaN, identical
//! points) gives an error or [`PairwiseOutcome::NotAligned`], never a panic.

pub mod bench;
pub mod confidence;
pub mod fpfh;
pub mod harris;
pub mod matching;
pub mod normals;
pub mod polish;
pub mod preprocess;
pub mod ransac;

use std::time::Duration;

use cloud::PointCloud;
use cloud::stopwatch::Stopwatch;
use nalgebra::{Isometry3, Point3};

pub use confidence::{Confidence, ConfidenceConfig};
pub use fpfh::{Fpfh, FpfhConfig};
pub use harris::HarrisConfig;
pub use matching::{Correspondence, MatchingConfig};
pub use normals::{NormalConfig, Orientation, Surfels};
pub use polish::PolishConfig;
pub use preprocess::{OutlierFilter, PreprocessConfig};
pub use ransac::RansacConfig;

/// Why one map's features could not be computed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum FeatureError {
    /// A setting is out of range.
    #[error("invalid configuration: {0}")]
    InvalidConfig(&'static str),
    /// Too little data survived a step.
    #[error("{points} usable points after {stage}, need at least {needed}")]
    TooFewPoints {
        /// The step after which the count fell short.
        stage: &'static str,
        /// Points (or descriptors) left.
        points: usize,
        /// Minimum required.
        needed: usize,
    },
}

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

/// Settings of the whole pipeline, one struct per step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PairwiseConfig {
    /// Step 1.
    pub preprocess: PreprocessConfig,
    /// Step 2.
    pub normals: NormalConfig,
    /// Step 3.
    pub keypoints: HarrisConfig,
    /// Step 4.
    pub descriptors: FpfhConfig,
    /// Step 5.
    pub matching: MatchingConfig,
    /// Step 6.
    pub ransac: RansacConfig,
    /// Step 7.
    pub polish: PolishConfig,
    /// Scores and acceptance.
    pub confidence: ConfidenceConfig,
}

impl Default for PairwiseConfig {
    fn default() -> Self {
        Self::outdoor()
    }
}

impl PairwiseConfig {
    /// Every radius scaled from the voxel size `v` (Open3D's tutorial ratios: normals 2v, FPFH 5v).
    pub fn for_resolution(v: f32) -> Self {
        let vd = f64::from(v);
        Self {
            preprocess: PreprocessConfig { voxel_size: v, min_spacing: 0.5 * v, ..PreprocessConfig::default() },
            normals: NormalConfig {
                radius: 2.0 * v,
                orientation: Orientation::LocalMass { radius: 5.0 * v },
                ..NormalConfig::default()
            },
            keypoints: HarrisConfig { radius: 3.0 * v, nms_radius: v, ..HarrisConfig::default() },
            descriptors: FpfhConfig { radius: 5.0 * v, ..FpfhConfig::default() },
            matching: MatchingConfig::default(),
            ransac: RansacConfig { inlier_distance: 2.5 * vd, min_edge: 2.5 * vd, ..RansacConfig::default() },
            polish: PolishConfig { max_distance: 2.0 * v, ..PolishConfig::default() },
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

    /// The largest neighbourhood radius of steps 2-4: the reach of the shared neighbour lists.
    pub fn reach(&self) -> f32 {
        let mass = match self.normals.orientation {
            Orientation::LocalMass { radius } => radius,
            _ => 0.0,
        };
        [self.normals.radius, mass, self.keypoints.radius, self.keypoints.nms_radius, self.descriptors.radius]
            .into_iter()
            .fold(0.0, f32::max)
    }

    /// Checks every step's settings.
    pub fn validate(&self) -> Result<(), FeatureError> {
        self.preprocess.validate()?;
        self.normals.validate()?;
        self.keypoints.validate()?;
        self.descriptors.validate()?;
        self.matching.validate()?;
        self.ransac.validate()?;
        self.polish.validate()?;
        self.confidence.validate()
    }
}

/// Wall time of the per-map steps.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FeatureTiming {
    /// Step 1.
    pub preprocess: Duration,
    /// Step 2.
    pub normals: Duration,
    /// Step 3.
    pub keypoints: Duration,
    /// Step 4.
    pub descriptors: Duration,
}

impl FeatureTiming {
    /// Sum of the four steps.
    pub fn total(&self) -> Duration {
        self.preprocess + self.normals + self.keypoints + self.descriptors
    }
}

/// Wall time of every step of one registration.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepTiming {
    /// Steps 1-4 on the source map.
    pub source: FeatureTiming,
    /// Steps 1-4 on the target map.
    pub target: FeatureTiming,
    /// Step 5.
    pub matching: Duration,
    /// Step 6.
    pub ransac: Duration,
    /// Step 7.
    pub polish: Duration,
    /// Confidence scores.
    pub confidence: Duration,
    /// End to end ([`register`] computes both maps' features concurrently, so this is less than
    /// the sum of the steps).
    pub total: Duration,
}

/// Steps 1-4 of one map: surfels, keypoints and their descriptors.
pub struct MapFeatures {
    /// Downsampled, filtered points with normals (and their k-d tree).
    pub surfels: Surfels,
    /// Indices into `surfels` of the keypoints that have a descriptor.
    pub keypoints: Vec<usize>,
    /// FPFH of each keypoint.
    pub descriptors: Vec<Fpfh>,
    /// Time spent per step.
    pub timing: FeatureTiming,
}

impl MapFeatures {
    /// Runs steps 1-4 on `cloud`.
    pub fn compute(cloud: &PointCloud, config: &PairwiseConfig) -> Result<Self, FeatureError> {
        config.validate()?;
        let mut timing = FeatureTiming::default();
        let mut watch = Stopwatch::start();
        let filtered = preprocess::preprocess(cloud, &config.preprocess)?;
        timing.preprocess = watch.lap();
        let surfels = normals::estimate_normals(&filtered, &config.normals, config.reach())?;
        timing.normals = watch.lap();
        let with_normals = surfels.with_normals();
        if with_normals < config.preprocess.min_points.max(3) {
            return Err(FeatureError::TooFewPoints {
                stage: "normal estimation",
                points: with_normals,
                needed: config.preprocess.min_points.max(3),
            });
        }
        let candidates = harris::detect_keypoints(&surfels, &config.keypoints);
        timing.keypoints = watch.lap();
        let described = fpfh::fpfh_at(&surfels, &candidates, &config.descriptors);
        let (keypoints, descriptors): (Vec<usize>, Vec<Fpfh>) =
            candidates.iter().zip(described).filter_map(|(&i, d)| Some((i, d?))).unzip();
        timing.descriptors = watch.lap();
        if keypoints.len() < 3 {
            return Err(FeatureError::TooFewPoints { stage: "descriptors", points: keypoints.len(), needed: 3 });
        }
        Ok(Self { surfels, keypoints, descriptors, timing })
    }

    /// Position of keypoint `k` (an index into [`MapFeatures::keypoints`]).
    pub fn keypoint(&self, k: usize) -> Point3<f32> {
        self.surfels.points[self.keypoints[k]]
    }

    /// Positions of all keypoints.
    pub fn keypoint_positions(&self) -> Vec<Point3<f32>> {
        (0..self.keypoints.len()).map(|k| self.keypoint(k)).collect()
    }
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
    let (s, t) = rayon::join(|| MapFeatures::compute(source, config), || MapFeatures::compute(target, config));
    let (s, t) = (s.map_err(PairwiseError::Source)?, t.map_err(PairwiseError::Target)?);
    let mut outcome = align(&s, &t, config);
    if let Some(r) = outcome.best_mut() {
        r.timing.total = watch.elapsed();
    }
    Ok(outcome)
}

/// Steps 5-6 and the scores for two maps' features (`total` timing: features plus this call).
pub fn align(source: &MapFeatures, target: &MapFeatures, config: &PairwiseConfig) -> PairwiseOutcome {
    let mut timing = StepTiming { source: source.timing, target: target.timing, ..StepTiming::default() };
    let mut watch = Stopwatch::start();
    let matches = matching::reciprocal_matches(&source.descriptors, &target.descriptors, config.matching.k);
    timing.matching = watch.lap();
    let src: Vec<Point3<f64>> = matches.iter().map(|c| source.keypoint(c.source).cast()).collect();
    let tgt: Vec<Point3<f64>> = matches.iter().map(|c| target.keypoint(c.target).cast()).collect();
    let model = ransac::ransac(&src, &tgt, &config.ransac);
    timing.ransac = watch.lap();
    let Some(model) = model else {
        return PairwiseOutcome::NotAligned {
            reason: Rejection::NoModel { correspondences: matches.len() },
            best: None,
        };
    };
    let transform = polish::polish(&source.surfels, &target.surfels, &model.transform, &config.polish);
    timing.polish = watch.lap();
    let inlier_ratio = model.inliers.len() as f64 / matches.len() as f64;
    let scores = confidence::confidence(
        &source.surfels.points,
        &target.surfels.tree,
        &transform,
        inlier_ratio,
        &config.confidence,
    );
    timing.confidence = watch.lap();
    timing.total = source.timing.total()
        + target.timing.total()
        + timing.matching
        + timing.ransac
        + timing.polish
        + timing.confidence;
    let result = PairwiseResult {
        transform,
        coarse_transform: model.transform,
        inliers: model.inliers.iter().map(|&i| matches[i]).collect(),
        correspondences: matches.len(),
        inlier_ratio,
        keypoints: (source.keypoint_positions(), target.keypoint_positions()),
        ransac_iterations: model.iterations,
        confidence: scores,
        timing,
    };
    accept(result, &config.confidence)
}

/// The outcome of the reliability checks on a result.
fn accept(result: PairwiseResult, config: &ConfidenceConfig) -> PairwiseOutcome {
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
