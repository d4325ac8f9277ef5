//! The robot's keyframe pose graph: one pose per keyframe, an odometry edge between consecutive
//! keyframes, an edge per accepted loop; optimised ([`cloud::pose_graph`]) whenever the accepted
//! loops change, and followed by odometry in between.

use cloud::se3;
use nalgebra::{Isometry3, Matrix6};
use serde::{Deserialize, Serialize};

use cloud::pose_graph::{Edge, EdgeKind, OdometryNoise, PoseGraph, PoseGraphConfig, PoseGraphError, Report};

/// How the graph weighs odometry and is optimised.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GraphConfig {
    /// Odometry translation error per metre between keyframes (m/m). Default 0.01: F-LOAM and
    /// KISS-ICP drift ~1 % on KITTI, and a loop is what corrects that much.
    pub odometry_drift: f64,
    /// Odometry rotation error per metre between keyframes (deg/m). Default 0.01 °/m.
    pub odometry_rotation_deg_per_m: f64,
    /// Least odometry translation deviation of an edge (m): keyframes a turn apart without travel
    /// are not exact either. Default 0.01 m.
    pub odometry_min_sigma_m: f64,
    /// Least odometry rotation deviation of an edge (deg). Default 0.1°.
    pub odometry_min_sigma_deg: f64,
    /// The optimiser (its loop kernel keeps a wrong loop from pulling the whole graph).
    pub optimizer: PoseGraphConfig,
}

impl Default for GraphConfig {
    fn default() -> Self {
        GraphConfig {
            odometry_drift: 0.01,
            odometry_rotation_deg_per_m: 0.01,
            odometry_min_sigma_m: 0.01,
            odometry_min_sigma_deg: 0.1,
            optimizer: PoseGraphConfig::default(),
        }
    }
}

impl GraphConfig {
    /// The information of an odometry edge over `step` (diagonal, tangent `[ρ; φ]`).
    fn odometry_information(&self, step: &Isometry3<f64>) -> Matrix6<f64> {
        let noise = OdometryNoise {
            drift: self.odometry_drift,
            rotation_deg_per_m: self.odometry_rotation_deg_per_m,
            min_sigma_m: self.odometry_min_sigma_m,
            min_sigma_deg: self.odometry_min_sigma_deg,
        };
        noise.information(step)
    }
}

/// The keyframe poses: optimised when loops changed, odometry-propagated since.
#[derive(Clone, Debug, Default)]
pub struct KeyframeGraph {
    poses: Vec<Isometry3<f64>>,
    revision: u64,
}

impl KeyframeGraph {
    /// The keyframe poses (odometry frame, corrected by the loops), by keyframe index.
    pub fn poses(&self) -> &[Isometry3<f64>] {
        &self.poses
    }

    /// How many optimisations have run.
    pub fn revision(&self) -> u64 {
        self.revision
    }

    /// Appends the next keyframe at odometry pose `odometry`, placed after the previous one (at
    /// odometry pose `previous`) by the odometry's motion between them.
    pub fn extend(&mut self, previous: Option<&Isometry3<f64>>, odometry: &Isometry3<f64>) {
        let pose = match (self.poses.last(), previous) {
            (Some(last), Some(previous)) => follow(last, previous, odometry),
            _ => *odometry,
        };
        self.poses.push(pose);
    }

    /// Optimises the graph of `odometry` (one pose per keyframe) and `loops` from the current poses;
    /// the first keyframe stays where it is.
    pub fn optimise(
        &mut self,
        odometry: &[Isometry3<f64>],
        loops: &[Edge],
        config: &GraphConfig,
    ) -> Result<Report, PoseGraphError> {
        let mut graph = build(&self.poses, odometry, loops, config)?;
        let report = graph.optimize(&config.optimizer)?;
        self.poses.copy_from_slice(graph.poses());
        self.revision += 1;
        Ok(report)
    }
}

/// Where a pose the odometry put at `odometry` goes when the keyframe it follows, at odometry pose
/// `odometry_keyframe`, was optimised to `keyframe`: it moves rigidly with the keyframe.
pub fn follow(
    keyframe: &Isometry3<f64>,
    odometry_keyframe: &Isometry3<f64>,
    odometry: &Isometry3<f64>,
) -> Isometry3<f64> {
    keyframe * (odometry_keyframe.inverse() * odometry)
}

/// The pose graph of keyframes at `poses` with odometry poses `odometry` (an edge between each
/// consecutive pair) and `loops` (edges of kind [`EdgeKind::Loop`]).
pub fn build(
    poses: &[Isometry3<f64>],
    odometry: &[Isometry3<f64>],
    loops: &[Edge],
    config: &GraphConfig,
) -> Result<PoseGraph, PoseGraphError> {
    let mut graph = PoseGraph::new();
    for pose in poses {
        graph.add_pose(*pose);
    }
    for k in 1..odometry.len().min(poses.len()) {
        let step = odometry[k - 1].inverse() * odometry[k];
        let information = config.odometry_information(&step);
        graph.add_edge(Edge { from: k - 1, to: k, measurement: step, information, kind: EdgeKind::Odometry })?;
    }
    for l in loops {
        graph.add_edge(l.clone())?;
    }
    Ok(graph)
}

/// The SE(3) distance of a step, for the path length: its translation.
pub fn step_length(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    se3::pose_error(b, a).translation_m
}
