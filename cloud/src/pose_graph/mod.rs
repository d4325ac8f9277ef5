//! SE(3) pose-graph optimisation: poses joined by relative-pose measurements (odometry and loop
//! closures), optimised by Levenberg-Marquardt over a sparse Cholesky factorisation.
//!
//! The cost is GTSAM's: half the sum of the edges' squared Mahalanobis norms, each passed through
//! the robust kernel of its [`EdgeKind`],
//!
//! ```text
//! F(T) = ½ Σₑ ρₑ(eₑᵀ Ωₑ eₑ),   eₑ = log(Zₑ⁻¹ Tᵢ⁻¹ Tⱼ)                              (1)
//! ```
//!
//! with the workspace's one Lie convention ([`crate::se3`]): tangent `[ρ; φ]` translation first,
//! poses perturbed on the right. Ω is in that order too, which is also g2o's (translation then
//! rotation), so a g2o file's information matrix is used as it stands. The error and its
//! Jacobians are in [`residual`], robust kernels in [`kernel`], the sparse normal equations in
//! [`system`], Levenberg-Marquardt in [`solve`], the g2o text format in [`g2o`], and a synthetic
//! graph with known truth (tests, benchmark) in [`synthetic`].
//!
//! The graph's gauge (where it sits in the world) is fixed by holding poses constant: those marked
//! with [`PoseGraph::fix`], or the first pose when none is.

pub mod g2o;
pub mod kernel;
pub mod residual;
pub mod solve;
pub mod synthetic;
pub mod system;

use nalgebra::{Isometry3, Matrix6, SymmetricEigen};
use serde::{Deserialize, Serialize};

pub use kernel::Kernel;

/// What an edge measures, which decides its robust kernel ([`PoseGraphConfig`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EdgeKind {
    /// Between consecutive poses, from odometry: trusted.
    Odometry,
    /// A loop closure from place recognition and registration: may be false.
    Loop,
}

/// A relative-pose measurement between two poses of the graph.
#[derive(Clone, Debug, PartialEq)]
pub struct Edge {
    /// Index of pose `i`.
    pub from: usize,
    /// Index of pose `j`.
    pub to: usize,
    /// `Z`: the measured pose of `j` in the frame of `i`.
    pub measurement: Isometry3<f64>,
    /// `Ω`: inverse covariance of the error `[ρ; φ]` (translation first), symmetric positive
    /// semi-definite.
    pub information: Matrix6<f64>,
    /// Which kernel applies.
    pub kind: EdgeKind,
}

/// How far odometry may be off over a step: a deviation growing with the distance travelled, with
/// a floor for steps that turn without travel. What both the robots' keyframe graphs and the
/// station's joint graph weigh their odometry edges by.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OdometryNoise {
    /// Translation error per metre travelled (m/m).
    pub drift: f64,
    /// Rotation error per metre travelled (deg/m).
    pub rotation_deg_per_m: f64,
    /// Least translation deviation of a step (m).
    pub min_sigma_m: f64,
    /// Least rotation deviation of a step (deg).
    pub min_sigma_deg: f64,
}

impl OdometryNoise {
    /// Deviations of the translation (m) and rotation (deg) of an odometry step over `step`.
    pub fn sigmas(&self, step: &Isometry3<f64>) -> (f64, f64) {
        self.deviations(step.translation.vector.norm(), 1.0)
    }

    /// The information of an odometry edge over `step` (diagonal, tangent `[ρ; φ]`).
    pub fn information(&self, step: &Isometry3<f64>) -> Matrix6<f64> {
        let (sigma_m, sigma_deg) = self.sigmas(step);
        diagonal_information(sigma_m, sigma_deg)
    }

    /// [`OdometryNoise::sigmas`] for a path keyed at any rate: below a metre of travel the least
    /// deviations shrink with the square root of the step, as a random walk's do (the variances of
    /// n steps of 1/n metre add up to one metre's), so that a robot keyed every sweep is held as
    /// firmly as one keyed every metre; from a metre on the two are the same. A radian turned
    /// counts as a metre travelled; a step that neither moves nor turns is held to a hundredth of
    /// the least deviations, so that no information is infinite.
    pub fn sigmas_along_path(&self, step: &Isometry3<f64>) -> (f64, f64) {
        let length = step.translation.vector.norm();
        self.deviations(length, (length + step.rotation.angle()).clamp(1e-4, 1.0).sqrt())
    }

