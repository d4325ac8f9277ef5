//! Geometric verification of a loop candidate: the new keyframe registered against a submap around
//! the candidate, from Scan Context's yaw, and judged by the overlap score the station's merge uses
//! ([`cloud::confidence`]) and by how well the fit pins the pose down.
//!
//! 1. Coarse: VGICP on 4, 2 and 1 m voxels ([`crate::odometry::coarse`]): a revisit is rarely within
//!    a fine fit's basin of the candidate's pose, metres and the yaw's 6° sector off.
//! 2. Fine: GICP on the `voxel`-downsampled clouds ([`cloud::registration`]).
//! 3. Overlap: the share of the keyframe's points within `overlap_distance` of the submap. A wrong
//!    place that shares the floor and a wall overlaps a little; a revisit most of the scan.
//! 4. Constraint: the fit's information about translation (the 3x3 block of `Σ Jᵀ W J`) must not be
//!    weak in any direction compared with its strongest: in a long corridor or between identical
//!    shelves the fit slides, and a loop along the slide direction would be a guess.
//!
//! A fit is trusted only within `reach_m` of its start: from farther the coarse stage does not
//! find its way, and a fit that moved farther has slid along something. That bound is what lets the
//! loop closure refuse, before registering, a candidate whose odometry puts it farther away than any
//! fit within reach could agree with.
//!
//! A loop that passes (and agrees with the odometry) is then [`refine`]d: GICP again from its fit,
//! between the merged neighbourhoods of both keyframes, covariances estimated on the merged
//! points. One sweep of a 16-beam sensor puts the floor on rings a metre apart, so a point's
//! neighbours lie on one ring and its covariance is a line whose "normal" may point anywhere
//! across it; the single keyframe's fit then tilts by tenths of a degree (0.27 deg of pitch on a
//! simulated warehouse revisit, where the odometry between the same keyframes is off by 0.07).
//! Several keyframes together fill the floor between the rings and give planes their normals.

use cloud::confidence::{ConfidenceConfig, confidence};
use cloud::registration::{self, GaussianCloud, Method, RegistrationConfig};
use cloud::{PointCloud, voxel};
use nalgebra::{Isometry3, Matrix6, SymmetricEigen};
use serde::{Deserialize, Serialize};

use crate::odometry::coarse::{self, CoarseConfig};

/// Settings of the verification.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VerifyConfig {
    /// Keyframe clouds are downsampled to this voxel for verification and kept so (m). Default
    /// 0.25 m: finer than the fine fit's 1 m reach, coarse enough to keep a thousand keyframes
    /// in tens of megabytes.
    pub voxel: f32,
    /// Keyframes either side of the candidate that make its submap. Default 2: a single keyframe
    /// sees a revisit's scene from one place, its neighbours fill in what that place hid.
    pub submap_keyframes: usize,
    /// Keyframes whose covariances are kept between verifications. Default 32: a revisit verifies
    /// keyframe after keyframe against a submap that slides by one, so each keyframe's
    /// covariances are estimated once (in its own frame, then rotated into the submap's), which
    /// was two thirds of a verification's time.
    pub cached_keyframes: usize,
    /// The coarse stage.
    pub coarse: CoarseConfig,
    /// Correspondences farther than this in the fine fit are ignored (m). Default 1 m.
    pub max_correspondence: f64,
    /// A keyframe point overlaps the submap when a submap point lies within this distance (m).
    /// Default 0.5 m (twice the voxel).
    pub overlap_distance: f32,
    /// Least overlap of a loop. Default 0.6.
    pub min_overlap: f64,
    /// Least ratio of the weakest to the strongest translation information. Default 0.02: a
    /// corridor's fit has ~1e-3, a room's 0.1-0.5.
    pub min_constraint: f64,
    /// Standard deviation of a loop's translation along its best-constrained direction (m). Default
    /// 0.05 m. The fit's `Σ Jᵀ W J` gives the information's shape (which directions the scene pins
    /// down, how rotation and translation couple) but not its scale: small_gicp's covariances are
    /// regularised to a fixed shape, not metric, and neighbouring points' errors are correlated
    /// (the same surface, the same beam), so the sum is scaled to this.
    pub sigma_m: f64,
    /// Keyframes on each side that a verified loop is refined with ([`refine`]): the new keyframe's
    /// predecessors (it has no successors yet), the candidate's neighbours both ways. Default 4:
    /// five sweeps fill the floor between a 16-beam sensor's rings; 2 left loops on the simulated
    /// warehouses 0.1-0.2 deg off in pitch. 0 turns the refinement off.
    pub refine_keyframes: usize,
    /// How far a fit may move from its start (m); a fit that moved farther is refused
    /// ([`Verdict::Wandered`]), and a candidate the odometry puts farther than this beyond what it
    /// can have drifted is not registered at all (`consistency::reachable`). Default 16 m, four
    /// times the coarse stage's coarsest correspondences (scale it with them): started 2-16 m off
    /// the truth in 8 directions, the verification found the true pose of KITTI 08's reverse
    /// revisit from up to 12 m (4 of 8 starts there), of simulated revisits from up to 10-12 m, and
    /// from 16 m never (0 of 32 starts).
    pub reach_m: f64,
}

