//! The joint pose graph (beyond the paper): every merged robot's keyframes in one graph, so robots
//! correct each other's drift instead of each being moved by one rigid transform.
//!
//! The rigid merge ([`crate::merge`]) places each robot's map by one transform `Gᵣ`; a map bent by
//! its robot's drift can then agree with the others only where the transform was found. Here each
//! keyframe `k` of robot `r` is a pose of its own, starting at
//!
//! ```text
//! Xᵣₖ = Gᵣ · Pᵣₖ                                                                    (1)
//! ```
//!
//! (`Pᵣₖ` the robot's loop-closed keyframe pose in its odometry frame), joined by
//!
//! - **odometry edges** between consecutive keyframes of a robot, `Z = Pᵣ,ₖ₋₁⁻¹ Pᵣₖ`, weighed by
//!   [`JointConfig::odometry`] (drift grows with the distance travelled, as a random walk's below a
//!   metre: [`cloud::pose_graph::OdometryNoise::sigmas_along_path`]);
//! - **inter-robot edges** ([`constraints`]): a keyframe of one robot registered (VGICP) onto the
//!   submap around the nearest keyframe of another, from where (1) puts it; `Z` is the registered
//!   pose of the one in the frame of the other, weighed by [`JointConfig::sigma_m`] /
//!   [`JointConfig::sigma_deg`], grown with the distance between the two keyframes
//!   ([`JointConfig::sigma_growth`]), under the optimiser's robust loop kernel, and kept only where
//!   they agree with each other ([`consistency`]: per pair of robots, the largest set that does).
//!
//! The first keyframe of the reference robot is held (the global frame is the rigid merge's); a
//! robot that no inter-robot edge links to the reference, directly or through others, keeps its
//! rigid placement. The cost is the pose graph's, `½ Σₑ ρₑ(eₑᵀ Ωₑ eₑ)`
//! ([`cloud::pose_graph`], GTSAM's).

pub mod consistency;
pub mod constraints;

use std::sync::Arc;
use std::time::Duration;

use cloud::PointCloud;
use cloud::pose_graph::{
    Edge, EdgeKind, OdometryNoise, PoseGraph, PoseGraphConfig, PoseGraphError, Report, diagonal_information,
};
use cloud::registration::{Method, RegistrationConfig};
use cloud::stopwatch::Stopwatch;
use nalgebra::{Isometry3, Matrix6};

pub use constraints::{Constraint, KeyframeRef};

/// One merged robot as the joint graph sees it.
#[derive(Clone, Debug)]
pub struct RobotPath {
    /// `Gᵣ`: where the rigid merge placed the robot's odometry frame in the global frame.
    pub placement: Isometry3<f64>,
    /// `Pᵣₖ`: keyframe poses in the robot's odometry frame (its loop-closed graph), in order.
    pub poses: Vec<Isometry3<f64>>,
    /// Keyframe clouds in the sensor frame, one per pose.
    pub clouds: Vec<Arc<PointCloud>>,
}

impl RobotPath {
    /// `Xᵣₖ` of (1): keyframe `k` in the global frame as the rigid merge places it.
    pub fn placed(&self, k: usize) -> Isometry3<f64> {
        self.placement * self.poses[k]
    }
}

