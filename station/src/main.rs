//! `emr-station`: the central station of EMR-FLOAM. Thin: parses arguments, sets up logging and calls
//! the libraries.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use proto::{Fleet, keyexpr};

/// The central station of EMR-FLOAM multi-robot LiDAR SLAM.
///
/// The station collects the keyframes that every robot of a fleet streams over Zenoh, finds where
/// the robots' maps overlap, fuses them into one global 3D map and publishes it with a confidence
/// score per robot. Today it offers the inspection tools below; map merging and the networked
/// service arrive with the next releases.
#[derive(Parser, Debug)]
#[command(name = "emr-station", version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Print the Zenoh key expressions of a fleet: what to subscribe to from your own tools.
    Keys {
        /// Fleet name (ASCII letters, digits, '-' and '_').
        #[arg(long, default_value = "demo")]
        fleet: String,
        /// Robot id used in the per-robot keys.
        #[arg(long, default_value_t = 1)]
        robot: u32,
    },
    /// Read point-cloud files (.bin KITTI, .pcd, .ply) and print what they hold: points, channels,
    /// bounds and how many invalid (NaN/inf) points were dropped.
    Info {
        /// The files to read.
        #[arg(required = true)]
        files: Vec<PathBuf>,
    },
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Keys { fleet, robot } => print_keys(&Fleet::new(&fleet)?, robot),
        Command::Info { files } => {
            for f in &files {
                print_info(f)?;
            }
        }
    }
    Ok(())
}

fn print_keys(fleet: &Fleet, robot: u32) {
    let rows = [
        (keyexpr::keyframe(fleet, robot), "Keyframe", "edge"),
        (keyexpr::posegraph(fleet, robot), "PoseGraphUpdate", "edge"),
        (keyexpr::keyframe_store(fleet, robot), "queryable: KeyframeRequest -> Keyframe", "edge"),
        (keyexpr::alive(fleet, robot), "liveliness token", "edge"),
        (keyexpr::global_map(fleet), "GlobalMap (also a queryable)", "station"),
        (keyexpr::station_status(fleet), "StationStatus", "station"),
        (keyexpr::all_robots(fleet), "wildcard: every robot topic", "subscribers"),
    ];
    for (key, payload, from) in rows {
        println!("{key:<40} {payload:<42} {from}");
    }
}

fn print_info(path: &std::path::Path) -> Result<()> {
    let read = cloud::formats::read_cloud(path)?;
    let c = &read.cloud;
    let ch = c.channels();
    let (lo, hi) = c.points.iter().fold(([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]), |(lo, hi), p| {
        (std::array::from_fn(|i| lo[i].min(p[i])), std::array::from_fn(|i| hi[i].max(p[i])))
    });
    println!(
        "{}: {} points (dropped {} non-finite), intensity {}, ring {}, time {}",
        path.display(),
        c.len(),
        read.dropped_non_finite,
        yes_no(ch.intensity),
        yes_no(ch.ring),
        yes_no(ch.time)
    );
    if !c.is_empty() {
        println!("  bounds min {lo:.3?} max {hi:.3?}");
    }
    c.validate().with_context(|| format!("{}: inconsistent cloud", path.display()))?;
    Ok(())
}

fn yes_no(b: bool) -> &'static str {
    if b { "yes" } else { "no" }
}
