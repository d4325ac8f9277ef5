//! Step 2-3 — one pairwise estimate: global registration, VGICP refinement, confidence.

use cloud::registration::{Method, align_gaussians};
use cloud::se3::pose_error;
use nalgebra::Isometry3;

use super::ambiguity::{mean_displacement, runner_up};
use super::{MergeConfig, PreparedMap};
use crate::pairwise::{self, Confidence, PairwiseOutcome, Rejection, confidence};

/// An accepted edge of the match graph between maps `a` and `b`.
#[derive(Clone, Debug, PartialEq)]
pub struct Edge {
    /// Position of the first map.
    pub a: usize,
    /// Position of the second map.
    pub b: usize,
    /// Maps map `b`'s points into map `a`'s frame (refined when [`Edge::refined`]).
    pub transform: Isometry3<f64>,
    /// The global registration's transform before VGICP.
    pub global_transform: Isometry3<f64>,
    /// True when the VGICP refinement was kept.
    pub refined: bool,
    /// Scores at `transform`; `score` is the published confidence.
    pub confidence: Confidence,
    /// RANSAC inliers of the global registration.
    pub inliers: usize,
    /// Inliers of the strongest distinct alternative over `inliers` (0: none found).
    pub ambiguity: f64,
}

/// Why a pair gave no edge.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PairRejection {
    /// A map of the pair has no features (see the map's own status).
    #[error("a map of the pair is unusable")]
    Unusable,
    /// The global registration's reliability checks failed.
    #[error(transparent)]
    Pairwise(Rejection),
    /// The score at the refined transform is below [`MergeConfig::min_confidence`].
    #[error("confidence {score:.3}, need {needed:.3}")]
    LowConfidence {
        /// Score at the final transform.
        score: f64,
        /// The threshold.
        needed: f64,
    },
    /// A distinct transform has nearly as much support: repetitive structure, no unique answer.
    #[error("ambiguous: an alternative {away:.1} m away has {runner_up} inliers against {inliers}")]
    Ambiguous {
        /// Inliers of the chosen transform.
        inliers: usize,
        /// Inliers of the alternative.
        runner_up: usize,
        /// Mean displacement between the two on the source keypoints, metres.
        away: f64,
    },
}

/// What an estimate concluded for one pair.
#[derive(Clone, Debug, PartialEq)]
pub enum PairVerdict {
    /// A reliable transform: an edge of the match graph.
    Edge(Edge),
    /// No reliable transform (the scores of the best hypothesis, if there was one).
    Rejected {
        /// The check that failed.
        reason: PairRejection,
        /// Scores of the best hypothesis.
        best: Option<Confidence>,
        /// The best hypothesis (maps `b` into `a`), for inspection.
        best_transform: Option<Isometry3<f64>>,
    },
}

impl PairVerdict {
    /// The edge if the pair was accepted.
    pub fn edge(&self) -> Option<&Edge> {
        match self {
            PairVerdict::Edge(e) => Some(e),
            PairVerdict::Rejected { .. } => None,
        }
    }
}

/// Estimates the transform mapping map `b` (source) into map `a` (target), both usable.
pub fn estimate_pair(
    (a, map_a): (usize, &PreparedMap),
    (b, map_b): (usize, &PreparedMap),
    config: &MergeConfig,
) -> PairVerdict {
    let (Some(target), Some(source)) = (map_a.usable(), map_b.usable()) else {
        return PairVerdict::Rejected { reason: PairRejection::Unusable, best: None, best_transform: None };
    };
    let global = match pairwise::align(source, target, &config.pairwise) {
        PairwiseOutcome::Aligned(r) => r,
        PairwiseOutcome::NotAligned { reason, best } => {
            return PairVerdict::Rejected {
                reason: PairRejection::Pairwise(reason),
                best: best.as_ref().map(|r| r.confidence),
                best_transform: best.map(|r| r.transform),
            };
        }
    };
    let score_at = |t: &Isometry3<f64>| {
        confidence::confidence(
            &source.surfels.points,
            &target.surfels.tree,
            t,
            global.inlier_ratio,
            &config.pairwise.confidence,
        )
    };
    let at_global = score_at(&global.transform);
    // VGICP minimises its own cost on other points; the mean squared nearest-neighbour distance on
    // the feature surfels arbitrates (identical maps: VGICP's voxel means pull it a centimetre off
    // the exact answer, which this catches).
    let refined = refine(map_b, map_a, &global.transform, config)
        .map(|t| (t, score_at(&t)))
        .filter(|(_, s)| s.fitness >= at_global.fitness);
    let (transform, scores) = refined.unwrap_or((global.transform, at_global));
    let reject = |reason| PairVerdict::Rejected { reason, best: Some(scores), best_transform: Some(transform) };
    if scores.score < config.min_confidence {
        return reject(PairRejection::LowConfidence { score: scores.score, needed: config.min_confidence });
    }
    let inliers = global.inliers.len();
    let alternative = runner_up(source, target, &transform, config.ambiguity_distance, &config.pairwise);
    let ambiguity = alternative.map_or(0.0, |r| r.inliers as f64 / inliers.max(1) as f64);
    if let Some(r) = alternative.filter(|_| ambiguity > config.max_ambiguity) {
        let away = mean_displacement(&source.keypoint_positions(), &transform, &r.transform);
        return reject(PairRejection::Ambiguous { inliers, runner_up: r.inliers, away });
    }
    PairVerdict::Edge(Edge {
        a,
        b,
        transform,
        global_transform: global.transform,
        refined: refined.is_some(),
        confidence: scores,
        inliers,
        ambiguity,
    })
}

/// The VGICP transform from `init`, if it converged nearby; `None` keeps the global estimate.
pub fn refine(
    source: &PreparedMap,
    target: &PreparedMap,
    init: &Isometry3<f64>,
    config: &MergeConfig,
) -> Option<Isometry3<f64>> {
    let (s, t) = (source.fine.as_ref()?, target.fine.as_ref()?);
    let result = align_gaussians(s, t, init, Method::Vgicp, &config.refine).ok()?;
    let moved = pose_error(&result.transform, init);
    let plausible =
        moved.translation_m <= config.max_refine_translation && moved.rotation_deg <= config.max_refine_rotation_deg;
    (plausible && result.inliers > 0).then_some(result.transform)
}
