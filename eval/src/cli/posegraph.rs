//! `emr-eval posegraph`: the pose-graph optimiser on the standard g2o benchmarks and on a
//! synthetic graph with loops and known truth.

use std::fmt;
use std::path::Path;

use anyhow::{Context, Result};
use cloud::pose_graph::synthetic::{self, SyntheticConfig};
use cloud::pose_graph::{PoseGraph, PoseGraphConfig, Report, g2o};
use nalgebra::Isometry3;
use sim::noise::SplitMix;

use super::median;

/// The g2o files measured, in `--data`.
const FILES: [&str; 2] = ["parking-garage.g2o", "smallGrid3D.g2o"];

/// Seed of the synthetic graph's noise.
const SEED: u64 = 14;

/// One graph optimised `runs` times from the same start.
pub struct Row {
    /// What was optimised, and how.
    pub name: String,
    /// Poses and edges.
    pub poses: usize,
    pub edges: usize,
    /// The last run's report.
    pub report: Report,
    /// Median optimiser time over the runs (file reading excluded), milliseconds.
    pub median_ms: f64,
    /// ATE RMSE against the truth before and after, metres (synthetic graphs only).
    pub ate: Option<(f64, f64)>,
}

/// Figures of `emr-eval posegraph`.
pub struct PosegraphReport {
    /// Timed runs per graph.
    pub runs: usize,
    /// One row per graph and configuration.
    pub rows: Vec<Row>,
}

/// Optimises the g2o files of `data` (least squares, as GTSAM does) and a synthetic graph of
/// `poses` poses (with the default Cauchy loops, and least squares), `runs` times each; writes the
/// synthetic graph's starting point to `write_synthetic` when given.
pub fn posegraph(data: &Path, poses: usize, runs: usize, write_synthetic: Option<&Path>) -> Result<PosegraphReport> {
    let least_squares = PoseGraphConfig::least_squares();
    let mut rows = Vec::new();
    for file in FILES {
        let path = data.join(file);
        let text = std::fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))?;
        let graph = g2o::parse(&text).with_context(|| format!("{}", path.display()))?.graph;
        rows.push(measure(file.to_owned(), &graph, &least_squares, runs, None)?);
        tracing::info!(file, "measured");
    }
    let mut rng = SplitMix::new(SEED);
    let synthetic = synthetic::generate(&SyntheticConfig { poses, ..SyntheticConfig::default() }, || rng.gaussian());
    if let Some(path) = write_synthetic {
        std::fs::write(path, g2o::write(&synthetic.graph))
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    let default = PoseGraphConfig::default();
    let truth = Some(synthetic.truth.as_slice());
    rows.push(measure(format!("synthetic, {} loops", default.loop_kernel), &synthetic.graph, &default, runs, truth)?);
    rows.push(measure("synthetic, least squares".to_owned(), &synthetic.graph, &least_squares, runs, truth)?);
    Ok(PosegraphReport { runs, rows })
}

/// `graph` optimised `runs` times from its own start (the copy made for each run is not timed).
fn measure(
    name: String,
    graph: &PoseGraph,
    config: &PoseGraphConfig,
    runs: usize,
    truth: Option<&[Isometry3<f64>]>,
) -> Result<Row> {
    let (mut times, mut last) = (Vec::new(), None);
    for _ in 0..runs.max(1) {
        let mut run = graph.clone();
        let report = run.optimize(config).with_context(|| format!("optimising {name}"))?;
        times.push(report.time_ms);
        last = Some((report, run));
    }
    let (report, optimised) = last.context("no run")?;
    let ate = |poses: &[Isometry3<f64>], truth: &[Isometry3<f64>]| {
        cloud::trajectory::ate(truth, poses, false).map(|a| a.rmse)
    };
    let ate =
        truth.map(|t| Ok::<_, anyhow::Error>((ate(graph.poses(), t)?, ate(optimised.poses(), t)?))).transpose()?;
    Ok(Row { name, poses: graph.poses().len(), edges: graph.edges().len(), report, median_ms: median(&times), ate })
}

impl fmt::Display for PosegraphReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "pose-graph Levenberg-Marquardt, optimiser time median of {} runs (file reading excluded)",
            self.runs
        )?;
        writeln!(
            f,
            "{:<30} {:>6} {:>6} {:>14} {:>12} {:>5} {:>9}  ATE before -> after",
            "graph", "poses", "edges", "initial error", "final error", "iter", "ms"
        )?;
        for row in &self.rows {
            let Report { initial_error, final_error, iterations, converged, .. } = row.report;
            let mark = if converged { "" } else { " (not converged)" };
            write!(
                f,
                "{:<30} {:>6} {:>6} {initial_error:>14.6} {final_error:>12.6} {iterations:>5} {:>9.1}",
                row.name, row.poses, row.edges, row.median_ms
            )?;
            match row.ate {
                Some((before, after)) => writeln!(f, "  {before:.3} m -> {after:.3} m{mark}")?,
                None => writeln!(f, "{mark}")?,
            }
        }
        Ok(())
    }
}