    /// The drift over `length` metres, at least `share` of the least deviations.
    fn deviations(&self, length: f64, share: f64) -> (f64, f64) {
        (
            (self.drift * length).max(self.min_sigma_m * share),
            (self.rotation_deg_per_m * length).max(self.min_sigma_deg * share),
        )
    }
}

/// The information of an edge whose translation and rotation errors are independent, each axis
/// with deviation `sigma_m` (metres) and `sigma_deg` (degrees): diagonal, tangent `[ρ; φ]`.
pub fn diagonal_information(sigma_m: f64, sigma_deg: f64) -> Matrix6<f64> {
    let t = 1.0 / (sigma_m * sigma_m);
    let r = 1.0 / sigma_deg.to_radians().powi(2);
    Matrix6::from_diagonal(&nalgebra::Vector6::new(t, t, t, r, r, r))
}

/// How a pose graph is optimised. The stopping rules and λ schedule are GTSAM's
/// `LevenbergMarquardtParams` defaults.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoseGraphConfig {
    /// Linearisations at most. Default 100 (GTSAM).
    pub max_iterations: usize,
    /// Stop when an accepted step lowers the cost by less than this fraction. Default 1e-5 (GTSAM).
    pub relative_tolerance: f64,
    /// Stop when an accepted step lowers the cost by less than this, absolutely. Default 1e-5
    /// (GTSAM).
    pub absolute_tolerance: f64,
    /// First damping factor λ. Default 1e-5 (GTSAM).
    pub initial_lambda: f64,
    /// λ is multiplied by this after a rejected step and divided by it after an accepted one.
    /// Default 10 (GTSAM).
    pub lambda_factor: f64,
    /// Give up when λ exceeds this without a step lowering the cost. Default 1e5 (GTSAM).
    pub max_lambda: f64,
    /// Kernel of odometry edges. Default none: consecutive scans registered by the odometry are
    /// trusted, and a robust kernel there would only slow convergence.
    pub odometry_kernel: Kernel,
    /// Kernel of loop edges. Default Cauchy with k = 3 (standard deviations of the loop's own
    /// noise): a loop the rest of the graph agrees with (r² ≈ 6, the mean of χ² with 6 degrees of
    /// freedom) keeps 60 % of its weight k² / (k² + r²), one it contradicts by 30 σ keeps 1 %. On
    /// the synthetic ring with two false loops (cloud/tests/integration/pose_graph.rs), k = 3 and 5 leave the
    /// trajectory as without them; k = 1 (SC-A-LOAM's, whose loop noise is loose) weighs true loops
    /// 0.14 at the optimum, and took 3-4x the iterations to a worse trajectory.
    pub loop_kernel: Kernel,
}

impl Default for PoseGraphConfig {
    fn default() -> Self {
        PoseGraphConfig {
            max_iterations: 100,
            relative_tolerance: 1e-5,
            absolute_tolerance: 1e-5,
            initial_lambda: 1e-5,
            lambda_factor: 10.0,
            max_lambda: 1e5,
            odometry_kernel: Kernel::None,
            loop_kernel: Kernel::Cauchy(3.0),
        }
    }
}

impl PoseGraphConfig {
    /// Least squares on every edge: the cost GTSAM minimises for a g2o file.
    pub fn least_squares() -> Self {
        PoseGraphConfig { loop_kernel: Kernel::None, ..PoseGraphConfig::default() }
    }

    /// The kernel of edges of `kind`.
    pub fn kernel(&self, kind: EdgeKind) -> Kernel {
        match kind {
            EdgeKind::Odometry => self.odometry_kernel,
            EdgeKind::Loop => self.loop_kernel,
        }
    }

    fn validate(&self) -> Result<(), PoseGraphError> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        let ok = positive(self.initial_lambda)
            && self.lambda_factor.is_finite()
            && self.lambda_factor > 1.0
            && positive(self.max_lambda)
            && self.relative_tolerance >= 0.0
            && self.absolute_tolerance >= 0.0
            && self.odometry_kernel.is_valid()
            && self.loop_kernel.is_valid();
        ok.then_some(()).ok_or(PoseGraphError::InvalidConfig)
    }
}

