//! Benchmark of the station's pairwise registration on two point-cloud files (`emr-eval merge`).
//!
//! Runs [`register`] several times on the same pair, reports the wall time of each run, the step
//! timing, the scores and, given a reference transform, the error against it.

use std::fmt;
use std::path::Path;
use std::time::Duration;

use cloud::PointCloud;
use cloud::formats::{FormatError, TransformError, read_cloud, read_transform};
use cloud::se3::{PoseError, pose_error};
use cloud::stopwatch::timed;
use nalgebra::Isometry3;

use station::pairwise::{PairwiseConfig, PairwiseError, PairwiseOutcome, register};

/// Why the benchmark could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// A cloud file could not be read.
    #[error(transparent)]
    Read(#[from] FormatError),
    /// The reference transform file is unreadable or not a rigid transform.
    #[error(transparent)]
    Transform(#[from] TransformError),
    /// The registration itself failed.
    #[error(transparent)]
    Pairwise(#[from] PairwiseError),
}

/// Measurements of repeated registrations of one pair.
#[derive(Clone, Debug)]
pub struct PairwiseBench {
    /// Points of the source cloud as given.
    pub source_points: usize,
    /// Points of the target cloud as given.
    pub target_points: usize,
    /// End-to-end wall time of each run.
    pub runs: Vec<Duration>,
    /// Outcome of the last run (all runs are identical: the sampler is seeded).
    pub outcome: PairwiseOutcome,
    /// Error of the best transform against the reference, if one was given.
    pub error: Option<PoseError>,
    /// Error of the RANSAC transform (before the polish) against the reference.
    pub coarse_error: Option<PoseError>,
}

/// Registers `source` onto `target` `runs` times (at least once) and compares with `reference`.
pub fn bench_pairwise(
    source: &PointCloud,
    target: &PointCloud,
    config: &PairwiseConfig,
    runs: usize,
    reference: Option<&Isometry3<f64>>,
) -> Result<PairwiseBench, PairwiseError> {
    let run = || {
        let (outcome, took) = timed(|| register(source, target, config));
        outcome.map(|o| (o, took))
    };
    let (mut outcome, first) = run()?;
    let mut times = vec![first];
    for _ in 1..runs {
        let (o, t) = run()?;
        times.push(t);
        outcome = o;
    }
    let error = reference.zip(outcome.best()).map(|(r, b)| pose_error(&b.transform, r));
    let coarse_error = reference.zip(outcome.best()).map(|(r, b)| pose_error(&b.coarse_transform, r));
    Ok(PairwiseBench {
        source_points: source.len(),
        target_points: target.len(),
        runs: times,
        outcome,
        error,
        coarse_error,
    })
}

/// [`bench_pairwise`] on two files (.bin, .pcd, .ply), with an optional 4x4 reference file that maps
/// source points into the target frame.
pub fn bench_merge_files(
    source: &Path,
    target: &Path,
    reference: Option<&Path>,
    config: &PairwiseConfig,
    runs: usize,
) -> Result<PairwiseBench, BenchError> {
    let s = read_cloud(source)?.cloud;
    let t = read_cloud(target)?.cloud;
    let reference = reference.map(read_transform).transpose()?;
    Ok(bench_pairwise(&s, &t, config, runs, reference.as_ref())?)
}

impl fmt::Display for PairwiseBench {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let ms = cloud::stopwatch::millis;
        let mut sorted = self.runs.clone();
        sorted.sort();
        let median = sorted.get(sorted.len() / 2).copied().unwrap_or_default();
        let min = sorted.first().copied().unwrap_or_default();
        writeln!(f, "source {} points, target {} points", self.source_points, self.target_points)?;
        writeln!(f, "runs {}: median {:.1} ms, best {:.1} ms", self.runs.len(), ms(median), ms(min))?;
        match &self.outcome {
            PairwiseOutcome::Aligned(_) => writeln!(f, "outcome: aligned")?,
            PairwiseOutcome::NotAligned { reason, .. } => writeln!(f, "outcome: not aligned ({reason})")?,
        }
        if let Some(r) = self.outcome.best() {
            let t = &r.timing;
            writeln!(
                f,
                "keypoints {} / {}, correspondences {}, inliers {} ({:.1}%), RANSAC samples {}",
                r.keypoints.0.len(),
                r.keypoints.1.len(),
                r.correspondences,
                r.inliers.len(),
                r.inlier_ratio * 100.0,
                r.ransac_iterations
            )?;
            writeln!(
                f,
                "confidence: fitness {:.2} 1/m², overlap {:.3}, score {:.3}",
                r.confidence.fitness, r.confidence.overlap, r.confidence.score
            )?;
            for (name, s) in [("source", &t.source), ("target", &t.target)] {
                writeln!(
                    f,
                    "{name}: preprocess {:.1} ms, normals {:.1} ms, keypoints {:.1} ms, descriptors {:.1} ms",
                    ms(s.preprocess),
                    ms(s.normals),
                    ms(s.keypoints),
                    ms(s.descriptors)
                )?;
            }
            writeln!(
                f,
                "matching {:.1} ms, ransac {:.1} ms, polish {:.1} ms, confidence {:.1} ms, total {:.1} ms",
                ms(t.estimate.matching),
                ms(t.estimate.ransac),
                ms(t.estimate.polish),
                ms(t.confidence),
                ms(t.total)
            )?;
            let m = r.transform.to_homogeneous();
            for row in 0..4 {
                writeln!(f, "  [{:10.6} {:10.6} {:10.6} {:10.4}]", m[(row, 0)], m[(row, 1)], m[(row, 2)], m[(row, 3)])?;
            }
        }
        if let (Some(e), Some(c)) = (&self.error, &self.coarse_error) {
            writeln!(
                f,
                "error vs reference: {:.3} m, {:.3} deg (before polish {:.3} m, {:.3} deg)",
                e.translation_m, e.rotation_deg, c.translation_m, c.rotation_deg
            )?;
        }
        Ok(())
    }
}
