//! F-LOAM odometry (Wang et al., IROS 2021, section III) with the paper's two-stage distortion
//! compensation. One call per scan, in [`Odometry::register`]:
//!
//! 1. features: per-ring smoothness (eq. 1), 6 sectors, edges and planes ([`features`]); for
//!    scans without rings, the shape of each voxel's points ([`voxel_features`]);
//! 2. stage 1: constant-velocity motion from the last frame (eq. 2) moves each feature to the sweep
//!    end by its own timestamp (eq. 3) ([`deskew`]);
//! 3. pose: scan-to-local-map point-to-line / point-to-plane matching (eq. 4) ([`solver`]) from the
//!    constant-velocity prediction; the fit is judged against the recent ones ([`health`]), and
//!    where it is suspect, or the prediction has no measured velocity behind it (the second scan,
//!    after a gap), it is fitted again from a coarse alignment ([`coarse`], its reach KISS-ICP's
//!    adaptive threshold, [`motion_model`]) and, still suspect, from a global re-localisation
//!    ([`cloud::global`]); the fit agreeing best with the map wins, and a scan no start fits is
//!    lost: reported, but kept out of the map;
//!    where the features are too few for that fit to measure the pose, or it is lost, the whole
//!    scan is registered densely against a local map of points instead ([`dense`], KISS-ICP's fit);
//! 4. stage 2: the distortion is recomputed with the estimated motion and the features are corrected
//!    again before they enter the map;
//! 5. local map: edge and plane voxel maps cropped around the robot, k-d trees ([`local_map`]);
//! 6. keyframes every N metres or M degrees, carrying the deskewed, downsampled cloud.
//!
//! With `method = "aloam"` the scans go through A-LOAM instead ([`aloam`]: scan-to-scan odometry
//! every sweep, scan-to-map refinement at a lower rate, linear deskewing), for the paper's
//! MR-ALOAM and EMR-ALOAM comparisons.
//!
//! Every parameter and the presets are in [`config`]; [`pipeline`] runs the odometry over a source,
//! evaluates it against ground truth and writes the results.
//!
//! Poses are those of the sensor at the END of each sweep, in the odometry frame (the sensor frame at
//! the end of the first sweep).

pub mod aloam;
pub mod coarse;
pub mod config;
pub mod dense;
pub mod deskew;
pub mod feature_points;
pub mod features;
pub mod health;
pub mod local_map;
pub mod motion_model;
pub mod pipeline;
pub mod solver;
pub mod stats;
pub mod voxel_features;

use cloud::PointCloud;
use cloud::stopwatch::{Stopwatch, millis, timed};
use nalgebra::{Isometry3, Point3};
use serde::Serialize;

pub use crate::keyframe::Keyframe;
pub use config::{FeatureConfig, KeyframeConfig, MapConfig, Method, OdometryConfig, SolverConfig};
use deskew::SweepMotion;
use features::{FeatureError, Features};
use health::Health;
use local_map::{FeatureMap, MAX_POINTS_PER_VOXEL, ScanLine};
use motion_model::MotionModel;

/// What one scan produced.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Sensor pose at the sweep end in the odometry frame.
    pub pose: Isometry3<f64>,
    /// Edge features extracted.
    pub edges: usize,
    /// Plane features extracted (after thinning).
    pub planes: usize,
    /// Gauss-Newton iterations.
    pub iterations: usize,
    /// True when the pose problem was ill-conditioned and the motion prior was kept along some directions.
    pub degenerate: bool,
    /// Smallest eigenvalue of the pose problem's normal matrix over the sum of weights (1 for the
    /// first scan): how well the worst direction is constrained.
    pub conditioning: f64,
    /// Where the feature fit started: the prediction, or a coarse or global alignment when the
    /// prediction's fit was suspect or had no measured velocity behind it.
    pub start: Start,
    /// True when even the best fit matched too few features to trust: the scan's features were
    /// kept out of the map.
    pub lost: bool,
    /// Which extractor made the features: rings, or voxel shapes for scans without rings.
    pub feature_kind: features::FeatureKind,
    /// Which fit gave the pose: the features', or the dense one where they were too few.
    pub fit: Fit,
    /// The keyframe this scan made, if any.
    pub keyframe: Option<Keyframe>,
    /// Where the time went.
    pub timings: FrameTimings,
}

