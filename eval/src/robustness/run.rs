//! Running a case with our odometry and judging any trajectory against the case's ground truth.

use cloud::se3::pose_error;
use nalgebra::Isometry3;

use super::case::{Case, prepared};
use edge::odometry::pipeline::{self, AteRmse};
use edge::odometry::{Odometry, OdometryConfig};

/// When a run counts as having held its track.
#[derive(Clone, Debug, PartialEq)]
pub struct HoldCriterion {
    /// The final position error must stay below this fraction of the true path length. Default
    /// 0.05 (5 %).
    pub path_fraction: f64,
    /// ... or below this, metres, whichever is larger: short and in-place runs have next to no
    /// path. Default 0.1 m.
    pub min_error_m: f64,
    /// The final rotation error must stay below this, degrees: a robot turning in place goes
    /// nowhere, only its heading can be lost. Default 5°.
    pub max_rotation_deg: f64,
}

impl Default for HoldCriterion {
    fn default() -> Self {
        HoldCriterion { path_fraction: 0.05, min_error_m: 0.1, max_rotation_deg: 5.0 }
    }
}

/// An estimated trajectory against the truth, both starting at the identity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Verdict {
    /// ATE RMSE, metres (NaN when the estimate is not finite).
    pub ate: AteRmse,
    /// Length of the true path, metres.
    pub path_m: f64,
    /// Distance between the last estimated and true positions, metres.
    pub final_error_m: f64,
    /// Angle between the last estimated and true orientations, degrees.
    pub final_rotation_deg: f64,
    /// Whether the track held: finite, and the final errors within the [`HoldCriterion`].
    pub held: bool,
}

/// Why a trajectory cannot be judged.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum JudgeError {
    /// Not one estimated pose per true pose.
    #[error("{estimated} estimated poses for {truth} true ones")]
    Count { estimated: usize, truth: usize },
    /// The ATE cannot be computed.
    #[error(transparent)]
    Trajectory(#[from] cloud::trajectory::TrajectoryError),
}

/// `estimate` (odometry frame: the first pose the identity) against `truth` (world frame).
pub fn judge(
    truth: &[Isometry3<f64>],
    estimate: &[Isometry3<f64>],
    criterion: &HoldCriterion,
) -> Result<Verdict, JudgeError> {
    if truth.len() != estimate.len() || truth.is_empty() {
        return Err(JudgeError::Count { estimated: estimate.len(), truth: truth.len() });
    }
    let first = truth[0].inverse();
    let relative: Vec<Isometry3<f64>> = truth.iter().map(|p| first * p).collect();
    let path_m = cloud::trajectory::Trajectory { poses: relative.clone(), stamps: None }.length();
    if !estimate.iter().all(finite) {
        let ate = AteRmse { unaligned: f64::NAN, aligned: None };
        return Ok(Verdict { ate, path_m, final_error_m: f64::NAN, final_rotation_deg: f64::NAN, held: false });
    }
    let accuracy = pipeline::evaluate(truth, estimate)?.ok_or(JudgeError::Count { estimated: 0, truth: 0 })?;
    let end = pose_error(&estimate[estimate.len() - 1], &relative[relative.len() - 1]);
    let allowed = (criterion.path_fraction * path_m).max(criterion.min_error_m);
    let held = end.translation_m < allowed && end.rotation_deg < criterion.max_rotation_deg;
    Ok(Verdict {
        ate: accuracy.ate,
        path_m,
        final_error_m: end.translation_m,
        final_rotation_deg: end.rotation_deg,
        held,
    })
}

/// Whether every number of a pose is finite (a diverged solve gives NaN).
fn finite(pose: &Isometry3<f64>) -> bool {
    pose.translation.vector.iter().chain(pose.rotation.coords.iter()).all(|v| v.is_finite())
}

/// What one odometry made of a case.
#[derive(Clone, Debug, PartialEq)]
pub struct Outcome {
    /// The verdict, or why there is none (the odometry refused a scan, the run failed).
    pub verdict: Result<Verdict, String>,
    /// Median wall time per scan, milliseconds, when it ran.
    pub ms_per_scan: Option<f64>,
    /// Scans on which the odometry declared itself lost. None where it did not run;
    /// KISS-ICP does not say.
    pub lost: Option<usize>,
    /// Scans located from a coarse or global alignment instead of the prediction. None where it
    /// did not run.
    pub recoveries: Option<usize>,
    /// The estimated poses (odometry frame), empty when it did not run.
    pub poses: Vec<Isometry3<f64>>,
}

impl Outcome {
    /// A run that produced no trajectory.
    pub fn failed(reason: String) -> Self {
        Outcome { verdict: Err(reason), ms_per_scan: None, lost: None, recoveries: None, poses: Vec::new() }
    }
}