/// Settings of the joint graph; defaults for robot maps of the simulated and KITTI kind (10-30 m
/// of sensor range, keyframes about a metre apart).
#[derive(Clone, Debug, PartialEq)]
pub struct JointConfig {
    /// How far the robots' odometry may be off between keyframes. Default the robots' own
    /// keyframe graph's: 1 % of the distance, 0.01 deg/m, at least 1 cm and 0.1 deg over a metre,
    /// shrinking with the square root of shorter steps
    /// ([`OdometryNoise::sigmas_along_path`]): 0.45 cm and 0.045 deg for keyframes 0.2 m apart.
    /// With the least deviations per step, a robot keyed every sweep was held 2.2 times looser
    /// than one keyed every metre, and on the load bench's 16 robots (exact maps, keyed every
    /// sweep) the joint graph bent them by 3.4 cm against 2.7.
    pub odometry: OdometryNoise,
    /// Keyframes of two robots at most this far apart in the global frame, by (1), are registered
    /// onto each other, metres. Default 10: well inside a LiDAR's range, so the two scans share
    /// most of what they see.
    pub reach: f64,
    /// A robot's keyframes are tried against the others at least this far apart along its path,
    /// metres. Default 0.8: about an edge per metre travelled, between which the odometry is good to a
    /// centimetre (a robot that sends a keyframe per sweep, 0.2 m apart at 2 m/s, would otherwise
    /// cost five registrations where one does).
    pub spacing: f64,
    /// Keyframes within this distance along the target robot's path, either side of the target
    /// keyframe, join its submap, those at least [`JointConfig::spacing`] apart, metres. Default 1:
    /// three sweeps over 2 m of path at any keyframe rate. A single sweep is sparse far out, and its
    /// rings on the ground are circles around one centre that VGICP aligns with the source's own:
    /// on the load bench's 10 Hz keyframes (0.2 m apart) two keyframes either side (0.8 m of path)
    /// registered keyframes 3-10 m apart 0.4-0.6 deg and 2-3 cm off the truth, 1 m of path 0.23 deg
    /// and 1.2 cm at the median. Wider is better on exact poses (2 m: 0.11 deg) but gathers the
    /// target robot's own local errors: on the simulated warehouse-small, where robot 1's keyframes
    /// come from 46 closed loops, robot 2's joint ATE was 12.4-12.6 cm at 2 m against 8.1 at 1 m
    /// and 8.5 with two keyframes either side.
    pub window: f64,
    /// Voxel the keyframes are downsampled to for the registration, metres. Default 0.25
    /// (small_gicp's downsampling for LiDAR scans).
    pub voxel: f32,
    /// The keyframe-to-submap VGICP. Default 1 m voxels and correspondences, one coarser level.
    pub registration: RegistrationConfig,
    /// A registration may move a keyframe at most this far from where (1) put it, metres. Default
    /// 1.0: the rigid merge was checked; more is a slide into a look-alike structure.
    pub max_translation: f64,
    /// A registration may turn a keyframe at most this much from where (1) put it, degrees.
    /// Default 3.
    pub max_rotation_deg: f64,
    /// Least share of the keyframe's points with a correspondence in the submap. Default 0.5.
    pub min_overlap: f64,
    /// Deviation of the translation of an inter-robot edge between keyframes at the same place,
    /// metres. Default 0.01: keyframes of two robots on the simulated campus, at their true poses,
    /// less than a metre apart registered 0.2-0.5 cm and 0.03-0.14 deg from the truth.
    pub sigma_m: f64,
    /// Deviation of the rotation of an inter-robot edge between keyframes at the same place,
    /// degrees. Default 0.1.
    pub sigma_deg: f64,
    /// Both deviations grow by this many times themselves for every metre between the two
    /// keyframes: `σ(d) = σ (1 + g d)` (4). Default 0.5 (3 cm and 0.3 deg at 4 m): there,
    /// keyframes 1-5 m apart registered 0.1-2.1 cm and 0.03-0.49 deg from the truth, 5-10 m apart
    /// 0.8-3.3 cm and 0.11-0.58 deg (the two scans share less, and what they share lies farther
    /// from the keyframe). Weighed alike (3 cm, 0.3 deg), the edges bent the exact maps of the load
    /// bench's 16 robots by 2.7 cm; by (4), 1.0 cm (0.5 cm and 0.05 deg growing by 1 a metre: 1.05
    /// cm, but the simulated warehouse-large's odometry-built maps 0.4 cm further off the truth).
    pub sigma_growth: f64,
    /// Deviation an edge is given in the consistency check ([`consistency`]), whatever the
    /// distance between its keyframes, metres. Default 0.03. The check is there to drop edges that
    /// slid by decimetres; with (4) there, it also dropped 29 of the simulated warehouse-large's
    /// 191 edges, which lay a few centimetres off the rest where the robots' own maps bend.
    pub consistency_sigma_m: f64,
    /// Deviation of the rotation an edge is given in the consistency check, degrees. Default 0.3.
    pub consistency_sigma_deg: f64,
    /// Two edges between the same robots agree when (3) of [`consistency`] differs by at most this
    /// many deviations. Default 3.
    pub consistency_sigmas: f64,
    /// Fewest mutually consistent edges that join two robots. Default 3: a lone edge, or two that
    /// agree by chance, could be wrong with nothing to tell.
    pub min_consistent: usize,
    /// Deviation of an odometry step's roll and pitch (rotations about the keyframe's x and y
    /// axes, horizontal for a level sensor), degrees. Default 0.001: held as the robot has them.
    /// A robot's keyframe tilts jitter by tenths of a degree; given the odometry's rotation
    /// deviation there (0.1 deg a step), the graph met an edge's few centimetres by tilting a
    /// keyframe, which lifted the chain beyond it: on the simulated warehouse-large the robots'
    /// common vertical drift grew from 6.7 to 11 cm, with the true relative poses as the edges too
    /// (9.7 cm with their rotations ignored); held, 6.9-7.1 cm.
    pub tilt_sigma_deg: f64,
    /// The optimiser; its loop kernel (Cauchy, k = 3) applies to the inter-robot edges.
    pub optimizer: PoseGraphConfig,
}

