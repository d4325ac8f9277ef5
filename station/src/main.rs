//! `emr-station`: the central station of EMR-FLOAM. Thin: parses arguments, sets up logging and calls
//! the command modules in `cli`, which call the library.

mod cli;

use anyhow::Result;
use clap::{Parser, Subcommand};
use cli::{certs, files, service};

/// The central station of EMR-FLOAM multi-robot LiDAR SLAM.
///
/// The station collects the keyframes that every robot of a fleet streams over Zenoh, finds where
/// the robots' maps overlap, fuses them into one global 3D map and publishes it with a confidence
/// score per robot (`run`); `watch` and `save` inspect a running system, the other commands work on
/// files.
#[derive(Parser, Debug)]
#[command(name = "emr-station", version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Print the Zenoh key expressions of a fleet: what to subscribe to from your own tools.
    Keys(service::KeysArgs),
    /// Read point-cloud files (.bin KITTI, .pcd, .ply) and print what they hold: points, channels,
    /// bounds and how many invalid (NaN/inf) points were dropped.
    Info(files::InfoArgs),
    /// Merge robot maps (.pcd, .ply, .bin) into one global map, without initial guesses.
    ///
    /// Writes DIR/global_map.ply (binary little endian, in the reference map's frame) and
    /// DIR/transforms.json: per input map its `transform` (4x4 row-major, maps THAT MAP's points
    /// into the global frame; identity when unmerged), `confidence` (the overlap-aware score of
    /// the weakest tree edge to the reference, 1 for the reference, 0 unmerged) and `status`
    /// ("merged" or "unmerged"); per accepted pair an edge {a, b, transform, confidence, inliers}
    /// whose transform maps map b's points into map a's frame (a, b: 0-based input positions);
    /// and `timing_ms` per stage; and DIR/top_down.png: the merged maps seen from above in the
    /// global frame, one colour per input.
    Merge(files::MergeArgs),
    /// Register SOURCE onto TARGET; prints the 4x4 transform mapping SOURCE points into the
    /// TARGET frame (4 lines, row-major) and a confidence line.
    Align(files::AlignArgs),
    /// Run the station service: collect every robot of the fleet over Zenoh, merge their maps and
    /// publish the global map (also answered to queries) and the station status. State persists
    /// in DATA_DIR/station.redb; SIGINT or SIGTERM commits the last batch and exits 0.
    Run(service::RunArgs),
    /// Print one line per sample on KEYEXPR (e.g. 'emr/demo/**'): key, message type and a summary.
    /// Without network options, connects to tcp/127.0.0.1:7447.
    Watch(service::WatchArgs),
    /// Fetch the latest global map from the fleet's station and write its cloud (.ply, .pcd or
    /// .bin by extension). Without network options, connects to tcp/127.0.0.1:7447.
    Save(service::SaveArgs),
    /// Make a fleet's certificates for zenoh's mutual TLS (a CA, the router's, the station's, one
    /// per robot) and the zenoh configurations that use them: the router's with the access control
    /// that lets robot N publish only under emr/{fleet}/robot/N/**, the station only under
    /// emr/{fleet}/station/**, and tools (plain TCP) only subscribe and query.
    Certs(certs::CertsArgs),
}

fn main() -> Result<()> {
    bus::init_logging();
    // A long-running station frees large merge buffers all the time: give them pages of their own.
    cloud::memory::configure_allocator();
    match Cli::parse().command {
        Command::Keys(args) => service::keys(args),
        Command::Info(args) => files::info(args),
        Command::Merge(args) => files::merge(args),
        Command::Align(args) => files::align(args),
        Command::Run(args) => service::run(args),
        Command::Watch(args) => service::watch(args),
        Command::Save(args) => service::save(args),
        Command::Certs(args) => certs::certs(args),
    }
}