impl Default for VerifyConfig {
    fn default() -> Self {
        VerifyConfig {
            voxel: 0.25,
            submap_keyframes: 2,
            cached_keyframes: 32,
            coarse: CoarseConfig::default(),
            max_correspondence: 1.0,
            overlap_distance: 0.5,
            min_overlap: 0.6,
            min_constraint: 0.02,
            sigma_m: 0.05,
            refine_keyframes: 4,
            reach_m: 16.0,
        }
    }
}

/// A loop the geometry supports.
#[derive(Clone, Debug, PartialEq)]
pub struct Fit {
    /// Pose of the new keyframe in the candidate's frame (maps its points into that frame).
    pub transform: Isometry3<f64>,
    /// Share of the keyframe's points on the submap, in [0, 1].
    pub overlap: f64,
    /// The merge's score `√(overlap · inlier ratio)`; a fine fit has no RANSAC, so `√overlap`.
    pub score: f64,
    /// Weakest over strongest translation information.
    pub constraint: f64,
    /// Information of `transform` in the right-perturbation tangent `[ρ; φ]`.
    pub information: Matrix6<f64>,
}

/// Why a candidate is not a loop.
#[derive(Clone, Debug, PartialEq)]
pub enum Verdict {
    /// The geometry supports it.
    Loop(Fit),
    /// A cloud is too small or degenerate to register.
    Unregistrable,
    /// The fit moved farther from its start than the verification reaches.
    Wandered(Fit),
    /// Too little of the keyframe lies on the submap after the fit.
    LowOverlap(Fit),
    /// The fit leaves a translation direction nearly free.
    Degenerate(Fit),
}

/// Registers `keyframe` (its own frame) against `submap` (the candidate's frame) from `initial`;
/// covariances are estimated here (see [`verify`] for clouds that have them).
pub fn verify_clouds(
    keyframe: &PointCloud,
    submap: &PointCloud,
    initial: &Isometry3<f64>,
    config: &VerifyConfig,
) -> Verdict {
    let (source, target) = rayon::join(|| gaussians(keyframe, config), || gaussians(submap, config));
    verify(&source, &target, initial, config)
}

/// The cloud's points with the covariances the verification uses.
pub fn gaussians(cloud: &PointCloud, config: &VerifyConfig) -> GaussianCloud {
    GaussianCloud::new(&cloud.points, config.coarse.neighbours)
}

/// Registers `keyframe` (its own frame) against `submap` (the candidate's frame) from `initial`.
pub fn verify(
    keyframe: &GaussianCloud,
    submap: &GaussianCloud,
    initial: &Isometry3<f64>,
    config: &VerifyConfig,
) -> Verdict {
    if !registrable(keyframe, submap, config) {
        return Verdict::Unregistrable;
    }
    let Some(coarse) = coarse::align_gaussians(keyframe, submap, initial, &config.coarse) else {
        return Verdict::Unregistrable;
    };
    let Ok(result) = registration::align_gaussians(keyframe, submap, &coarse, Method::Gicp, &fine_config(config))
    else {
        return Verdict::Unregistrable;
    };
    let fit = judged_fit(keyframe, submap, &result, config);
    if (fit.transform.translation.vector - initial.translation.vector).norm() > config.reach_m {
        return Verdict::Wandered(fit);
    }
    judge(fit, config)
}