/// What an optimisation did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Report {
    /// Cost (1) before the first step.
    pub initial_error: f64,
    /// Cost (1) at the returned poses.
    pub final_error: f64,
    /// Linearisations, as GTSAM counts its iterations: each is followed by steps at growing λ
    /// until one lowers the cost.
    pub iterations: usize,
    /// Whether a tolerance stopped it (not the iteration cap or λ growing past its bound).
    pub converged: bool,
    /// Wall time of the whole optimisation, the sparsity analysis included, milliseconds.
    pub time_ms: f64,
}

/// Why a graph could not be built or optimised.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PoseGraphError {
    /// An edge or a fix names a pose that does not exist.
    #[error("pose {index} does not exist (the graph has {poses})")]
    UnknownPose {
        /// The index asked for.
        index: usize,
        /// Number of poses.
        poses: usize,
    },
    /// An edge joins a pose to itself: its error does not depend on the pose.
    #[error("edge from pose {0} to itself")]
    SelfLoop(usize),
    /// A measurement or information matrix holds NaN or infinity.
    #[error("edge {from} -> {to}: non-finite measurement or information")]
    NonFinite {
        /// Index of pose `i`.
        from: usize,
        /// Index of pose `j`.
        to: usize,
    },
    /// An information matrix is not symmetric positive semi-definite.
    #[error("edge {from} -> {to}: information matrix not symmetric positive semi-definite")]
    NotPositiveSemiDefinite {
        /// Index of pose `i`.
        from: usize,
        /// Index of pose `j`.
        to: usize,
    },
    /// A setting is out of range.
    #[error(
        "invalid configuration: λ and its factor must be positive (factor > 1), tolerances non-negative, kernel scales positive"
    )]
    InvalidConfig,
    /// The sparse Cholesky factorisation failed for a reason other than a non-positive pivot.
    #[error("sparse factorisation failed: {0}")]
    Factorisation(String),
}

/// Poses and the relative-pose edges between them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PoseGraph {
    poses: Vec<Isometry3<f64>>,
    edges: Vec<Edge>,
    fixed: Vec<bool>,
    ids: Vec<i64>,
}

impl PoseGraph {
    /// An empty graph.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a pose at its initial estimate; returns its index. Its id (kept for writing g2o) is one
    /// above the largest so far.
    pub fn add_pose(&mut self, initial: Isometry3<f64>) -> usize {
        let id = self.ids.iter().max().map_or(0, |m| m + 1);
        self.add_pose_with_id(initial, id)
    }

    /// Adds a pose with an external id (a g2o vertex id).
    pub(crate) fn add_pose_with_id(&mut self, initial: Isometry3<f64>, id: i64) -> usize {
        self.poses.push(initial);
        self.fixed.push(false);
        self.ids.push(id);
        self.poses.len() - 1
    }

    /// Adds an edge; refused when a pose is unknown, the edge joins a pose to itself, or the
    /// measurement or information is unusable (non-finite, not symmetric PSD).
    pub fn add_edge(&mut self, edge: Edge) -> Result<(), PoseGraphError> {
        for index in [edge.from, edge.to] {
            self.check_index(index)?;
        }
        let (from, to) = (edge.from, edge.to);
        if from == to {
            return Err(PoseGraphError::SelfLoop(from));
        }
        let m = &edge.measurement;
        let finite = m.translation.vector.iter().chain(m.rotation.coords.iter()).chain(edge.information.iter());
        if !finite.into_iter().all(|v| v.is_finite()) {
            return Err(PoseGraphError::NonFinite { from, to });
        }
        if !is_symmetric_psd(&edge.information) {
            return Err(PoseGraphError::NotPositiveSemiDefinite { from, to });
        }
        self.edges.push(edge);
        Ok(())
    }

    /// Holds pose `index` constant during optimisation.
    pub fn fix(&mut self, index: usize) -> Result<(), PoseGraphError> {
        self.check_index(index)?;
        self.fixed[index] = true;
        Ok(())
    }

    /// Whether pose `index` is held constant: marked with [`PoseGraph::fix`], or the first pose
    /// when none is marked (the default gauge).
    pub fn is_fixed(&self, index: usize) -> bool {
        self.fixed[index] || (index == 0 && !self.fixed.contains(&true))
    }