impl Default for JointConfig {
    fn default() -> Self {
        Self {
            odometry: OdometryNoise { drift: 0.01, rotation_deg_per_m: 0.01, min_sigma_m: 0.01, min_sigma_deg: 0.1 },
            reach: 10.0,
            spacing: 0.8,
            window: 1.0,
            voxel: 0.25,
            registration: RegistrationConfig {
                voxel_resolution: 1.0,
                max_correspondence_distance: 1.0,
                coarse_levels: 1,
                ..RegistrationConfig::default()
            },
            max_translation: 1.0,
            max_rotation_deg: 3.0,
            min_overlap: 0.5,
            sigma_m: 0.01,
            sigma_deg: 0.1,
            sigma_growth: 0.5,
            consistency_sigma_m: 0.03,
            consistency_sigma_deg: 0.3,
            consistency_sigmas: 3.0,
            min_consistent: 3,
            tilt_sigma_deg: 0.001,
            optimizer: PoseGraphConfig::default(),
        }
    }
}

impl JointConfig {
    /// The registration method of the inter-robot edges.
    pub const METHOD: Method = Method::Vgicp;

    /// The information of an odometry edge over `step`: [`JointConfig::odometry`]'s, its roll and
    /// pitch held by [`JointConfig::tilt_sigma_deg`].
    fn odometry_information(&self, step: &Isometry3<f64>) -> Matrix6<f64> {
        let (sigma_m, sigma_deg) = self.odometry.sigmas_along_path(step);
        let mut information = diagonal_information(sigma_m, sigma_deg);
        let tilt = 1.0 / self.tilt_sigma_deg.to_radians().powi(2);
        information[(3, 3)] = tilt;
        information[(4, 4)] = tilt;
        information
    }

    /// The deviations (4) of `edge`, metres and degrees.
    pub fn edge_sigmas(&self, edge: &Constraint) -> (f64, f64) {
        let grown = 1.0 + self.sigma_growth * edge.measurement.translation.vector.norm();
        (self.sigma_m * grown, self.sigma_deg * grown)
    }