/// Wall time of the pipeline's stages for one scan, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct FrameTimings {
    /// Feature extraction and thinning.
    pub features: f64,
    /// Distortion compensation and pose estimation.
    pub registration: f64,
    /// Map insertion, crop and k-d tree rebuild, keyframe.
    pub map: f64,
}

/// Where the feature fit that gave a scan's pose started.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Start {
    /// The constant-velocity prediction (eq. 2): the usual case.
    #[default]
    Prediction,
    /// A coarse alignment ([`coarse`]) from the prediction.
    Coarse,
    /// A global re-localisation against the local map, without a guess.
    Global,
}

/// Which registration gave a scan's pose.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Fit {
    /// Edge and plane features against the feature maps (eq. 4): the usual case.
    #[default]
    Features,
    /// The whole scan against the local map of points ([`dense`]): the features were too few.
    Dense,
}

/// One start's fit: the estimate, and the compensation of its last round.
struct Fitted {
    estimate: solver::Estimate,
    motion: SweepMotion,
}

/// Where a scan was found, and from what.
struct Located {
    /// The fine fit.
    estimate: solver::Estimate,
    /// The sweep motion its features were compensated with in its last round.
    motion: SweepMotion,
    /// The constant-velocity prediction.
    predicted: Isometry3<f64>,
    /// Where the fine fit started.
    start: Start,
    /// True when even the best fit is suspect.
    lost: bool,
}

/// How much higher (as a fraction) a fit from another start must score in agreement with the map
/// to replace the prediction's: where the scene leaves a direction unconstrained (a corridor) fits
/// slid along it score about as well, and the prediction is the better guess there.
const RECOVERY_MARGIN: f64 = 0.1;

/// Two fits are the same pose when they place a point [`SAME_FIT_RANGE_M`] away within this (m):
/// well above a converged fit's jitter (millimetres), well below a wrong basin (decimetres up).
const SAME_FIT_M: f64 = 0.02;
/// See [`SAME_FIT_M`].
const SAME_FIT_RANGE_M: f64 = 10.0;

impl Located {
    /// True when the feature fit measured the pose (matches enough to solve) and is not lost.
    fn measured(&self) -> bool {
        !self.lost && self.estimate.iterations > 0
    }

    /// Takes `estimate` (started from `start`) when it found another pose than the current fit
    /// and `agreement` scores it higher, by `margin` (a fraction) at least. Two starts that
    /// converged to the same pose differ by chance; the prediction's fit is kept then.
    fn keep_better(
        &mut self,
        Fitted { estimate, motion }: Fitted,
        start: Start,
        margin: f64,
        agreement: impl Fn(&Isometry3<f64>) -> f64,
    ) {
        let apart = motion_model::displacement(&(self.estimate.pose.inverse() * estimate.pose), SAME_FIT_RANGE_M);
        if apart > SAME_FIT_M && agreement(&estimate.pose) > (1.0 + margin) * agreement(&self.estimate.pose) {
            self.estimate = estimate;
            self.motion = motion;
            self.start = start;
        }
    }
}

/// A scan's features compensated with the predicted sweep motion (stage 1), made once for the
/// starts and comparisons of one scan.
struct Stage1 {
    edges: Vec<features::Feature>,
    planes: Vec<features::Feature>,
}

impl Stage1 {
    fn of(raw: &Features, motion: &SweepMotion) -> Self {
        Stage1 { edges: deskew::compensate(&raw.edges, motion), planes: deskew::compensate(&raw.planes, motion) }
    }

    /// Edges and planes together, as points to register.
    fn points(&self) -> Vec<Point3<f32>> {
        self.edges.iter().chain(&self.planes).map(|f| f.point).collect()
    }
}

/// Correspondences of a fit's last search: the better a pose, the more features find their line
/// or plane within the neighbour radius.
fn matches(estimate: &solver::Estimate) -> usize {
    estimate.edge_matches + estimate.plane_matches
}

/// The share of a scan's features a fit matched.
fn share(estimate: &solver::Estimate, raw: &Features) -> f64 {
    matches(estimate) as f64 / (raw.edges.len() + raw.planes.len()).max(1) as f64
}

