//! A-LOAM odometry (Zhang & Singh, "LOAM: Lidar Odometry and Mapping in Real-time", RSS 2014, as
//! HKUST's A-LOAM implements it) beside F-LOAM, selected by [`OdometryConfig::method`]: the paper's
//! MR-ALOAM and EMR-ALOAM systems run it.
//!
//! Per sweep, in [`Odometry::register_aloam`]:
//!
//! 1. features: F-LOAM's extractor twice, once as the sweep's sharp and flat points (the
//!    configuration's features), once as its "less sharp" and "less flat" points (more edges per
//!    sector, finer thinning: [`AloamConfig`]), which the next sweep matches against;
//! 2. scan-to-scan odometry (LOAM section V, Algorithm 1): the sharp and flat points, deskewed by
//!    linear interpolation of the sweep's motion (eq. 4), matched point-to-line (eq. 2) and
//!    point-to-plane (eq. 3) against the previous sweep's less sharp and less flat points, the
//!    stacked distances (eq. 9) minimised by F-LOAM's Gauss-Newton ([`solver`], in place of the
//!    paper's Levenberg-Marquardt step, eq. 10); twice, the second time deskewed with the first
//!    estimate, as A-LOAM's two optimisation rounds;
//! 3. scan-to-map refinement (LOAM section VI) every [`AloamConfig::map_every`] sweeps (every
//!    sweep by default, as A-LOAM's launch files run it): the same
//!    features against F-LOAM's local maps ([`local_map`]), which only refined sweeps enter; in
//!    between, the pose is the last refined pose composed with the scan-to-scan increments
//!    (A-LOAM's `T_map_odom · T_odom_curr`);
//! 4. keyframes as F-LOAM makes them.
//!
//! Deskewing is linear only: no F-LOAM stage 2 and no repeated stage 1 against the map.
//!
//! [`solver`]: super::solver
//! [`local_map`]: super::local_map

use std::str::FromStr;

use cloud::PointCloud;
use cloud::stopwatch::Stopwatch;
use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

use super::deskew::{self, SweepMotion};
use super::features::{self, Feature, Features};
use super::local_map::{FeatureMap, MAX_POINTS_PER_VOXEL, ScanLine};
use super::{FeatureConfig, Fit, Frame, FrameTimings, MapConfig, Odometry, OdometryError, Start, solver};

/// Which odometry registers the scans.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// F-LOAM: scan-to-map every sweep, two-stage distortion compensation (the default).
    #[default]
    Floam,
    /// A-LOAM: scan-to-scan every sweep, scan-to-map every [`AloamConfig::map_every`] sweeps,
    /// linear deskewing.
    Aloam,
}

impl Method {
    /// The lower-case name used on command lines and in files.
    pub fn name(self) -> &'static str {
        match self {
            Method::Floam => "floam",
            Method::Aloam => "aloam",
        }
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A method name that is neither floam nor aloam.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("unknown odometry method {0:?}: expected floam or aloam")]
pub struct UnknownMethod(pub String);

impl FromStr for Method {
    type Err = UnknownMethod;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        [Method::Floam, Method::Aloam].into_iter().find(|m| m.name() == s).ok_or_else(|| UnknownMethod(s.to_owned()))
    }
}

/// A-LOAM's parameters (used only with [`Method::Aloam`]).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct AloamConfig {
    /// Sweeps per scan-to-map refinement. Default 1: A-LOAM's launch files map every sweep
    /// (`mapping_skip_frame` 1; its mapping drops sweeps only when it falls behind). The LOAM
    /// paper's 1 Hz mapping (10) let the scan-to-scan chain drift 5-140 cm between refinements in
    /// the simulator, 6-100x F-LOAM's error, against 1.5-5x at 1.
    pub map_every: usize,
    /// Most "less sharp" edges per ring sector, the next sweep's edge targets. Default 20
    /// (A-LOAM keeps 20 less sharp points against 2 sharp ones per sector).
    pub target_edges_per_sector: usize,
    /// The less sharp points are thinned to one per voxel of this size (m). Default 0.1 m: a single
    /// sweep must still hold five points of an edge within a metre.
    pub target_edge_voxel: f32,
    /// The less flat points are thinned to one per voxel of this size (m). Default 0.2 m
    /// (A-LOAM's downsampling of the less flat cloud).
    pub target_plane_voxel: f32,
}

