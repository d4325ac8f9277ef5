//! The loop closure alongside a pass of the odometry: keyframes go to the [`LoopCloser`], every scan
//! remembers the keyframe it follows, and at the end each scan's pose is its keyframe's optimised
//! pose composed with the odometry's motion since that keyframe. What `emr-edge odometry --loops`
//! writes (`loops.json`, the figures in `stats.json`) is described here; the files are written by
//! the pipeline.

use nalgebra::Isometry3;
use serde::Serialize;

use super::{LoopCloser, LoopConfig, LoopError, Rejected, Rejection};
use crate::odometry::Frame;

/// A pass's loop closure.
pub struct LoopTrack {
    closer: LoopCloser,
    /// Per registered scan: the keyframe it follows.
    keyframe_of_scan: Vec<usize>,
    /// Per registered scan: its odometry pose.
    odometry: Vec<Isometry3<f64>>,
    /// Per keyframe: milliseconds of description, search and verification.
    detect_ms: Vec<f64>,
    /// Per optimisation: milliseconds.
    optimise_ms: Vec<f64>,
}

/// `loops.json`: the loops in the graph and the candidates that are not, with input scan indices.
#[derive(Clone, Debug, Serialize)]
pub struct LoopsFile {
    /// Loops in the optimised graph.
    pub loops: Vec<LoopRecord>,
    /// Candidates that failed a test or were outvoted.
    pub rejected: Vec<RejectedRecord>,
}

/// One loop of `loops.json`.
#[derive(Clone, Debug, Serialize)]
pub struct LoopRecord {
    /// Input scan index of the older keyframe (`i`).
    pub scan_a: usize,
    /// Input scan index of the newer keyframe (`j`).
    pub scan_b: usize,
    /// Keyframe sequence numbers.
    pub keyframe_a: u64,
    pub keyframe_b: u64,
    /// Maps scan `j`'s points into scan `i`'s frame: 4x4, row-major.
    pub transform: [[f64; 4]; 4],
    /// The merge's overlap-aware score, in [0, 1].
    pub score: f64,
    /// Scan Context distance of the pair.
    pub descriptor_distance: f64,
}

/// One rejected candidate of `loops.json`.
#[derive(Clone, Debug, Serialize)]
pub struct RejectedRecord {
    #[serde(flatten)]
    pub candidate: LoopRecord,
    /// Why it is not in the graph.
    pub reason: String,
}

/// The loop closure's figures in `stats.json`.
#[derive(Clone, Debug, Serialize)]
pub struct LoopSummary {
    /// Keyframes described.
    pub keyframes: usize,
    /// Loops in the optimised graph.
    pub accepted: usize,
    /// Candidates verified or tested and left out.
    pub rejected: usize,
    /// Of them, left out before registration: out of reach by odometry.
    pub unreachable: usize,
    /// Optimisations run.
    pub optimisations: usize,
    /// Median and 95th percentile milliseconds per keyframe of description, search and
    /// verification.
    pub detect_ms_median: f64,
    pub detect_ms_p95: f64,
    /// Milliseconds of all optimisations together.
    pub optimise_ms_total: f64,
}

impl LoopTrack {
    /// A track with a fresh loop closure.
    pub fn new(config: LoopConfig) -> Self {
        LoopTrack {
            closer: LoopCloser::new(config),
            keyframe_of_scan: Vec::new(),
            odometry: Vec::new(),
            detect_ms: Vec::new(),
            optimise_ms: Vec::new(),
        }
    }

    /// The next registered scan.
    pub fn observe(&mut self, frame: &Frame) -> Result<(), LoopError> {
        if let Some(keyframe) = &frame.keyframe {
            let step = self.closer.add(keyframe)?;
            self.detect_ms.push(step.detect_ms);
            self.optimise_ms.extend(step.optimised.map(|r| r.time_ms));
        }
        // The first scan is always a keyframe; before it there is nothing to follow.
        self.keyframe_of_scan.push(self.closer.places().len().saturating_sub(1));
        self.odometry.push(frame.pose);
        Ok(())
    }

    /// The loop closure.
    pub fn closer(&self) -> &LoopCloser {
        &self.closer
    }

    /// Every scan's pose with the loops applied.
    pub fn corrected(&self) -> Vec<Isometry3<f64>> {
        self.odometry.iter().zip(&self.keyframe_of_scan).map(|(pose, &k)| self.closer.follow(k, pose)).collect()
    }