/// Our odometry over the case's scans on a one-thread pool (as KISS-ICP runs, one thread), with the
/// case's preset, sweep period and compensation; channels derived first where the case says so
/// (not timed). An error of the odometry is the outcome, never a panic.
pub fn run_ours(case: &Case, criterion: &HoldCriterion) -> Outcome {
    let scans = prepared(case);
    let config =
        OdometryConfig { scan_period: case.scan_period, deskew: case.deskew, ..OdometryConfig::preset(case.preset) };
    let pool = match rayon::ThreadPoolBuilder::new().num_threads(1).build() {
        Ok(pool) => pool,
        Err(e) => return Outcome::failed(chain(&e)),
    };
    let pass = pool.install(|| -> Result<_, String> {
        let mut odometry = Odometry::new(config).map_err(|e| chain(&e))?;
        pipeline::register(&mut odometry, &scans, |_, _| Ok(())).map_err(|e| chain(&e))
    });
    let pass = match pass {
        Ok(pass) => pass,
        Err(reason) => return Outcome::failed(reason),
    };
    let verdict = judge(&case.truth(), &pass.estimate.poses, criterion).map_err(|e| chain(&e));
    let summary = pass.stats.summary();
    let r = summary.recoveries;
    let ms_per_scan = Some(summary.ms_per_frame.median);
    let (lost, recoveries) = (Some(r.lost), Some(r.coarse + r.global));
    Outcome { verdict, ms_per_scan, lost, recoveries, poses: pass.estimate.poses }
}

/// An error and its sources, `outer: inner: ...`.
pub fn chain(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(e) = source {
        text = format!("{text}: {e}");
        source = e.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    /// Ten metres east in ten 1 m steps, from a world pose that is not the identity.
    fn truth() -> Vec<Isometry3<f64>> {
        let origin = Isometry3::new(Vector3::new(5.0, -3.0, 1.0), Vector3::new(0.0, 0.0, 0.4));
        (0..=10).map(|i| origin * Isometry3::translation(i as f64, 0.0, 0.0)).collect()
    }

    /// The true trajectory in the odometry frame, the last pose moved by `last`.
    fn estimate(last: Isometry3<f64>) -> Vec<Isometry3<f64>> {
        let mut poses: Vec<Isometry3<f64>> = (0..=10).map(|i| Isometry3::translation(i as f64, 0.0, 0.0)).collect();
        poses[10] *= last;
        poses
    }

    #[test]
    fn a_perfect_estimate_holds_with_zero_error() {
        let v = judge(&truth(), &estimate(Isometry3::identity()), &HoldCriterion::default()).unwrap();
        assert!(v.held && v.ate.unaligned < 1e-12 && v.final_error_m < 1e-12, "{v:?}");
        assert!((v.path_m - 10.0).abs() < 1e-12);
    }

    #[test]
    fn the_final_error_decides_against_5_percent_of_the_path_and_5_degrees() {
        let criterion = HoldCriterion::default();
        // 0.4 m after 10 m is within 5 %, 0.6 m is not.
        let near = judge(&truth(), &estimate(Isometry3::translation(0.0, 0.4, 0.0)), &criterion).unwrap();
        let far = judge(&truth(), &estimate(Isometry3::translation(0.0, 0.6, 0.0)), &criterion).unwrap();
        assert!(near.held && (near.final_error_m - 0.4).abs() < 1e-12, "{near:?}");
        assert!(!far.held && (far.final_error_m - 0.6).abs() < 1e-12, "{far:?}");
        // RMSE of one 0.6 m error among 11 poses.
        assert!((far.ate.unaligned - (0.36f64 / 11.0).sqrt()).abs() < 1e-12);
        let turned = Isometry3::from_parts(Translation3::identity(), UnitQuaternion::from_euler_angles(0.0, 0.0, 0.1));
        let v = judge(&truth(), &estimate(turned), &criterion).unwrap();
        assert!(!v.held && (v.final_rotation_deg - 0.1f64.to_degrees()).abs() < 1e-9, "{v:?}");
    }

    #[test]
    fn an_in_place_run_is_judged_by_the_floor_and_a_diverged_one_fails() {
        let still = vec![Isometry3::identity(); 4];
        let criterion = HoldCriterion::default();
        let mut est = still.clone();
        est[3] = Isometry3::translation(0.05, 0.0, 0.0);
        assert!(judge(&still, &est, &criterion).unwrap().held);
        est[3] = Isometry3::translation(0.15, 0.0, 0.0);
        assert!(!judge(&still, &est, &criterion).unwrap().held);
        est[3] = Isometry3::translation(f64::NAN, 0.0, 0.0);
        let v = judge(&still, &est, &criterion).unwrap();
        assert!(!v.held && v.ate.unaligned.is_nan());
        assert_eq!(judge(&still, &est[..2], &criterion), Err(JudgeError::Count { estimated: 2, truth: 4 }));
    }
}
