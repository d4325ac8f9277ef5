//! F-LOAM odometry (Wang et al., IROS 2021, section III) with the paper's two-stage distortion
//! compensation. One call per scan, in [`Odometry::register`]:
//!
//! 1. features: per-ring smoothness (eq. 1), 6 sectors, edges and planes ([`features`]);
//! 2. stage 1: constant-velocity motion from the last frame (eq. 2) moves each feature to the sweep
//!    end by its own timestamp (eq. 3) ([`deskew`]);
//! 3. pose: scan-to-local-map point-to-line / point-to-plane matching (eq. 4) ([`solver`]);
//! 4. stage 2: the distortion is recomputed with the estimated motion and the features are corrected
//!    again before they enter the map;
//! 5. local map: edge and plane voxel maps cropped around the robot, k-d trees ([`local_map`]);
//! 6. keyframes every N metres or M degrees, carrying the deskewed, downsampled cloud.
//!
//! Every parameter and the presets are in [`config`]; [`pipeline`] runs the odometry over a source,
//! evaluates it against ground truth and writes the results.
//!
//! Poses are those of the sensor at the END of each sweep, in the odometry frame (the sensor frame at
//! the end of the first sweep).

pub mod config;
pub mod deskew;
pub mod features;
pub mod local_map;
pub mod pipeline;
pub mod solver;
pub mod stats;

use cloud::PointCloud;
use cloud::stopwatch::Stopwatch;
use nalgebra::{Isometry3, Point3};
use serde::Serialize;

pub use config::{FeatureConfig, KeyframeConfig, MapConfig, OdometryConfig, SolverConfig};
use deskew::SweepMotion;
use features::{FeatureError, Features};
use local_map::{FeatureMap, MAX_POINTS_PER_VOXEL, ScanLine};

/// A keyframe: the deskewed, downsampled scan at its pose.
#[derive(Clone, Debug)]
pub struct Keyframe {
    /// 0, 1, 2, ... in order.
    pub seq: u64,
    /// Index of the scan that made it.
    pub frame: usize,
    /// Sensor pose at the sweep end, odometry frame.
    pub pose: Isometry3<f64>,
    /// Motion-compensated cloud in the sweep-end sensor frame, voxel-downsampled.
    pub cloud: PointCloud,
}

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

