//! `emr-eval`: what measures the system rather than serves it. Thin: parses arguments, sets up
//! logging and calls the commands under `cli`.

mod cli;

use anyhow::Result;
use clap::Parser;

/// Measurements of EMR-FLOAM: micro-benchmarks on real data, the odometry's robustness matrix
/// beside KISS-ICP, loop closure, pose graphs, registration, merging, the station under load and
/// the paper's four systems. docs/benchmarks.md gives each table with the command that
/// regenerates it. Data paths default to ../shared/data, as seen from the repository root.
#[derive(Parser, Debug)]
#[command(name = "emr-eval", version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: cli::Command,
}

fn main() -> Result<()> {
    bus::init_logging();
    // The load bench runs a station in this process: it frees large merge buffers all the time.
    cloud::memory::configure_allocator();
    cli::run(Cli::parse().command)
}