/// Points of the last scan kept to start the map of points from (every k-th): more than its
/// thinning leaves of a 64-beam scan (15-20k), at a tenth of a copy's cost of a 120k-point one.
const SEED_POINTS: usize = 30_000;

/// Fewest RANSAC inliers a re-localisation needs.
const RELOCALISE_MIN_INLIERS: usize = 15;
/// Smallest share of the scan a re-localisation must place on the map.
const RELOCALISE_MIN_FITNESS: f64 = 0.5;

/// Why a scan could not be registered.
#[derive(Debug, thiserror::Error)]
pub enum OdometryError {
    /// The scan lacks a channel the odometry needs.
    #[error(transparent)]
    Features(#[from] FeatureError),
    /// A configuration value is unusable.
    #[error("invalid configuration: {0}")]
    Config(String),
}

/// The odometry state of one robot: F-LOAM, or A-LOAM ([`aloam`]) with `method = "aloam"`.
pub struct Odometry {
    config: OdometryConfig,
    frames: usize,
    pose: Isometry3<f64>,
    /// The motion over one sweep, from the last two scans (eq. 2).
    motion: SweepMotion,
    /// Stamp of the last scan, seconds.
    stamp: f64,
    /// Sweeps between the last scan and this one (1 unless scans were dropped).
    sweeps: f64,
    /// Sweeps between the two scans before this one: the last motion's span.
    last_sweeps: f64,
    edge_map: FeatureMap,
    plane_map: FeatureMap,
    last_keyframe: Option<Isometry3<f64>>,
    keyframes: u64,
    model: MotionModel,
    health: Health,
    /// The same judgement of the dense fits, by the share of the scan they place on the map.
    dense_health: Health,
    /// Scans registered since the start or the last reset of the motion model.
    since_reset: usize,
    /// The first scan's features, until the second scan measured the motion they were taken in.
    first: Option<Features>,
    /// A-LOAM's state, used with [`Method::Aloam`].
    aloam: aloam::AloamState,
    /// The local map of points the dense fit registers against, made at the scale of the first
    /// scan it holds, once a dense fit was wanted.
    points: Option<dense::PointMap>,
    /// True once a dense fit was wanted: from then on every accepted scan enters [`Self::points`].
    points_wanted: bool,
    /// Until then, the last accepted scan, the motion it is compensated with and its pose: what
    /// the map of points starts from when a scan with scan lines first needs the dense fit. A
    /// spinning sensor's scans fit by their features, and thinning each into a map no fit uses
    /// cost 6 of 15 ms per KITTI scan.
    last_scan: Option<(PointCloud, SweepMotion, Isometry3<f64>)>,
}

impl Odometry {
    /// A fresh odometry; the first scan defines the odometry frame.
    pub fn new(config: OdometryConfig) -> Result<Self, OdometryError> {
        let positive = [
            ("scan_period", config.scan_period),
            ("edge_map.voxel_size", config.edge_map.voxel_size),
            ("plane_map.voxel_size", config.plane_map.voxel_size),
            ("features.edge_voxel", config.features.edge_voxel),
            ("features.plane_voxel", config.features.plane_voxel),
            ("keyframes.voxel", config.keyframes.voxel),
        ];
        if let Some((name, v)) = positive.iter().find(|(_, v)| !(*v > 0.0 && v.is_finite())) {
            return Err(OdometryError::Config(format!("{name} must be positive, got {v}")));
        }
        for (name, map) in [("edge_map", &config.edge_map), ("plane_map", &config.plane_map)] {
            if !(1..=MAX_POINTS_PER_VOXEL).contains(&map.points_per_voxel) || map.max_voxels == 0 {
                return Err(OdometryError::Config(format!(
                    "{name}: points_per_voxel must be 1 to {MAX_POINTS_PER_VOXEL} and max_voxels at least 1, got {} and {}",
                    map.points_per_voxel, map.max_voxels
                )));
            }
        }
        config.aloam.check()?;
        Ok(Odometry {
            aloam: aloam::AloamState::new(),
            edge_map: FeatureMap::new(config.edge_map.clone()),
            plane_map: FeatureMap::new(config.plane_map.clone()),
            frames: 0,
            pose: Isometry3::identity(),
            motion: SweepMotion::zero(),
            stamp: 0.0,
            sweeps: 1.0,
            last_sweeps: 1.0,
            last_keyframe: None,
            keyframes: 0,
            model: MotionModel::new(config.motion_model.clone()),
            health: Health::new(config.health.clone()),
            // A dense fit at the right pose puts nearly the whole scan on the map it came from.
            dense_health: Health::with_prior(config.health.clone(), 1.0),
            since_reset: 0,
            first: None,
            points: None,
            points_wanted: false,
            last_scan: None,
            config,
        })
    }