/// The F-LOAM odometry state of one robot.
pub struct Odometry {
    config: OdometryConfig,
    frames: usize,
    pose: Isometry3<f64>,
    motion: SweepMotion,
    edge_map: FeatureMap,
    plane_map: FeatureMap,
    last_keyframe: Option<Isometry3<f64>>,
    keyframes: u64,
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
        Ok(Odometry {
            edge_map: FeatureMap::new(config.edge_map.clone()),
            plane_map: FeatureMap::new(config.plane_map.clone()),
            config,
            frames: 0,
            pose: Isometry3::identity(),
            motion: SweepMotion::zero(),
            last_keyframe: None,
            keyframes: 0,
        })
    }

    /// The configuration in use.
    pub fn config(&self) -> &OdometryConfig {
        &self.config
    }

    /// Registers one scan (with ring and per-point time channels) and returns its pose.
    pub fn register(&mut self, scan: &PointCloud) -> Result<Frame, OdometryError> {
        // The stages' parallel loops hand their work to rayon's pool and wait for it: called from
        // a thread outside the pool, each loop costs a worker's wake-up and a hand-over back, a
        // dozen per scan. Run on a worker, the scan pays for one.
        rayon::scope(|_| self.register_on_pool(scan))
    }

    /// [`Odometry::register`] on a worker of rayon's pool.
    fn register_on_pool(&mut self, scan: &PointCloud) -> Result<Frame, OdometryError> {
        let mut watch = Stopwatch::start();
        let raw = features::extract(scan, self.config.scan_period, &self.config.features)?;
        let features_ms = watch.lap_ms();
        let estimate = self.locate(&raw);
        let registration_ms = watch.lap_ms();
        let keyframe = self.update_map(scan, &raw, estimate.pose);
        let timings = FrameTimings { features: features_ms, registration: registration_ms, map: watch.lap_ms() };
        Ok(Frame {
            timings,
            pose: self.pose,
            edges: raw.edges.len(),
            planes: raw.planes.len(),
            iterations: estimate.iterations,
            degenerate: estimate.degenerate_directions > 0,
            conditioning: estimate.min_eigen_ratio,
            keyframe,
        })
    }

    /// Stage 1 and the pose, from the constant-velocity prediction (eq. 2); the first scan defines
    /// the odometry frame.
    fn locate(&self, raw: &Features) -> solver::Estimate {
        if self.frames == 0 {
            return solver::Estimate {
                pose: Isometry3::identity(),
                iterations: 0,
                edge_matches: 0,
                plane_matches: 0,
                degenerate_directions: 0,
                min_eigen_ratio: 1.0,
            };
        }
        let predicted = self.pose * cloud::se3::exp(&self.motion.0);
        self.estimate(raw, predicted)
    }

    /// Stage 2 and the local map: the sweep's motion is re-estimated from the new pose, corrects
    /// the features before they enter the maps, and the maps follow the robot; the keyframe if due.
    fn update_map(&mut self, scan: &PointCloud, raw: &Features, pose: Isometry3<f64>) -> Option<Keyframe> {
        let previous = self.pose;
        self.pose = pose;
        self.motion = if self.frames == 0 { SweepMotion::zero() } else { SweepMotion::between(&previous, &self.pose) };
        let corrected = if self.config.deskew { self.motion } else { SweepMotion::zero() };
        let index = self.frames;
        let placed = |f: &features::Feature| (corrected.compensate(&f.point, f.phase), ScanLine::new(index, f.ring));
        self.edge_map.insert(raw.edges.iter().map(placed), &self.pose);
        self.plane_map.insert(raw.planes.iter().map(placed), &self.pose);
        let centre = Point3::from(self.pose.translation.vector);
        self.edge_map.crop_and_rebuild(&centre);
        self.plane_map.crop_and_rebuild(&centre);
        let keyframe = self.keyframe(scan, &corrected);
        self.frames += 1;
        keyframe
    }

    /// Stage 1 and the pose (eq. 4): the features compensated with the predicted motion, then, while
    /// the estimate says the sweep moved otherwise, with the estimated one (see
    /// [`OdometryConfig::deskew_rounds`]).
    fn estimate(&self, raw: &Features, predicted: Isometry3<f64>) -> solver::Estimate {
        let mut searches = solver::Neighbourhoods::new(raw.edges.len(), raw.planes.len());
        let mut solve = |motion: &SweepMotion, from: Isometry3<f64>| {
            let edges = deskew::compensate(&raw.edges, motion);
            let planes = deskew::compensate(&raw.planes, motion);
            let (edge_map, plane_map) = (&self.edge_map, &self.plane_map);
            solver::estimate(&edges, &planes, edge_map, plane_map, from, &self.config.solver, &mut searches)
        };
        if !self.config.deskew {
            return solve(&SweepMotion::zero(), predicted);
        }
        let mut motion = self.motion;
        let mut estimate = solve(&motion, predicted);
        for _ in 1..self.config.deskew_rounds {
            let mut measured = SweepMotion::between(&self.pose, &estimate.pose);
            measured.0.fixed_rows_mut::<3>(0).copy_from(&motion.0.fixed_rows::<3>(0));
            if motion.difference_at(&measured, 10.0) <= self.config.deskew_tolerance {
                break;
            }
            motion = measured;
            estimate = solve(&motion, estimate.pose);
        }
        estimate
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
        let times = scan.time.as_deref().unwrap_or(&[]);
        let period = self.config.scan_period;
        let mut deskewed = scan.clone();
        if !motion.is_zero() {
            let table = motion.table();
            for (p, t) in deskewed.points.iter_mut().zip(times) {
                *p = table.compensate(p, t / period);
            }
        }
        let cloud = cloud::voxel::downsample(&deskewed, kc.voxel).unwrap_or(deskewed);
        self.last_keyframe = Some(self.pose);
        let seq = self.keyframes;
        self.keyframes += 1;
        Some(Keyframe { seq, frame: self.frames, pose: self.pose, cloud })
    }
}
