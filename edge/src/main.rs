//! `emr-edge`: the robot side of EMR-FLOAM. Thin: parses arguments, sets up logging and calls the library.

mod bench;

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

/// The robot (edge) side of EMR-FLOAM multi-robot LiDAR SLAM.
///
/// Each robot runs one `emr-edge`: it turns LiDAR scans into odometry, closes its own loops and
/// streams compressed keyframes to the central station over Zenoh. Today it offers the benchmarks;
/// the scan sources, odometry and the networked service arrive with the next releases.
#[derive(Parser, Debug)]
#[command(name = "emr-edge", version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Measure speed and size figures on real data (the numbers in the README).
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
    },
}

#[derive(Subcommand, Debug)]
enum BenchCommand {
    /// Point-cloud codec: compression ratio against raw f32 xyz, encode and decode time per scan
    /// (one core), maximum coordinate error, on every KITTI .bin scan of a directory.
    Codec {
        /// Directory of KITTI .bin scans (searched recursively one level: DIR or DIR/velodyne).
        #[arg(default_value = "../shared/data/kitti00")]
        data: PathBuf,
        /// Quantisation step in metres; every coordinate decodes within step/2.
        #[arg(long, default_value_t = 0.001)]
        step: f64,
        /// Timed repetitions per scan (the median is reported).
        #[arg(long, default_value_t = 20)]
        repeat: usize,
    },
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Bench { what: BenchCommand::Codec { data, step, repeat } } => {
            let report = bench::codec(&data, step, repeat)?;
            println!("{report}");
        }
    }
    Ok(())
}