    /// The configuration in use.
    pub fn config(&self) -> &OdometryConfig {
        &self.config
    }

    /// Registers one scan swept from `stamp` (seconds) and returns its pose. With a ring channel
    /// the scan needs per-point times too; without one, its features come from voxel shapes.
    pub fn register(&mut self, scan: &PointCloud, stamp: f64) -> Result<Frame, OdometryError> {
        self.advance_clock(stamp);
        // The stages' parallel loops hand their work to rayon's pool and wait for it: called from
        // a thread outside the pool, each loop costs a worker's wake-up and a hand-over back, a
        // dozen per scan. Run on a worker, the scan pays for one.
        rayon::scope(|_| self.register_on_pool(scan))
    }

    /// How many sweeps passed since the last scan: the sensor spins at a fixed rate, so the gap
    /// between two stamps is a whole number of sweeps (more than one where scans were dropped or
    /// thinned out); after a gap of [`MotionModelConfig::gap_s`] the prediction is not trusted.
    fn advance_clock(&mut self, stamp: f64) {
        let elapsed = stamp - self.stamp;
        let period = f64::from(self.config.scan_period);
        self.sweeps = if self.frames > 0 && elapsed.is_finite() { (elapsed / period).round().max(1.0) } else { 1.0 };
        if self.frames > 0 && self.model.is_gap(self.stamp, stamp) {
            // The velocity is stale: predict one sweep of it and align coarse to fine, as for the
            // scan after the first.
            self.model.reset();
            self.sweeps = 1.0;
            self.since_reset = 1;
        }
        self.stamp = stamp;
    }

    /// [`Odometry::register`] on a worker of rayon's pool.
    fn register_on_pool(&mut self, scan: &PointCloud) -> Result<Frame, OdometryError> {
        if self.config.method == Method::Aloam {
            return self.register_aloam(scan);
        }
        let mut watch = Stopwatch::start();
        let (raw, feature_kind) = features::extract_any(scan, self.config.scan_period, &self.config.features)?;
        let features_ms = watch.lap_ms();
        let scan_lines = feature_kind == features::FeatureKind::Rings;
        let mut located = self.locate(&raw);
        if let Some(first) = self.first.take() {
            located.estimate = self.recompensate_first(&first, &raw, located.estimate);
        }
        if !scan_lines || (self.frames > 0 && !located.measured()) {
            self.want_points();
        }
        let dense = self.dense(scan, &located, scan_lines);
        if let Some(fit) = &dense {
            located.estimate.pose = fit.pose;
            located.estimate.iterations = fit.iterations;
            located.lost = self.dense_health.is_suspect(fit.on_map);
            tracing::debug!(frame = self.frames, on_map = fit.on_map, lost = located.lost, "dense fit");
        } else if !scan_lines && self.frames > 0 && located.estimate.iterations == 0 {
            // Nothing measured the pose, and the scan would enter the map where it was guessed.
            located.lost = true;
        }
        let registration_ms = watch.lap_ms();
        let estimate = &located.estimate;
        tracing::debug!(
            frame = self.frames,
            sigma = self.model.sigma(),
            start = ?located.start,
            lost = located.lost,
            correction = motion_model::displacement(&(located.predicted.inverse() * estimate.pose), 50.0),
            matched = share(estimate, &raw),
            iterations = estimate.iterations,
            "located"
        );
        let fit = if dense.is_some() { Fit::Dense } else { Fit::Features };
        let keyframe = if located.lost {
            self.skip(located.estimate.pose)
        } else {
            if let Some(dense) = &dense {
                self.dense_health.accept(dense.on_map);
            }
            self.accept(scan, &raw, &located, fit)
        };
        let timings = FrameTimings { features: features_ms, registration: registration_ms, map: watch.lap_ms() };
        Ok(Frame {
            timings,
            pose: self.pose,
            edges: raw.edges.len(),
            planes: raw.planes.len(),
            iterations: located.estimate.iterations,
            degenerate: located.estimate.degenerate_directions > 0,
            conditioning: located.estimate.min_eigen_ratio,
            start: located.start,
            lost: located.lost,
            feature_kind,
            fit,
            keyframe,
        })
    }