    /// Whether pose `index` was marked with [`PoseGraph::fix`] (what g2o's FIX lines record).
    pub fn is_marked_fixed(&self, index: usize) -> bool {
        self.fixed[index]
    }

    /// The poses, by index.
    pub fn poses(&self) -> &[Isometry3<f64>] {
        &self.poses
    }

    /// The edges, in the order added.
    pub fn edges(&self) -> &[Edge] {
        &self.edges
    }

    /// External ids of the poses, by index (g2o vertex ids, or 0, 1, 2, ... from [`PoseGraph::add_pose`]).
    pub fn ids(&self) -> &[i64] {
        &self.ids
    }

    /// Cost (1) at the current poses: `½ Σ ρ(eᵀ Ω e)`.
    pub fn error(&self, config: &PoseGraphConfig) -> f64 {
        system::cost(&self.poses, &self.edges, config)
    }

    /// Moves the free poses to a minimum of cost (1), see [`solve`].
    pub fn optimize(&mut self, config: &PoseGraphConfig) -> Result<Report, PoseGraphError> {
        config.validate()?;
        let fixed: Vec<bool> = (0..self.poses.len()).map(|i| self.is_fixed(i)).collect();
        solve::levenberg_marquardt(&mut self.poses, &self.edges, &fixed, config)
    }

    fn check_index(&self, index: usize) -> Result<(), PoseGraphError> {
        if index < self.poses.len() {
            Ok(())
        } else {
            Err(PoseGraphError::UnknownPose { index, poses: self.poses.len() })
        }
    }
}

/// The nearest positive semi-definite matrix to a symmetric `m` in the Frobenius norm: `m` itself
/// when it already is one (to [`is_symmetric_psd`]'s rounding), else its eigen-decomposition with
/// the negative eigenvalues set to zero (Higham 1988); and `m`'s smallest eigenvalue.
/// A matrix with a non-finite entry is returned as it is, for [`PoseGraph::add_edge`] to refuse.
pub(crate) fn nearest_psd(m: &Matrix6<f64>) -> (Matrix6<f64>, f64) {
    if !m.iter().all(|v| v.is_finite()) {
        return (*m, f64::NAN);
    }
    let eigen = SymmetricEigen::new(m.symmetric_part());
    let min = eigen.eigenvalues.min();
    if psd_to_rounding(m, min) {
        return (*m, min);
    }
    let clamped = eigen.eigenvalues.map(|v| v.max(0.0));
    let repaired = eigen.eigenvectors * Matrix6::from_diagonal(&clamped) * eigen.eigenvectors.transpose();
    (repaired.symmetric_part(), min)
}

/// Symmetric to rounding and no eigenvalue below −1e-9 of the largest magnitude.
fn is_symmetric_psd(m: &Matrix6<f64>) -> bool {
    psd_to_rounding(m, SymmetricEigen::new(m.symmetric_part()).eigenvalues.min())
}

/// [`is_symmetric_psd`] given the smallest eigenvalue of `m`'s symmetric part, so that a caller
/// that has decomposed `m` already does not decompose it again.
fn psd_to_rounding(m: &Matrix6<f64>, min_eigenvalue: f64) -> bool {
    let tolerance = 1e-9 * m.amax().max(f64::MIN_POSITIVE);
    (m - m.transpose()).amax() <= tolerance && min_eigenvalue >= -tolerance
}

#[cfg(test)]
mod tests {
    use super::*;

    fn edge(from: usize, to: usize) -> Edge {
        Edge {
            from,
            to,
            measurement: Isometry3::translation(1.0, 0.0, 0.0),
            information: Matrix6::identity(),
            kind: EdgeKind::Odometry,
        }
    }

