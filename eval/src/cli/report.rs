//! `emr-eval report`: the paper's four systems through the demo.

use std::path::PathBuf;

use anyhow::{Context, Result};
use eval::report::{self, ReportConfig};

/// The arguments of `emr-eval report`.
#[derive(clap::Args, Debug)]
pub struct ReportArgs {
    /// Output directory.
    #[arg(long, default_value = "out/report")]
    out: PathBuf,
    /// Scenario to run (repeatable) [default: warehouse-small, warehouse-large, campus, aisles].
    #[arg(long = "scenario")]
    scenarios: Vec<String>,
    /// Scans per robot [default: the whole scenario].
    #[arg(long)]
    frames: Option<usize>,
}

/// `emr-eval report`.
pub fn report(args: ReportArgs) -> Result<()> {
    let mut config = ReportConfig { frames: args.frames, out: args.out, ..ReportConfig::default() };
    if !args.scenarios.is_empty() {
        config.scenarios = args.scenarios;
    }
    let started = std::time::Instant::now();
    let report = super::runtime()?.block_on(async {
        let interrupt = bus::shutdown_signal().context("cannot handle SIGINT/SIGTERM")?;
        report::run(&config, interrupt, |line| eprintln!("[{:>5.0} s] {line}", started.elapsed().as_secs_f64()))
            .await
            .map_err(anyhow::Error::from)
    })?;
    std::fs::create_dir_all(&config.out).with_context(|| format!("cannot create {}", config.out.display()))?;
    for (name, text) in [("report.md", report::markdown(&report)), ("report.json", report::json(&report))] {
        let path = config.out.join(name);
        std::fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))?;
        println!("wrote {}", path.display());
    }
    Ok(())
}