    /// The dense fit ([`dense::register`]) of the whole scan, compensated with the predicted sweep
    /// motion, from the prediction, where the features may not carry the pose: a feature fit that
    /// measured nothing (too few matches to solve) or is lost, or a scan without scan lines, whose
    /// voxel-shape features can be too few and too one-sided to fit (a solid-state sensor's few
    /// thousand points in a 70 deg view). There both fits are judged alike, by the share of the
    /// scan each places on the map of points, and the feature fit stands where it places as much.
    /// `None` where the feature fit stands, or the dense one found too little.
    fn dense(&self, scan: &PointCloud, located: &Located, scan_lines: bool) -> Option<dense::DenseFit> {
        let fitted = located.measured();
        if self.frames == 0 || (scan_lines && fitted) {
            return None;
        }
        let map = self.points.as_ref().filter(|m| !m.is_empty())?;
        let motion = if self.config.deskew { self.motion } else { SweepMotion::zero() };
        let source = self.thinned(scan, &motion, map.scale().source_grid());
        let sigma = self.model.sigma();
        let from_prediction = dense::register(&source, map, &located.predicted, sigma);
        if !fitted {
            return from_prediction;
        }
        let from_features = dense::register(&source, map, &located.estimate.pose, sigma);
        let fit =
            [from_prediction, from_features].into_iter().flatten().max_by(|a, b| a.on_map.total_cmp(&b.on_map))?;
        if dense::on_map(&source, map, &located.estimate.pose) >= fit.on_map {
            return None;
        }
        Some(fit)
    }

    /// From now on the accepted scans enter the map of points, which starts from the last one.
    fn want_points(&mut self) {
        self.points_wanted = true;
        if let (None, Some((scan, motion, pose))) = (&self.points, self.last_scan.take()) {
            let Some(scale) = dense::Scale::of(&scan.points) else { return };
            let mut map = dense::PointMap::new(scale);
            map.insert(&self.thinned(&scan, &motion, scale.map_grid()), &pose);
            self.points = Some(map);
        }
    }

    /// The scan's points compensated with `motion` and thinned on a grid of `grid` metres.
    fn thinned(&self, scan: &PointCloud, motion: &SweepMotion, grid: f32) -> Vec<Point3<f32>> {
        let deskewed = deskew::cloud(scan, motion, self.config.scan_period);
        cloud::voxel::downsample(&deskewed, grid).unwrap_or(deskewed).points
    }

    /// Stage 1 and the pose, from the constant-velocity prediction (eq. 2); where that fit is
    /// suspect or the prediction has nothing behind it, also from a coarse alignment and, failing
    /// that, from a global re-localisation: each start is refined by the feature fit and the fit
    /// agreeing best with the map wins ([`solver::agreement`]). The first scan defines the
    /// odometry frame.
    fn locate(&self, raw: &Features) -> Located {
        if self.frames == 0 {
            let estimate = solver::Estimate::first();
            let (predicted, motion) = (Isometry3::identity(), SweepMotion::zero());
            return Located { estimate, motion, predicted, start: Start::Prediction, lost: false };
        }
        let predicted = self.predicted();
        let Fitted { estimate, motion } = self.estimate(raw, predicted);
        let mut best = Located { estimate, motion, predicted, start: Start::Prediction, lost: false };
        // Without a measured velocity (the second scan, after a gap) the coarse start is tried
        // too: the prediction is a guess of no motion.
        let untrusted = self.since_reset < 2;
        // A degenerate fit matches few features by nature (a corridor), and another start could
        // only slide along the direction the prior holds.
        let degenerate = best.estimate.degenerate_directions > 0;
        if !untrusted && (degenerate || !self.health.is_suspect(share(&best.estimate, raw))) {
            return best;
        }
        // Against a guess of no motion, any start that agrees better is better.
        let margin = if untrusted { 0.0 } else { RECOVERY_MARGIN };
        let stage1 = Stage1::of(raw, &self.motion);
        let agreement = |pose: &Isometry3<f64>| self.agreement(&stage1, pose);
        // The coarse alignment's basin is wide but its voxels are blunt: along a street it can
        // settle a metre off where the prediction was right, hence the comparison.
        if let Some(start) = self.coarse(&stage1, &predicted) {
            best.keep_better(self.estimate(raw, start), Start::Coarse, margin, agreement);
        }
        // Global registration only where a history says the fit is still wrong: a scan against a
        // one-scan map (the second) finds spurious places that match as many features.
        let still_suspect = self.health.is_suspect(share(&best.estimate, raw));
        if still_suspect && self.health.config().relocalise {
            let (found, took) = timed(|| self.relocalise(&stage1));
            tracing::debug!("relocalise: {:.1} ms", millis(took));
            if let Some(start) = found {
                best.keep_better(self.estimate(raw, start), Start::Global, margin, agreement);
            }
        }
        best.lost = self.health.is_suspect(share(&best.estimate, raw));
        best
    }

