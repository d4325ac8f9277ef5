//! `emr-edge posegraph`: optimises a g2o pose graph with the library's Levenberg-Marquardt.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow};
use cloud::pose_graph::{Kernel, PoseGraph, PoseGraphConfig, Report, g2o};

/// Arguments of `emr-edge posegraph`.
#[derive(clap::Args, Debug)]
pub struct PosegraphArgs {
    /// Pose graph in g2o format (VERTEX_SE3:QUAT, EDGE_SE3:QUAT, FIX).
    input: PathBuf,
    /// Where to write the optimised graph (g2o).
    #[arg(long)]
    out: PathBuf,
    /// Linearisations at most.
    #[arg(long, default_value_t = 100)]
    max_iterations: usize,
    /// Robust kernel of the loop edges (those between non-consecutive vertices): none, huber:K or
    /// cauchy:K, K in standard deviations of each edge's noise. Odometry edges are least squares.
    #[arg(long, default_value_t = Kernel::None)]
    kernel: Kernel,
}

/// `emr-edge posegraph`.
pub fn posegraph(args: &PosegraphArgs) -> Result<()> {
    let mut graph = read(&args.input)?;
    let config = PoseGraphConfig {
        max_iterations: args.max_iterations,
        loop_kernel: args.kernel,
        ..PoseGraphConfig::least_squares()
    };
    let report = graph.optimize(&config).with_context(|| format!("optimising {}", args.input.display()))?;
    std::fs::write(&args.out, g2o::write(&graph)).with_context(|| format!("cannot write {}", args.out.display()))?;
    print_report(&graph, &report);
    Ok(())
}

/// The graph of a g2o file; errors name the file (and the parser the line). Edges whose
/// information matrix was repaired are counted in a warning.
pub fn read(path: &Path) -> Result<PoseGraph> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let read = g2o::parse(&text).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    if let Some(first) = read.repaired.first() {
        tracing::warn!(
            "{}: {} of {} edges had an information matrix that is not positive semi-definite (first on line {}, \
             smallest eigenvalue {:.3e}); their negative eigenvalues were set to zero",
            path.display(),
            read.repaired.len(),
            read.graph.edges().len(),
            first.line,
            first.min_eigenvalue
        );
    }
    Ok(read.graph)
}

fn print_report(graph: &PoseGraph, report: &Report) {
    println!("poses {} edges {}", graph.poses().len(), graph.edges().len());
    println!("initial error {:.6}", report.initial_error);
    println!("final error {:.6}", report.final_error);
    let how = if report.converged { "converged" } else { "not converged" };
    println!("iterations {} ({how})", report.iterations);
    println!("optimiser {:.1} ms", report.time_ms);
}