    fn validate(&self) -> Result<(), JointError> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        let ok = positive(self.reach)
            && self.spacing.is_finite()
            && self.spacing >= 0.0
            && self.window.is_finite()
            && self.window >= 0.0
            && self.voxel.is_finite()
            && self.voxel > 0.0
            && positive(self.max_translation)
            && positive(self.max_rotation_deg)
            && (0.0..=1.0).contains(&self.min_overlap)
            && positive(self.sigma_m)
            && positive(self.sigma_deg)
            && positive(self.consistency_sigma_m)
            && positive(self.consistency_sigma_deg)
            && self.sigma_growth.is_finite()
            && self.sigma_growth >= 0.0
            && positive(self.consistency_sigmas)
            && positive(self.tilt_sigma_deg);
        ok.then_some(()).ok_or(JointError::InvalidConfig)
    }
}

/// What the joint graph made of the robots.
#[derive(Clone, Debug)]
pub struct JointSolution {
    /// Per robot, its keyframes in the global frame: optimised where the robot is joined, its
    /// rigid placement (1) where not.
    pub poses: Vec<Vec<Isometry3<f64>>>,
    /// Per robot, whether inter-robot edges link it to the reference (the reference itself is).
    pub joined: Vec<bool>,
    /// The inter-robot edges that passed their registration's checks.
    pub registered: usize,
    /// Those of them that agree with each other: the ones in the graph.
    pub constraints: Vec<Constraint>,
    /// The optimisation; `None` when no edge links any robot to the reference.
    pub report: Option<Report>,
    /// Wall time of each step.
    pub timing: JointTiming,
}

/// Wall time of the steps of [`solve`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct JointTiming {
    /// Finding and registering the inter-robot edges ([`constraints`]).
    pub edges: Duration,
    /// Keeping those that agree ([`consistency`]).
    pub consistency: Duration,
    /// Building and optimising the graph.
    pub optimise: Duration,
}

/// Why the joint graph could not be built.
#[derive(Debug, thiserror::Error)]
pub enum JointError {
    /// A robot has a different number of keyframe poses and clouds.
    #[error("robot {robot}: {poses} keyframe poses but {clouds} clouds")]
    MismatchedKeyframes {
        /// Index of the robot in the input.
        robot: usize,
        /// Poses given.
        poses: usize,
        /// Clouds given.
        clouds: usize,
    },
    /// The reference is not one of the robots.
    #[error("reference {reference} is not one of the {robots} robots")]
    UnknownReference {
        /// The index asked for.
        reference: usize,
        /// Robots given.
        robots: usize,
    },
    /// A setting is out of range.
    #[error(
        "invalid joint-graph configuration: reach, voxel, limits and deviations must be positive, spacing, window and sigma_growth finite and not negative, overlap within 0-1"
    )]
    InvalidConfig,
    /// A pose or edge was refused, or the optimisation failed.
    #[error(transparent)]
    PoseGraph(#[from] PoseGraphError),
}

/// Optimises the robots' keyframes jointly, the first keyframe of robot `reference` held: finds
/// the inter-robot edges ([`constraints`]), keeps those that agree ([`consistency`]) and
/// [`optimise`]s.
pub fn solve(paths: &[RobotPath], reference: usize, config: &JointConfig) -> Result<JointSolution, JointError> {
    check(paths, reference, config)?;
    let mut watch = Stopwatch::start();
    let registered = constraints::find(paths, config);
    let edges = watch.lap();
    let kept = consistency::consistent(paths, &registered, config);
    let consistency = watch.lap();
    let mut solution = optimise_checked(paths, reference, kept, config)?;
    solution.registered = registered.len();
    solution.timing = JointTiming { edges, consistency, optimise: watch.lap() };
    Ok(solution)
}

/// The joint graph of `paths` with the inter-robot edges `constraints` as given, optimised.
pub fn optimise(
    paths: &[RobotPath],
    reference: usize,
    constraints: Vec<Constraint>,
    config: &JointConfig,
) -> Result<JointSolution, JointError> {
    check(paths, reference, config)?;
    let watch = Stopwatch::start();
    let mut solution = optimise_checked(paths, reference, constraints, config)?;
    solution.timing.optimise = watch.elapsed();
    Ok(solution)
}

