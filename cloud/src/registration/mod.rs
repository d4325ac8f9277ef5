//! Fine registration of two point clouds: GICP and VGICP, after koide3/small_gicp.
//!
//! The pipeline is small_gicp's: estimate a plane-regularised covariance per point ([`covariance`]),
//! put the target in a search structure (a k-d tree for GICP, a hashed map of Gaussian voxels for
//! VGICP, [`voxel_map`]), then minimise `Σ eᵀ W e` over the pose with Levenberg-Marquardt, where `e`
//! is the distance from a transformed source point to its nearest target Gaussian and the [`Factor`]
//! chooses `W` (GICP: `(C_t + R C_s Rᵀ)⁻¹`). Each iteration sums the 6x6 system in blocks, one rayon
//! task each, the blocks then in order ([`crate::gauss_newton`]): the result does not depend on the
//! number of threads, which a `rayon::ThreadPool::install` chooses.
//!
//! Inputs are used as given: downsample first (0.1-0.5 m voxels, [`crate::voxel::downsample`]).

pub mod covariance;
pub mod factor;
pub mod target;
pub mod voxel_map;

use nalgebra::{Isometry3, Matrix6, Point3, Vector6};

pub use covariance::{estimate_covariances, regularise};
pub use factor::{Factor, GicpFactor, LinearSystem, PointToPlaneFactor};
pub use target::{GaussianCloud, Target};
pub use voxel_map::{GaussianVoxel, GaussianVoxelMap, VoxelSearch};

use crate::PointCloud;
use crate::gauss_newton::{NormalEquations, solve_damped};
use crate::se3;
use factor::{NO_MATCH, SquaredDistance, evaluate, linearize};

/// Fewest points a cloud needs: below three the pose is undetermined whatever their shape.
pub const MIN_POINTS: usize = 3;

/// Which cost and target structure [`align`] uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    /// Point-to-distribution GICP against the target points (k-d tree search).
    Gicp,
    /// Voxelized GICP: against Gaussian voxels, coarse to fine (hash lookups, no tree search).
    Vgicp,
    /// Point-to-plane ICP against the target points, normals from their covariances.
    PointToPlane,
}

/// Every knob of the registration; defaults are small_gicp's unless noted.
#[derive(Clone, Debug, PartialEq)]
pub struct RegistrationConfig {
    /// Outer (linearisation) iterations per resolution level. Default 20.
    pub max_iterations: usize,
    /// Damping retries per iteration before giving up on a descent step. Default 10.
    pub max_inner_iterations: usize,
    /// Correspondences farther than this are ignored, metres. Default 1.0.
    pub max_correspondence_distance: f64,
    /// Nearest neighbours per covariance, the point included. Default 20.
    pub neighbours: usize,
    /// VGICP voxel edge at the finest level, metres. Default 1.0.
    pub voxel_resolution: f64,
    /// VGICP coarser levels run first, each doubling the voxel edge and the correspondence
    /// distance: 1 means resolutions [2r, r]. Default 1 (not in small_gicp; widens the basin).
    pub coarse_levels: usize,
    /// VGICP voxels searched per point. Default [`VoxelSearch::Direct1`].
    pub voxel_search: VoxelSearch,
    /// Initial Levenberg-Marquardt damping λ (added to the diagonal of H). Default 1e-3.
    pub lm_initial_lambda: f64,
    /// λ is divided by this after a step that lowers the cost and multiplied otherwise. Default 10.
    pub lm_lambda_factor: f64,
    /// Converged when a step rotates less than this, radians, and translates less than
    /// `translation_epsilon`. Default 1.745e-3 (0.1°).
    pub rotation_epsilon: f64,
    /// Converged when a step translates less than this, metres, and rotates less than
    /// `rotation_epsilon`. Default 1e-3 m.
    pub translation_epsilon: f64,
}

impl Default for RegistrationConfig {
    fn default() -> Self {
        RegistrationConfig {
            max_iterations: 20,
            max_inner_iterations: 10,
            max_correspondence_distance: 1.0,
            neighbours: 20,
            voxel_resolution: 1.0,
            coarse_levels: 1,
            voxel_search: VoxelSearch::Direct1,
            lm_initial_lambda: 1e-3,
            lm_lambda_factor: 10.0,
            rotation_epsilon: 0.1f64.to_radians(),
            translation_epsilon: 1e-3,
        }
    }
}

/// The outcome of a registration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RegistrationResult {
    /// `T_target_source`: maps source points into the target frame.
    pub transform: Isometry3<f64>,
    /// Linearisations done, all levels together.
    pub iterations: usize,
    /// True when the last step was below both epsilons.
    pub converged: bool,
    /// Source points with a correspondence at the last linearisation.
    pub inliers: usize,
    /// Cost `Σ eᵀ W e` at the last linearisation (squared Mahalanobis distances for GICP).
    pub error: f64,
    /// Mean squared distance of the inliers to their target Gaussians, m² (NaN without inliers).
    pub fitness: f64,
    /// `Σ Jᵀ W J` at the last linearisation: the information of the pose for a pose graph, in the
    /// right-perturbation tangent `T · exp([ρ; φ])`.
    pub hessian: Matrix6<f64>,
}

