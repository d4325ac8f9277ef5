//! A pose graph with known true poses, for tests and the benchmark: a robot drives laps of a
//! wavy ring, so it revisits every place; odometry edges join consecutive poses, loop edges join
//! poses at the same place on different laps, both measured with Gaussian noise.
//!
//! The noise comes from the caller (a standard-normal source), so tests draw it from their seeded
//! generator and the benchmark from its own, and a seed always gives the same graph.

use std::f64::consts::TAU;

use crate::se3;
use nalgebra::{Isometry3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};

use super::{Edge, EdgeKind, PoseGraph};

/// Standard deviations of a measurement's noise, applied on the right: `Z = Z_true · exp(n)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Noise {
    /// Per translation axis, metres.
    pub translation_m: f64,
    /// Per rotation axis, radians.
    pub rotation_rad: f64,
}

impl Noise {
    /// `Ω = diag(1/σ²)`: the information of this noise, translation first.
    pub fn information(&self) -> Matrix6<f64> {
        let (t, r) = (self.translation_m.powi(-2), self.rotation_rad.powi(-2));
        Matrix6::from_diagonal(&Vector6::new(t, t, t, r, r, r))
    }

    /// One draw of `n`.
    fn sample(&self, normal: &mut impl FnMut() -> f64) -> Vector6<f64> {
        let (t, r) = (self.translation_m, self.rotation_rad);
        Vector6::new(t * normal(), t * normal(), t * normal(), r * normal(), r * normal(), r * normal())
    }
}

/// The shape and noise of a synthetic graph.
#[derive(Clone, Debug, PartialEq)]
pub struct SyntheticConfig {
    /// Number of poses. Default 5000.
    pub poses: usize,
    /// Poses per lap of the ring. Default 250 (about 1 m apart).
    pub poses_per_lap: usize,
    /// Mean radius of the ring, metres. Default 40 m; each lap runs up to 10 % inside or outside
    /// the previous ones, and the path rises and falls by 1 m.
    pub radius_m: f64,
    /// Noise of odometry edges. Default 2 cm and 0.002 rad (0.11°) per axis and step.
    pub odometry: Noise,
    /// Noise of loop edges. Default 5 cm and 0.005 rad (0.29°) per axis.
    pub loop_noise: Noise,
    /// From the second lap on, every `loop_every`-th pose gets a loop edge to the same place on an
    /// earlier lap. Default 20 (5 % of the poses).
    pub loop_every: usize,
}

impl Default for SyntheticConfig {
    fn default() -> Self {
        SyntheticConfig {
            poses: 5000,
            poses_per_lap: 250,
            radius_m: 40.0,
            odometry: Noise { translation_m: 0.02, rotation_rad: 0.002 },
            loop_noise: Noise { translation_m: 0.05, rotation_rad: 0.005 },
            loop_every: 20,
        }
    }
}

/// A synthetic graph, initialised by dead reckoning (the noisy odometry chained from the true
/// first pose), and the true poses.
#[derive(Clone, Debug)]
pub struct Synthetic {
    /// Poses at their dead-reckoning estimates, and the edges.
    pub graph: PoseGraph,
    /// True pose of each graph pose.
    pub truth: Vec<Isometry3<f64>>,
}

/// Generates the graph of `config`, drawing the noise from `normal` (standard normal samples).
pub fn generate(config: &SyntheticConfig, mut normal: impl FnMut() -> f64) -> Synthetic {
    let truth: Vec<Isometry3<f64>> = (0..config.poses).map(|k| true_pose(config, k)).collect();
    let mut graph = PoseGraph::new();
    graph.add_pose(truth.first().copied().unwrap_or_else(Isometry3::identity));
    for k in 1..config.poses {
        let odometry = measure(&truth, k - 1, k, &config.odometry, EdgeKind::Odometry, &mut normal);
        graph.add_pose(graph.poses()[k - 1] * odometry.measurement);
        graph.add_edge(odometry).expect("poses exist and the noise is finite");
    }
    let (lap, every) = (config.poses_per_lap.max(1), config.loop_every.max(1));
    for k in (lap..config.poses).filter(|k| k % every == 0) {
        // Cycle through the earlier laps, so loops span one lap and many.
        let laps_back = 1 + (k / every) % (k / lap);
        let loop_edge = measure(&truth, k - laps_back * lap, k, &config.loop_noise, EdgeKind::Loop, &mut normal);
        graph.add_edge(loop_edge).expect("poses exist and the noise is finite");
    }
    Synthetic { graph, truth }
}

/// The true pose number `k`: on a ring whose radius drifts from lap to lap, heading along it, with
/// gentle roll, pitch and height changes.
fn true_pose(config: &SyntheticConfig, k: usize) -> Isometry3<f64> {
    let theta = TAU * k as f64 / config.poses_per_lap.max(1) as f64;
    let radius = config.radius_m * (1.0 + 0.1 * (theta / 7.3).sin());
    let position = Vector3::new(radius * theta.cos(), radius * theta.sin(), (3.0 * theta).sin());
    let rotation =
        UnitQuaternion::from_euler_angles(0.05 * (2.0 * theta).sin(), 0.05 * (5.0 * theta).cos(), theta + TAU / 4.0);
    Isometry3::from_parts(Translation3::from(position), rotation)
}

/// The edge from `i` to `j` with its true value perturbed by `noise`.
fn measure(
    truth: &[Isometry3<f64>],
    i: usize,
    j: usize,
    noise: &Noise,
    kind: EdgeKind,
    normal: &mut impl FnMut() -> f64,
) -> Edge {
    let measurement = truth[i].inverse() * truth[j] * se3::exp(&noise.sample(normal));
    Edge { from: i, to: j, measurement, information: noise.information(), kind }
}