/// [`optimise`] on input [`check`] passed.
fn optimise_checked(
    paths: &[RobotPath],
    reference: usize,
    constraints: Vec<Constraint>,
    config: &JointConfig,
) -> Result<JointSolution, JointError> {
    let joined = joined(reference, &constraints, paths);
    let mut poses: Vec<Vec<Isometry3<f64>>> =
        paths.iter().map(|p| (0..p.poses.len()).map(|k| p.placed(k)).collect()).collect();
    let report = if joined.iter().filter(|&&j| j).count() > 1 {
        let (mut graph, first) = build(paths, reference, &joined, &constraints, config)?;
        let report = graph.optimize(&config.optimizer)?;
        for (r, start) in first.iter().enumerate() {
            if let Some(start) = start {
                let n = poses[r].len();
                poses[r].copy_from_slice(&graph.poses()[*start..*start + n]);
            }
        }
        Some(report)
    } else {
        None
    };
    Ok(JointSolution {
        poses,
        joined,
        registered: constraints.len(),
        constraints,
        report,
        timing: JointTiming::default(),
    })
}

/// Refuses a configuration out of range, an unknown reference and robots whose keyframe poses and
/// clouds do not pair up.
fn check(paths: &[RobotPath], reference: usize, config: &JointConfig) -> Result<(), JointError> {
    config.validate()?;
    if reference >= paths.len() {
        return Err(JointError::UnknownReference { reference, robots: paths.len() });
    }
    for (robot, p) in paths.iter().enumerate() {
        if p.poses.len() != p.clouds.len() {
            return Err(JointError::MismatchedKeyframes { robot, poses: p.poses.len(), clouds: p.clouds.len() });
        }
    }
    Ok(())
}

/// Which robots inter-robot edges link to the reference, directly or through others (a robot
/// without keyframes takes no part).
fn joined(reference: usize, constraints: &[Constraint], paths: &[RobotPath]) -> Vec<bool> {
    let mut joined = vec![false; paths.len()];
    joined[reference] = !paths[reference].poses.is_empty();
    let mut grew = true;
    while grew {
        grew = false;
        for c in constraints {
            let (a, b) = (c.target.robot, c.source.robot);
            if joined[a] != joined[b] {
                joined[a] = true;
                joined[b] = true;
                grew = true;
            }
        }
    }
    joined
}

/// The graph of the joined robots: poses (1), odometry edges, inter-robot edges, the reference's
/// first keyframe held. Returns it with each joined robot's first pose index.
fn build(
    paths: &[RobotPath],
    reference: usize,
    joined: &[bool],
    constraints: &[Constraint],
    config: &JointConfig,
) -> Result<(PoseGraph, Vec<Option<usize>>), JointError> {
    let mut graph = PoseGraph::new();
    let mut first = vec![None; paths.len()];
    for (r, path) in paths.iter().enumerate().filter(|(r, _)| joined[*r]) {
        let start = graph.poses().len();
        first[r] = Some(start);
        for k in 0..path.poses.len() {
            graph.add_pose(path.placed(k));
        }
        for k in 1..path.poses.len() {
            let step = path.poses[k - 1].inverse() * path.poses[k];
            let information = config.odometry_information(&step);
            let (from, to) = (start + k - 1, start + k);
            graph.add_edge(Edge { from, to, measurement: step, information, kind: EdgeKind::Odometry })?;
        }
    }
    let node = |k: &KeyframeRef| first[k.robot].map(|s| s + k.keyframe);
    for c in constraints {
        if let (Some(from), Some(to)) = (node(&c.target), node(&c.source)) {
            let (sigma_m, sigma_deg) = config.edge_sigmas(c);
            let information = diagonal_information(sigma_m, sigma_deg);
            graph.add_edge(Edge { from, to, measurement: c.measurement, information, kind: EdgeKind::Loop })?;
        }
    }
    graph.fix(first[reference].expect("the reference is joined"))?;
    Ok((graph, first))
}