    /// The constant-velocity prediction (eq. 2): the last motion carried forward over the sweeps
    /// that passed, or as one scan's motion where that has predicted better
    /// ([`motion_model::Extrapolation`]).
    fn predicted(&self) -> Isometry3<f64> {
        self.pose * cloud::se3::exp(&(self.motion.0 * self.extrapolated_sweeps()))
    }

    /// The sweeps the prediction carries the last motion over.
    fn extrapolated_sweeps(&self) -> f64 {
        match self.model.extrapolation() {
            motion_model::Extrapolation::Time => self.sweeps,
            motion_model::Extrapolation::Scan => self.last_sweeps,
        }
    }

    /// The scan's features aligned coarse to fine to the local maps' points from `predicted`,
    /// reaching as far as the prediction's recent errors (3σ, the adaptive gate).
    fn coarse(&self, stage1: &Stage1, predicted: &Isometry3<f64>) -> Option<Isometry3<f64>> {
        let config = self.config.coarse.reaching(3.0 * self.model.sigma());
        coarse::align(&stage1.points(), &self.map_points(), predicted, &config)
    }

    /// The scan placed in the local map without a guess: FPFH + RANSAC ([`cloud::global`]) of the
    /// scan's features onto the maps' points.
    fn relocalise(&self, stage1: &Stage1) -> Option<Isometry3<f64>> {
        let source = PointCloud::from_points(stage1.points());
        let target = PointCloud::from_points(self.map_points());
        let found = cloud::global::align(&source, &target, &cloud::global::GlobalConfig::scan()).ok()?;
        // A transform that a handful of descriptor pairs agree on, or that leaves most of the scan
        // off the map, is a guess, not a place (cloud::global's tests pass with 15 and 0.5).
        (found.inliers >= RELOCALISE_MIN_INLIERS && found.fitness >= RELOCALISE_MIN_FITNESS).then_some(found.transform)
    }

    /// [`solver::agreement`] of the stage-1 features at `pose`.
    fn agreement(&self, stage1: &Stage1, pose: &Isometry3<f64>) -> f64 {
        solver::agreement(&stage1.edges, &stage1.planes, &self.edge_map, &self.plane_map, pose, &self.config.solver)
    }

    /// The points of both local maps.
    fn map_points(&self) -> Vec<Point3<f32>> {
        let mut map = self.edge_map.points().to_vec();
        map.extend_from_slice(self.plane_map.points());
        map
    }