/// Why a registration could not start.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RegistrationError {
    /// A cloud has fewer than [`MIN_POINTS`] points.
    #[error("the {cloud} cloud has {found} points, need at least {MIN_POINTS}")]
    TooFewPoints { cloud: &'static str, found: usize },
    /// A cloud has a NaN or infinite coordinate.
    #[error("point {index} of the {cloud} cloud is not finite")]
    NonFinitePoint { cloud: &'static str, index: usize },
    /// All points of a cloud coincide: it has no shape to register.
    #[error("all points of the {cloud} cloud coincide")]
    Degenerate { cloud: &'static str },
    /// The initial guess has a NaN or infinite entry.
    #[error("the initial guess is not finite")]
    NonFiniteInitialGuess,
    /// A configuration value is out of range.
    #[error("invalid registration config: {0}")]
    InvalidConfig(&'static str),
}

/// Registers `source` onto `target` from `init` (`T_target_source`), estimating covariances first.
pub fn align(
    source: &PointCloud,
    target: &PointCloud,
    init: &Isometry3<f64>,
    method: Method,
    config: &RegistrationConfig,
) -> Result<RegistrationResult, RegistrationError> {
    check_config(config)?;
    check_cloud(&source.points, "source")?;
    check_cloud(&target.points, "target")?;
    let source = GaussianCloud::new(&source.points, config.neighbours);
    let target = GaussianCloud::new(&target.points, config.neighbours);
    align_gaussians(&source, &target, init, method, config)
}

/// [`align`] on clouds whose covariances are already estimated (e.g. a target reused many times).
pub fn align_gaussians(
    source: &GaussianCloud,
    target: &GaussianCloud,
    init: &Isometry3<f64>,
    method: Method,
    config: &RegistrationConfig,
) -> Result<RegistrationResult, RegistrationError> {
    check_config(config)?;
    if target.len() < MIN_POINTS {
        return Err(RegistrationError::TooFewPoints { cloud: "target", found: target.len() });
    }
    match method {
        Method::Gicp => register(source, target, &GicpFactor, init, config),
        Method::PointToPlane => register(source, target, &PointToPlaneFactor, init, config),
        Method::Vgicp => align_coarse_to_fine(source, target, init, config),
    }
}

/// VGICP over voxel maps from `2^coarse_levels · r` down to `r`, each level starting where the
/// coarser one ended: large voxels see far correspondences, small ones give precision.
fn align_coarse_to_fine(
    source: &GaussianCloud,
    target: &GaussianCloud,
    init: &Isometry3<f64>,
    config: &RegistrationConfig,
) -> Result<RegistrationResult, RegistrationError> {
    let mut pose = *init;
    let mut iterations = 0;
    let mut result = None;
    for level in (0..=config.coarse_levels).rev() {
        let scale = f64::from(1u32 << level.min(16));
        let map = GaussianVoxelMap::new(target, config.voxel_resolution * scale, config.voxel_search);
        let level_config = RegistrationConfig {
            max_correspondence_distance: config.max_correspondence_distance * scale,
            rotation_epsilon: config.rotation_epsilon * scale,
            translation_epsilon: config.translation_epsilon * scale,
            ..config.clone()
        };
        // A coarse level only has to bring the pose into the fine level's basin: a 2^level-times
        // larger voxel merges ~8^level times more points, so a sparser source (every 4^level-th
        // point, if at least 64 remain) sees the same voxels at a fraction of the cost.
        let step = 1usize << (2 * level.min(8));
        let sparse;
        let level_source = if level == 0 || source.len() / step < 64 {
            source
        } else {
            sparse = source.strided_source(step);
            &sparse
        };
        let r = register(level_source, &map, &GicpFactor, &pose, &level_config)?;
        pose = r.transform;
        iterations += r.iterations;
        result = Some(r);
    }
    let result = result.expect("the finest level always runs");
    Ok(RegistrationResult { iterations, ..result })
}

/// Levenberg-Marquardt over the pose of `source` against any target and factor: the building block
/// of [`align`] for callers that keep a target (e.g. a map's voxel map) across registrations.
pub fn register<T: Target, F: Factor>(
    source: &GaussianCloud,
    target: &T,
    factor: &F,
    init: &Isometry3<f64>,
    config: &RegistrationConfig,
) -> Result<RegistrationResult, RegistrationError> {
    check_config(config)?;
    if source.len() < MIN_POINTS {
        return Err(RegistrationError::TooFewPoints { cloud: "source", found: source.len() });
    }
    if !init.to_homogeneous().iter().all(|v| v.is_finite()) {
        return Err(RegistrationError::NonFiniteInitialGuess);
    }
    let max_dist_sq = config.max_correspondence_distance.powi(2);
    // Allocated once: linearize writes each point's match, evaluate reads them back.
    let mut matches = vec![NO_MATCH; source.len()];
    let mut pose = *init;
    let mut lambda = config.lm_initial_lambda;
    let mut system = NormalEquations::<SquaredDistance>::zero();
    let (mut iterations, mut converged) = (0, false);
    while iterations < config.max_iterations && !converged {
        system = linearize(source, target, factor, &pose, max_dist_sq, &mut matches);
        iterations += 1;
        if system.count == 0 {
            break;
        }
        let cost = |candidate: &Isometry3<f64>| evaluate(source, target, factor, candidate, &matches);
        let (accepted, delta) = lm_step(&system, &pose, &mut lambda, config, cost);
        converged = is_small(&delta, config);
        match accepted {
            Some(next) => pose = next,
            // No damping lowered the cost: a minimum for these correspondences.
            None => break,
        }
    }
    Ok(RegistrationResult {
        transform: pose,
        iterations,
        converged,
        inliers: system.count,
        error: system.cost,
        fitness: system.sums.0 / system.count as f64,
        hessian: system.h,
    })
}

/// One damped step: solves `(H + λI) δ = −b` and moves `T ← T · exp(δ)`, raising λ until the cost
/// does not grow.
///
/// Returns the new pose (if a step was accepted) and the last step tried.
fn lm_step<S>(
    system: &NormalEquations<S>,
    pose: &Isometry3<f64>,
    lambda: &mut f64,
    config: &RegistrationConfig,
    cost: impl Fn(&Isometry3<f64>) -> f64,
) -> (Option<Isometry3<f64>>, Vector6<f64>) {
    let mut delta = Vector6::zeros();
    for _ in 0..config.max_inner_iterations.max(1) {
        if let Some(step) = solve_damped(system, *lambda) {
            delta = step;
            let mut candidate = se3::update(pose, &delta);
            candidate.rotation.renormalize();
            // `<=` rejects NaN costs.
            if cost(&candidate) <= system.cost {
                *lambda /= config.lm_lambda_factor;
                return (Some(candidate), delta);
            }
        }
        *lambda *= config.lm_lambda_factor;
    }
    (None, delta)
}

/// True when a step is below both convergence thresholds.
fn is_small(delta: &Vector6<f64>, config: &RegistrationConfig) -> bool {
    delta.fixed_rows::<3>(3).norm() < config.rotation_epsilon
        && delta.fixed_rows::<3>(0).norm() < config.translation_epsilon
}

/// The linear system at `pose` (fresh correspondences), e.g. an information matrix for a pose graph.
pub fn linear_system<T: Target, F: Factor>(
    source: &GaussianCloud,
    target: &T,
    factor: &F,
    pose: &Isometry3<f64>,
    max_correspondence_distance: f64,
) -> LinearSystem {
    let mut matches = vec![NO_MATCH; source.len()];
    linearize(source, target, factor, pose, max_correspondence_distance.powi(2), &mut matches).into()
}

/// Rejects clouds that are too small, non-finite or all one point.
fn check_cloud(points: &[Point3<f32>], cloud: &'static str) -> Result<(), RegistrationError> {
    if points.len() < MIN_POINTS {
        return Err(RegistrationError::TooFewPoints { cloud, found: points.len() });
    }
    if let Some(index) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(RegistrationError::NonFinitePoint { cloud, index });
    }
    if points.iter().all(|p| *p == points[0]) {
        return Err(RegistrationError::Degenerate { cloud });
    }
    Ok(())
}

/// Rejects configuration values that would make the registration meaningless.
fn check_config(c: &RegistrationConfig) -> Result<(), RegistrationError> {
    let positive = |v: f64| v > 0.0 && v.is_finite();
    let checks = [
        (positive(c.max_correspondence_distance), "max_correspondence_distance must be positive"),
        (positive(c.voxel_resolution), "voxel_resolution must be positive"),
        (c.neighbours >= 1, "neighbours must be at least 1"),
        (c.lm_initial_lambda >= 0.0 && c.lm_initial_lambda.is_finite(), "lm_initial_lambda must be >= 0"),
        (c.lm_lambda_factor > 1.0 && c.lm_lambda_factor.is_finite(), "lm_lambda_factor must exceed 1"),
        (c.rotation_epsilon >= 0.0 && c.translation_epsilon >= 0.0, "epsilons must be >= 0"),
    ];
    checks.iter().find(|(ok, _)| !ok).map_or(Ok(()), |(_, msg)| Err(RegistrationError::InvalidConfig(msg)))
}