    /// `loops.json`; `scan_index` maps registered scans to input scan indices.
    pub fn file(&self, scan_index: &[usize]) -> LoopsFile {
        let record = |a: usize, b: usize, fit: Option<&super::Fit>, descriptor_distance: f64| {
            let (pa, pb) = (&self.closer.places()[a], &self.closer.places()[b]);
            let input = |scan: usize| scan_index.get(scan).copied().unwrap_or(scan);
            let m = fit.map_or(nalgebra::Matrix4::zeros(), |f| f.transform.to_homogeneous());
            LoopRecord {
                scan_a: input(pa.scan),
                scan_b: input(pb.scan),
                keyframe_a: pa.seq,
                keyframe_b: pb.seq,
                transform: std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)])),
                score: fit.map_or(0.0, |f| f.score),
                descriptor_distance,
            }
        };
        let loops = self.closer.loops().map(|l| record(l.a, l.b, Some(&l.fit), l.descriptor_distance)).collect();
        let rejected = self
            .closer
            .rejected()
            .iter()
            .map(|r: &Rejected| RejectedRecord {
                candidate: record(r.a, r.b, r.fit.as_ref(), r.descriptor_distance),
                reason: r.reason.to_string(),
            })
            .collect();
        LoopsFile { loops, rejected }
    }

    /// The figures for `stats.json`.
    pub fn summary(&self) -> LoopSummary {
        let mut ms = self.detect_ms.clone();
        ms.sort_by(f64::total_cmp);
        let at = |q: f64| if ms.is_empty() { 0.0 } else { ms[((ms.len() - 1) as f64 * q).round() as usize] };
        // Built anew at each call (the outvoted loops added to the refused ones): once here.
        let rejected = self.closer.rejected();
        LoopSummary {
            keyframes: self.closer.places().len(),
            accepted: self.closer.loops().count(),
            rejected: rejected.len(),
            unreachable: rejected.iter().filter(|r| r.reason == Rejection::Unreachable).count(),
            optimisations: self.optimise_ms.len(),
            detect_ms_median: at(0.5),
            detect_ms_p95: at(0.95),
            // An empty f64 sum is -0.0; adding 0.0 makes it 0.
            optimise_ms_total: self.optimise_ms.iter().sum::<f64>() + 0.0,
        }
    }
}

/// The loops in the graph against the ground truth.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct LoopJudgement {
    /// Loops in the graph.
    pub loops: usize,
    /// Of them, farther than [`FALSE_LOOP`] from the true relative pose.
    pub false_loops: usize,
    /// The largest translation error of a loop (m).
    pub worst_translation_m: f64,
    /// The largest rotation error of a loop (deg).
    pub worst_rotation_deg: f64,
    /// The largest translation error of the odometry between the same keyframes (m): a loop
    /// corrects only what the odometry got wrong by more than the loop itself.
    pub worst_odometry_translation_m: f64,
    /// The largest rotation error of the odometry between the same keyframes (deg).
    pub worst_odometry_rotation_deg: f64,
    /// Rejected candidates whose fit was right after all (missed loops): the price of the tests.
    /// A candidate left out as out of reach counts when its true pose was within the
    /// verification's reach of the fit's start (a right fit could have been found).
    pub missed: usize,
}

/// A loop is false when its transform is farther than this from the truth: 0.3 m or 2°.
pub const FALSE_LOOP: (f64, f64) = (0.3, 2.0);

impl LoopTrack {
    /// Judges the loops in the graph against `truth`, one true pose per registered scan.
    pub fn judge(&self, truth: &[Isometry3<f64>]) -> LoopJudgement {
        let places = self.closer.places();
        let mut judgement = LoopJudgement::default();
        let error = |a: usize, b: usize, transform: &Isometry3<f64>| {
            let (ta, tb) = (truth.get(places[a].scan)?, truth.get(places[b].scan)?);
            Some(cloud::se3::pose_error(transform, &(ta.inverse() * tb)))
        };
        let wrong = |e: &cloud::se3::PoseError| e.translation_m > FALSE_LOOP.0 || e.rotation_deg > FALSE_LOOP.1;
        for l in self.closer.loops() {
            let Some(e) = error(l.a, l.b, &l.fit.transform) else { continue };
            judgement.loops += 1;
            judgement.false_loops += usize::from(wrong(&e));
            judgement.worst_translation_m = judgement.worst_translation_m.max(e.translation_m);
            judgement.worst_rotation_deg = judgement.worst_rotation_deg.max(e.rotation_deg);
            let odometry = places[l.a].odometry.inverse() * places[l.b].odometry;
            if let Some(o) = error(l.a, l.b, &odometry) {
                judgement.worst_odometry_translation_m = judgement.worst_odometry_translation_m.max(o.translation_m);
                judgement.worst_odometry_rotation_deg = judgement.worst_odometry_rotation_deg.max(o.rotation_deg);
            }
        }
        let reach_m = self.closer.config().verify.reach_m;
        for r in self.closer.rejected() {
            let right = match (&r.fit, r.reason) {
                (Some(fit), _) => error(r.a, r.b, &fit.transform).is_some_and(|e| !wrong(&e)),
                // The fit starts at zero translation (the descriptor's yaw).
                (None, Rejection::Unreachable) => {
                    error(r.a, r.b, &Isometry3::identity()).is_some_and(|e| e.translation_m <= reach_m + FALSE_LOOP.0)
                }
                (None, _) => false,
            };
            judgement.missed += usize::from(right);
        }
        judgement
    }
}