    /// The first scan entered the maps uncompensated: nothing was known of the motion it was taken
    /// in. A run that starts moving (a recording cut mid-drive, a robot turning) would keep that
    /// distortion in the map's frame; once the second scan measured the motion, the maps are made
    /// again from the first scan's features compensated with it and the second scan is fitted
    /// again, and the new maps are kept when the second scan agrees better with them.
    /// A start from rest (within [`OdometryConfig::deskew_tolerance`]) leaves the maps as they are.
    fn recompensate_first(&mut self, first: &Features, raw: &Features, fit: solver::Estimate) -> solver::Estimate {
        let pose = fit.pose;
        let motion = SweepMotion::per_sweep(&Isometry3::identity(), &pose, self.sweeps);
        if motion.difference_at(&SweepMotion::zero(), 10.0) <= self.config.deskew_tolerance {
            return fit;
        }
        // Each hypothesis is judged as a whole: the second scan as fitted (uncompensated, like the
        // map it was fitted to) against the maps as they are, and compensated against the
        // compensated maps.
        let before = self.agreement(&Stage1::of(raw, &SweepMotion::zero()), &pose);
        let mut edge_map = FeatureMap::new(self.config.edge_map.clone());
        let mut plane_map = FeatureMap::new(self.config.plane_map.clone());
        let placed = |f: &features::Feature| (motion.compensate(&f.point, f.phase), ScanLine::new(0, f.ring));
        edge_map.insert(first.edges.iter().map(placed), &Isometry3::identity());
        plane_map.insert(first.planes.iter().map(placed), &Isometry3::identity());
        edge_map.crop_and_rebuild(&Point3::origin());
        plane_map.crop_and_rebuild(&Point3::origin());
        let old_edges = std::mem::replace(&mut self.edge_map, edge_map);
        let old_planes = std::mem::replace(&mut self.plane_map, plane_map);
        let old_motion = std::mem::replace(&mut self.motion, motion);
        let refit = self.estimate(raw, pose).estimate;
        let refit_motion = SweepMotion::per_sweep(&Isometry3::identity(), &refit.pose, self.sweeps);
        let after = self.agreement(&Stage1::of(raw, &refit_motion), &refit.pose);
        tracing::debug!(before, after, "first scan compensated");
        // A recording published already compensated (KITTI) is distorted by compensating it
        // again: the second scan then agrees less with the first, and the maps stay as they were.
        if after > before {
            return refit;
        }
        self.motion = old_motion;
        self.edge_map = old_edges;
        self.plane_map = old_planes;
        fit
    }

    /// Stage 2 and the local map: the sweep's motion is re-estimated from the new pose, corrects
    /// the features before they enter the maps, and the maps follow the robot; the keyframe if due.
    fn update_map(&mut self, scan: &PointCloud, raw: &Features, pose: Isometry3<f64>) -> Option<Keyframe> {
        let previous = self.pose;
        self.pose = pose;
        self.motion = if self.frames == 0 {
            SweepMotion::zero()
        } else {
            SweepMotion::per_sweep(&previous, &self.pose, self.sweeps)
        };
        let corrected = if self.config.deskew { self.motion } else { SweepMotion::zero() };
        let index = self.frames;
        let placed = |f: &features::Feature| (corrected.compensate(&f.point, f.phase), ScanLine::new(index, f.ring));
        self.edge_map.insert(raw.edges.iter().map(placed), &self.pose);
        self.plane_map.insert(raw.planes.iter().map(placed), &self.pose);
        let centre = Point3::from(self.pose.translation.vector);
        self.edge_map.crop_and_rebuild(&centre);
        self.plane_map.crop_and_rebuild(&centre);
        self.update_points(scan, &corrected, &centre);
        let keyframe = self.keyframe(scan, &corrected);
        if self.frames == 0 && self.config.deskew {
            self.first = Some(raw.clone());
        }
        self.frames += 1;
        self.since_reset += 1;
        self.last_sweeps = self.sweeps;
        keyframe
    }

    /// The scan, compensated with `motion`, enters the local map of points at the current pose (the
    /// map made at the first scan's scale), and the map follows the robot; before a dense fit was
    /// wanted, the scan is only kept as the last one.
    fn update_points(&mut self, scan: &PointCloud, motion: &SweepMotion, centre: &Point3<f64>) {
        if !self.points_wanted {
            let stride = scan.len().div_ceil(SEED_POINTS).max(1);
            let seed = scan.select(&(0..scan.len()).step_by(stride).collect::<Vec<_>>());
            self.last_scan = Some((seed, *motion, self.pose));
            return;
        }
        let Some(scale) = self.points.as_ref().map(dense::PointMap::scale).or_else(|| dense::Scale::of(&scan.points))
        else {
            return;
        };
        let thinned = self.thinned(scan, motion, scale.map_grid());
        let map = self.points.get_or_insert_with(|| dense::PointMap::new(scale));
        map.insert(&thinned, &self.pose);
        map.crop(centre);
    }