    #[test]
    fn short_steps_add_up_to_a_metre_as_a_random_walk() {
        let noise = OdometryNoise { drift: 0.01, rotation_deg_per_m: 0.01, min_sigma_m: 0.01, min_sigma_deg: 0.1 };
        let metre = Isometry3::translation(1.0, 0.0, 0.0);
        assert_eq!(noise.sigmas_along_path(&metre), noise.sigmas(&metre));
        let long = Isometry3::translation(0.0, 5.0, 0.0);
        assert_eq!(noise.sigmas_along_path(&long), noise.sigmas(&long));
        // Five steps of 0.2 m: their variances add up to one metre's.
        let (m, deg) = noise.sigmas_along_path(&Isometry3::translation(0.2, 0.0, 0.0));
        let (metre_m, metre_deg) = noise.sigmas(&metre);
        assert!((5.0 * m * m - metre_m * metre_m).abs() < 1e-12, "{m}");
        assert!((5.0 * deg * deg - metre_deg * metre_deg).abs() < 1e-12, "{deg}");
        // Standing still: held firmly, but not infinitely.
        let (m, deg) = noise.sigmas_along_path(&Isometry3::identity());
        assert!(m > 0.0 && m < 1e-3 && deg > 0.0 && deg < 1e-2, "{m} {deg}");
        // A quarter turn in place counts as more than a metre.
        let turn = Isometry3::rotation(nalgebra::Vector3::z() * std::f64::consts::FRAC_PI_2);
        assert_eq!(noise.sigmas_along_path(&turn).1, noise.min_sigma_deg);
    }

    #[test]
    fn edges_are_checked() {
        let mut graph = PoseGraph::new();
        assert_eq!(graph.add_pose(Isometry3::identity()), 0);
        assert_eq!(graph.add_pose(Isometry3::identity()), 1);
        assert_eq!(graph.add_edge(edge(0, 2)), Err(PoseGraphError::UnknownPose { index: 2, poses: 2 }));
        assert_eq!(graph.add_edge(edge(1, 1)), Err(PoseGraphError::SelfLoop(1)));
        let mut bad = edge(0, 1);
        bad.information[(2, 3)] = f64::NAN;
        assert_eq!(graph.add_edge(bad), Err(PoseGraphError::NonFinite { from: 0, to: 1 }));
        let mut bad = edge(0, 1);
        bad.information[(5, 5)] = -1.0;
        assert_eq!(graph.add_edge(bad), Err(PoseGraphError::NotPositiveSemiDefinite { from: 0, to: 1 }));
        let mut bad = edge(0, 1);
        bad.information[(0, 1)] = 0.5;
        assert_eq!(graph.add_edge(bad), Err(PoseGraphError::NotPositiveSemiDefinite { from: 0, to: 1 }));
        // Rank-deficient information (a loop that constrains only the translation) is usable.
        let mut partial = edge(0, 1);
        partial.information.fixed_view_mut::<3, 3>(3, 3).fill(0.0);
        assert_eq!(graph.add_edge(partial), Ok(()));
        assert_eq!(graph.edges().len(), 1);
    }

    #[test]
    fn the_first_pose_is_the_gauge_unless_another_is_fixed() {
        let mut graph = PoseGraph::new();
        for _ in 0..3 {
            graph.add_pose(Isometry3::identity());
        }
        assert!(graph.is_fixed(0) && !graph.is_fixed(1));
        graph.fix(2).unwrap();
        assert!(!graph.is_fixed(0) && graph.is_fixed(2));
        assert_eq!(graph.fix(3), Err(PoseGraphError::UnknownPose { index: 3, poses: 3 }));
    }

    #[test]
    fn the_config_reads_from_toml_with_defaults_for_what_is_left_out() {
        let config: PoseGraphConfig = toml::from_str("max_iterations = 5\nloop_kernel = { huber = 2.0 }").unwrap();
        assert_eq!(config.max_iterations, 5);
        assert_eq!(config.loop_kernel, Kernel::Huber(2.0));
        assert_eq!(config.odometry_kernel, Kernel::None);
        let config: PoseGraphConfig = toml::from_str("loop_kernel = \"none\"").unwrap();
        assert_eq!(config, PoseGraphConfig::least_squares());
        assert!(toml::from_str::<PoseGraphConfig>("no_such_key = 1").is_err());
    }

    #[test]
    fn a_translation_error_costs_half_its_squared_mahalanobis_norm() {
        let mut graph = PoseGraph::new();
        graph.add_pose(Isometry3::identity());
        graph.add_pose(Isometry3::translation(1.5, 0.0, 0.0));
        let mut e = edge(0, 1);
        e.information *= 4.0;
        graph.add_edge(e).unwrap();
        // e = [0.5 0 0 0 0 0], eᵀΩe = 4 · 0.25 = 1.
        assert!((graph.error(&PoseGraphConfig::default()) - 0.5).abs() < 1e-12);
    }
}
