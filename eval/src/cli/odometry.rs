//! `emr-eval odometry`: time per scan of the library's odometry loop on scans held in memory.

use std::fmt;

use anyhow::{Result, bail};
use edge::odometry::pipeline::{self, AteRmse};
use edge::odometry::{Odometry, OdometryConfig};
use edge::source::SourceScan;

use super::median;

/// Figures of `emr-eval odometry`.
pub struct OdometryReport {
    /// Scans per run.
    pub scans: usize,
    /// Points per scan, on average.
    pub points: usize,
    /// Figures of each run.
    pub runs: Vec<RunFigures>,
    /// ATE RMSE, when the source has ground truth.
    pub ate: Option<AteRmse>,
}

/// One timed pass over the scans, milliseconds per scan.
pub struct RunFigures {
    /// Median wall time.
    pub median: f64,
    /// 95th percentile of the wall time.
    pub p95: f64,
    /// Median CPU time of the thread that ran the odometry.
    pub cpu: f64,
    /// Median time of the stages: features, registration, map.
    pub stages: [f64; 3],
}

impl fmt::Display for OdometryReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "odometry on {} scans of {} points, one thread", self.scans, self.points)?;
        for (i, run) in self.runs.iter().enumerate() {
            let RunFigures { median, p95, cpu, stages: [features, registration, map] } = run;
            writeln!(
                f,
                "run {}: median {median:.2} ms per scan (CPU {cpu:.2} ms), p95 {p95:.2} ms (features \
                 {features:.2}, registration {registration:.2}, map {map:.2})",
                i + 1
            )?;
        }
        let wall = median(&self.runs.iter().map(|r| r.median).collect::<Vec<_>>());
        let cpu = median(&self.runs.iter().map(|r| r.cpu).collect::<Vec<_>>());
        writeln!(f, "median of the runs: {wall:.2} ms per scan (CPU {cpu:.2} ms)")?;
        match self.ate {
            Some(AteRmse { aligned: Some(aligned), unaligned }) => {
                writeln!(f, "ATE RMSE {:.2} cm aligned, {:.2} cm unaligned", aligned * 100.0, unaligned * 100.0)?
            }
            // A straight path leaves the rotation about it undetermined.
            Some(AteRmse { aligned: None, unaligned }) => {
                writeln!(f, "ATE RMSE {:.2} cm unaligned (no alignment: straight path)", unaligned * 100.0)?
            }
            None => {}
        }
        Ok(())
    }
}

/// Registers `scans` `runs` times, each pass with a fresh odometry on a one-thread pool (the
/// calling thread stays out of it, so no pass waits on a hand-over between threads).
pub fn odometry(scans: &[SourceScan], config: &OdometryConfig, runs: usize) -> Result<OdometryReport> {
    if scans.is_empty() {
        bail!("the source gave no scans");
    }
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let mut report = OdometryReport {
        scans: scans.len(),
        points: scans.iter().map(|s| s.cloud.len()).sum::<usize>() / scans.len(),
        runs: Vec::new(),
        ate: None,
    };
    for _ in 0..runs.max(1) {
        let pass = pool.install(|| -> Result<_> {
            let mut odometry = Odometry::new(config.clone())?;
            Ok(pipeline::register(&mut odometry, scans, |_, _| Ok(()))?)
        })?;
        let spread = cloud::stats::Spread::of(pass.stats.ms());
        let (wall, p95) = (spread.median, spread.p95);
        let cpu = median(&pass.cpu_ms);
        let stages = pass.stats.stages().each_ref().map(|v| median(v));
        report.runs.push(RunFigures { median: wall, p95, cpu, stages });
        report.ate = pipeline::evaluate(&pass.truth, &pass.estimate.poses)?.map(|a| a.ate);
    }
    Ok(report)
}