    /// A fit judged good: the motion model and the health history learn from it, and the scan
    /// enters the map.
    fn accept(&mut self, scan: &PointCloud, raw: &Features, located: &Located, fit: Fit) -> Option<Keyframe> {
        let pose = located.estimate.pose;
        // The scan after the first (or after a reset) was predicted without a measured velocity:
        // its error says nothing about the prediction.
        if self.since_reset >= 2 {
            self.model.observe(&located.predicted, &pose, &(self.pose.inverse() * pose));
            let carried = |sweeps: f64| self.pose * cloud::se3::exp(&(self.motion.0 * sweeps));
            self.model.compare(&carried(self.sweeps), &carried(self.last_sweeps), &pose);
        }
        // The health history is of the feature fit's matches; a dense fit says nothing of them.
        if fit == Fit::Features {
            self.health.accept(share(&located.estimate, raw));
        }
        self.update_map(scan, raw, pose)
    }

    /// A lost scan: its best pose is reported, but its features stay out of the map (they would
    /// corrupt it) and the velocity is kept for the next scan's prediction.
    fn skip(&mut self, pose: Isometry3<f64>) -> Option<Keyframe> {
        self.pose = pose;
        self.frames += 1;
        None
    }

    /// Stage 1 and the pose (eq. 4): the features compensated with the predicted motion, then, while
    /// the estimate says the sweep moved otherwise, with the estimated one (see
    /// [`OdometryConfig::deskew_rounds`]).
    fn estimate(&self, raw: &Features, predicted: Isometry3<f64>) -> Fitted {
        let mut searches = solver::Neighbourhoods::new(raw.edges.len(), raw.planes.len());
        let mut solve = |motion: &SweepMotion, from: Isometry3<f64>| {
            self.fit(raw, motion, from, &self.config.solver, &mut searches)
        };
        // Against the first scan, uncompensated in the map, the second is fitted uncompensated
        // too: alike distortions cancel, where compensating one side only turns the fit further
        // the faster the robot turns. Both are compensated once the fit measured the motion.
        if !self.config.deskew || self.first.is_some() {
            let estimate = solve(&SweepMotion::zero(), predicted);
            return Fitted { estimate, motion: SweepMotion::zero() };
        }
        let mut motion = self.motion;
        let mut estimate = solve(&motion, predicted);
        for _ in 1..self.config.deskew_rounds {
            let mut measured = SweepMotion::per_sweep(&self.pose, &estimate.pose, self.sweeps);
            measured.0.fixed_rows_mut::<3>(0).copy_from(&motion.0.fixed_rows::<3>(0));
            if motion.difference_at(&measured, 10.0) <= self.config.deskew_tolerance {
                break;
            }
            motion = measured;
            estimate = solve(&motion, estimate.pose);
        }
        Fitted { estimate, motion }
    }

    /// The features compensated with `motion`, fitted to the maps from `from` (eq. 4).
    fn fit(
        &self,
        raw: &Features,
        motion: &SweepMotion,
        from: Isometry3<f64>,
        config: &SolverConfig,
        searches: &mut solver::Neighbourhoods,
    ) -> solver::Estimate {
        let edges = deskew::compensate(&raw.edges, motion);
        let planes = deskew::compensate(&raw.planes, motion);
        solver::estimate(&edges, &planes, &self.edge_map, &self.plane_map, from, config, searches)
    }

    /// A keyframe when the robot moved or turned enough since the last one (the first scan always is).
    fn keyframe(&mut self, scan: &PointCloud, motion: &SweepMotion) -> Option<Keyframe> {
        let kc = &self.config.keyframes;
        if let Some(last) = &self.last_keyframe {
            let d = last.inverse() * self.pose;
            if d.translation.vector.norm() < kc.distance && d.rotation.angle().to_degrees() < kc.angle_deg {
                return None;
            }
        }
        let deskewed = deskew::cloud(scan, motion, self.config.scan_period);
        let cloud = cloud::voxel::downsample(&deskewed, kc.voxel).unwrap_or(deskewed);
        self.last_keyframe = Some(self.pose);
        let seq = self.keyframes;
        self.keyframes += 1;
        Some(Keyframe { seq, frame: self.frames, pose: self.pose, cloud })
    }
}