/// Whether both clouds have the points a covariance and a fit need.
fn registrable(source: &GaussianCloud, target: &GaussianCloud, config: &VerifyConfig) -> bool {
    let least = config.coarse.neighbours.max(registration::MIN_POINTS);
    source.len() >= least && target.len() >= least
}

/// The fine stage's settings.
fn fine_config(config: &VerifyConfig) -> RegistrationConfig {
    RegistrationConfig {
        max_correspondence_distance: config.max_correspondence,
        neighbours: config.coarse.neighbours,
        ..Default::default()
    }
}

/// Fits a verified loop `fit` again between `source` (the new keyframe with its predecessors, in
/// its frame) and `target` (the candidate's neighbourhood, in its frame), each with covariances of
/// its own merged points (see the module documentation). `None` where the refined fit would not
/// pass the verification itself; the caller keeps the first fit then.
pub fn refine(source: &GaussianCloud, target: &GaussianCloud, fit: &Fit, config: &VerifyConfig) -> Option<Fit> {
    if !registrable(source, target, config) {
        return None;
    }
    let result =
        registration::align_gaussians(source, target, &fit.transform, Method::Gicp, &fine_config(config)).ok()?;
    match judge(judged_fit(source, target, &result, config), config) {
        Verdict::Loop(refined) => Some(refined),
        _ => None,
    }
}

/// Keyframe clouds, each with its pose in one frame, as one cloud for [`refine`]: placed in that
/// frame, voxelised again and given covariances of the merged points.
pub fn neighbourhood<'a>(
    keyframes: impl IntoIterator<Item = (&'a PointCloud, Isometry3<f64>)>,
    config: &VerifyConfig,
) -> GaussianCloud {
    let mut points = Vec::new();
    for (cloud, pose) in keyframes {
        let pose = pose.cast::<f32>();
        points.extend(cloud.points.iter().map(|p| pose * p));
    }
    gaussians(&thin(&PointCloud::from_points(points), config), config)
}

/// The fit's overlap, score, constraint and scaled information.
fn judged_fit(
    source: &GaussianCloud,
    target: &GaussianCloud,
    result: &registration::RegistrationResult,
    config: &VerifyConfig,
) -> Fit {
    let scores = ConfidenceConfig { overlap_distance: config.overlap_distance, ..ConfidenceConfig::default() };
    let judged = confidence(&source.points_f32(), target.tree(), &result.transform, 1.0, &scores);
    let (weakest, strongest) = translation_eigenvalues(&result.hessian);
    let constraint = if strongest > 0.0 { (weakest / strongest).max(0.0) } else { 0.0 };
    // Scaled so that the strongest translation direction has variance σ².
    let scale = if strongest > 0.0 { 1.0 / (config.sigma_m.powi(2) * strongest) } else { 0.0 };
    Fit {
        transform: result.transform,
        overlap: judged.overlap,
        score: judged.score,
        constraint,
        information: result.hessian * scale,
    }
}

/// The verdict on a fit: overlap first, then constraint.
fn judge(fit: Fit, config: &VerifyConfig) -> Verdict {
    if fit.overlap < config.min_overlap {
        Verdict::LowOverlap(fit)
    } else if fit.constraint < config.min_constraint {
        Verdict::Degenerate(fit)
    } else {
        Verdict::Loop(fit)
    }
}

/// The smallest and largest eigenvalue of the translation block of `H` (zeros when not finite).
fn translation_eigenvalues(h: &Matrix6<f64>) -> (f64, f64) {
    let block = h.fixed_view::<3, 3>(0, 0).into_owned();
    if !block.iter().all(|v| v.is_finite()) {
        return (0.0, 0.0);
    }
    let eigen = SymmetricEigen::new(block).eigenvalues;
    (eigen.min(), eigen.max())
}

/// A cloud downsampled for verification (the input as it is when the voxel is invalid).
pub fn thin(cloud: &PointCloud, config: &VerifyConfig) -> PointCloud {
    let bare = PointCloud::from_points(cloud.points.clone());
    voxel::downsample(&bare, config.voxel).unwrap_or(bare)
}