impl Default for AloamConfig {
    fn default() -> Self {
        AloamConfig { map_every: 1, target_edges_per_sector: 20, target_edge_voxel: 0.1, target_plane_voxel: 0.2 }
    }
}

impl AloamConfig {
    /// The extraction of the less sharp and less flat points: `features` with more edges and
    /// finer thinning.
    fn target_features(&self, features: &FeatureConfig) -> FeatureConfig {
        FeatureConfig {
            max_edges_per_sector: self.target_edges_per_sector,
            edge_voxel: self.target_edge_voxel,
            plane_voxel: self.target_plane_voxel,
            ..features.clone()
        }
    }

    /// The values that must be positive, named as in the configuration.
    pub(super) fn check(&self) -> Result<(), OdometryError> {
        let voxels = [
            ("aloam.target_edge_voxel", self.target_edge_voxel),
            ("aloam.target_plane_voxel", self.target_plane_voxel),
        ];
        if let Some((name, v)) = voxels.iter().find(|(_, v)| !(*v > 0.0 && v.is_finite())) {
            return Err(OdometryError::Config(format!("{name} must be positive, got {v}")));
        }
        if self.map_every == 0 {
            return Err(OdometryError::Config("aloam.map_every must be at least 1".into()));
        }
        Ok(())
    }
}

/// The previous sweep's less sharp and less flat points in its sweep-end frame, searchable.
struct SweepMaps {
    edges: FeatureMap,
    planes: FeatureMap,
}

/// What A-LOAM keeps between sweeps (beside the [`Odometry`]'s local maps and keyframes).
pub(super) struct AloamState {
    /// The previous sweep's targets; none before the first sweep.
    previous: Option<SweepMaps>,
    /// The scan-to-scan chain: the sensor at the last sweep end in the odometry's own frame.
    odometry: Isometry3<f64>,
    /// `T_map_odom`: the last refinement's correction of the chain.
    correction: Isometry3<f64>,
    /// Sweeps since the last refinement.
    since_refinement: usize,
}

impl AloamState {
    /// Nothing seen yet.
    pub(super) fn new() -> Self {
        AloamState {
            previous: None,
            odometry: Isometry3::identity(),
            correction: Isometry3::identity(),
            since_refinement: 0,
        }
    }
}

/// A sweep's features and targets.
struct Extracted {
    /// Sharp and flat points: matched against the previous sweep and the local maps.
    raw: Features,
    /// Less sharp and less flat points: the next sweep's targets.
    targets: Features,
    kind: features::FeatureKind,
}

impl Odometry {
    /// One sweep of A-LOAM (see the module's documentation).
    pub(super) fn register_aloam(&mut self, scan: &PointCloud) -> Result<Frame, OdometryError> {
        let mut watch = Stopwatch::start();
        let extracted = self.extract_aloam(scan)?;
        let features_ms = watch.lap_ms();
        let (increment, mut estimate) = self.scan_to_scan(&extracted.raw);
        // Eq. 4: points deskewed by linear interpolation of the sweep's estimated motion.
        let motion = if self.config.deskew {
            SweepMotion::per_sweep(&Isometry3::identity(), &increment, self.sweeps)
        } else {
            SweepMotion::zero()
        };
        let edges = deskew::compensate(&extracted.raw.edges, &motion);
        let planes = deskew::compensate(&extracted.raw.planes, &motion);
        self.aloam.odometry *= increment;
        let refine = self.frames == 0 || self.aloam.since_refinement + 1 >= self.config.aloam.map_every;
        let mut pose = self.aloam.correction * self.aloam.odometry;
        if refine {
            if self.frames > 0 {
                estimate = self.scan_to_map(&edges, &planes, pose);
                pose = estimate.pose;
            }
            self.aloam.correction = pose * self.aloam.odometry.inverse();
        }
        let registration_ms = watch.lap_ms();
        if refine {
            self.insert_refined(&edges, &planes, &pose);
        } else {
            self.aloam.since_refinement += 1;
        }
        self.aloam.previous = Some(sweep_maps(&extracted.targets, &motion, &self.config.features, &self.config.aloam));
        self.pose = pose;
        self.motion = motion;
        let keyframe = self.keyframe(scan, &motion);
        self.frames += 1;
        let timings = FrameTimings { features: features_ms, registration: registration_ms, map: watch.lap_ms() };
        Ok(Frame {
            timings,
            pose,
            edges: extracted.raw.edges.len(),
            planes: extracted.raw.planes.len(),
            iterations: estimate.iterations,
            degenerate: estimate.degenerate_directions > 0,
            conditioning: estimate.min_eigen_ratio,
            start: Start::Prediction,
            lost: false,
            feature_kind: extracted.kind,
            fit: Fit::Features,
            keyframe,
        })
    }

    /// The sweep's sharp and flat points (the configuration's features) and its less sharp and
    /// less flat ones (LOAM section V-A, eq. 1 for the smoothness).
    fn extract_aloam(&self, scan: &PointCloud) -> Result<Extracted, OdometryError> {
        let period = self.config.scan_period;
        let (raw, kind) = features::extract_any(scan, period, &self.config.features)?;
        let target_config = self.config.aloam.target_features(&self.config.features);
        let (targets, _) = features::extract_any(scan, period, &target_config)?;
        Ok(Extracted { raw, targets, kind })
    }

    /// Scan-to-scan odometry (LOAM section V, Algorithm 1): the motion since the last sweep end,
    /// from the constant-velocity guess; the identity for the first sweep.
    fn scan_to_scan(&self, raw: &Features) -> (Isometry3<f64>, solver::Estimate) {
        let Some(previous) = &self.aloam.previous else { return (Isometry3::identity(), solver::Estimate::first()) };
        let mut guess = cloud::se3::exp(&(self.motion.0 * self.sweeps));
        let mut searches = solver::Neighbourhoods::new(raw.edges.len(), raw.planes.len());
        let mut estimate = solver::Estimate::first();
        // Two rounds, each deskewing with the current estimate (eq. 4), as A-LOAM's two
        // optimisation rounds; eqs. 2, 3 and 9 are the solver's residuals.
        for _ in 0..2 {
            let motion = if self.config.deskew {
                SweepMotion::per_sweep(&Isometry3::identity(), &guess, self.sweeps)
            } else {
                SweepMotion::zero()
            };
            let edges = deskew::compensate(&raw.edges, &motion);
            let planes = deskew::compensate(&raw.planes, &motion);
            estimate = solver::estimate(
                &edges,
                &planes,
                &previous.edges,
                &previous.planes,
                guess,
                &self.config.solver,
                &mut searches,
            );
            guess = estimate.pose;
        }
        (guess, estimate)
    }

    /// Scan-to-map refinement (LOAM section VI): the deskewed features against the local maps
    /// from the chained pose.
    fn scan_to_map(&self, edges: &[Feature], planes: &[Feature], chained: Isometry3<f64>) -> solver::Estimate {
        let mut searches = solver::Neighbourhoods::new(edges.len(), planes.len());
        solver::estimate(edges, planes, &self.edge_map, &self.plane_map, chained, &self.config.solver, &mut searches)
    }

    /// A refined sweep enters the local maps, which follow the robot.
    fn insert_refined(&mut self, edges: &[Feature], planes: &[Feature], pose: &Isometry3<f64>) {
        let index = self.frames;
        let placed = |f: &Feature| (f.point, ScanLine::new(index, f.ring));
        self.edge_map.insert(edges.iter().map(placed), pose);
        self.plane_map.insert(planes.iter().map(placed), pose);
        let centre = Point3::from(pose.translation.vector);
        self.edge_map.crop_and_rebuild(&centre);
        self.plane_map.crop_and_rebuild(&centre);
        self.aloam.since_refinement = 0;
    }
}

/// The sweep's less sharp and less flat points, deskewed to its end (eq. 4), as the maps the next
/// sweep is matched against: sized to the points, searched from the first query on.
fn sweep_maps(targets: &Features, motion: &SweepMotion, features: &FeatureConfig, config: &AloamConfig) -> SweepMaps {
    let map = |points: &[Feature], voxel: f32| {
        let mut map = FeatureMap::new(MapConfig {
            voxel_size: voxel,
            points_per_voxel: MAX_POINTS_PER_VOXEL,
            min_point_distance: 0.0,
            radius: features.max_range * 2.0,
            rebuild_every: 1,
            max_voxels: points.len().max(1),
        });
        map.insert(
            points.iter().map(|f| (motion.compensate(&f.point, f.phase), ScanLine::new(0, f.ring))),
            &Isometry3::identity(),
        );
        map.crop_and_rebuild(&Point3::origin());
        map
    };
    SweepMaps {
        edges: map(&targets.edges, config.target_edge_voxel),
        planes: map(&targets.planes, config.target_plane_voxel),
    }
}
