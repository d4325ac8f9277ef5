//! `emr-edge`: the robot side of EMR-FLOAM. Thin: parses arguments, sets up logging and calls the
//! library; each command lives in its module under `cli`.

mod cli;

use anyhow::Result;
use clap::{Parser, Subcommand};
use cloud::memory::configure_allocator;

use cli::convert::ConvertArgs;
use cli::eval::EvalArgs;
use cli::odometry::OdometryArgs;
use cli::posegraph::PosegraphArgs;
use cli::run::RunArgs;
use cli::sim::SimArgs;

/// The robot (edge) side of EMR-FLOAM multi-robot LiDAR SLAM.
///
/// Each robot runs one `emr-edge`: it turns LiDAR scans into odometry, closes its own loops and
/// streams compressed keyframes to the central station over Zenoh. Scans come from a source: the
/// built-in simulator (`sim:SCENARIO:ROBOT`) or a recording (a directory of .bin/.pcd/.ply scans, a
/// ROS 1 .bag, an .mcap file). `emr-edge run` is the networked service.
#[derive(Parser, Debug)]
#[command(name = "emr-edge", version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Simulate one robot's LiDAR in a built-in scenario and write the sweeps in the KITTI layout:
    /// OUT/velodyne/NNNNNN.bin (raw, motion-distorted x y z intensity), OUT/poses.txt (ground truth
    /// at each sweep's end, first pose identity) and OUT/times.txt (sweep starts, first 0); or as
    /// the sensor's packets, written to a capture (--pcap) or sent to a loopback port (--send).
    Sim(SimArgs),
    /// Convert any source to the KITTI layout: OUT/velodyne/NNNNNN.bin (x y z intensity, float32)
    /// and OUT/times.txt (sweep starts relative to the first, seconds); for `sim:` sources also
    /// OUT/poses.txt (ground truth).
    Convert(ConvertArgs),
    /// Run F-LOAM odometry on a source as fast as possible and write OUT/poses_kitti.txt (one line
    /// per scan, sensor frame at the sweep end, first pose identity), OUT/poses_tum.txt (the same
    /// with timestamps) and OUT/stats.json (timing, features, degenerate frames, peak memory); for
    /// `sim:` sources also OUT/poses_gt_kitti.txt and the ATE against it.
    Odometry(OdometryArgs),
    /// Compare an estimated trajectory with ground truth (KITTI or TUM files): ATE RMSE with and
    /// without SE(3) alignment, and RPE (translation %, deg/100 m) KITTI style.
    Eval(EvalArgs),
    /// Optimise a 3-D pose graph in g2o format (VERTEX_SE3:QUAT, EDGE_SE3:QUAT) with
    /// Levenberg-Marquardt, least squares unless --kernel makes the loop edges robust; write the
    /// optimised graph to --out and print the initial and final error (GTSAM's: half the sum of
    /// squared Mahalanobis norms), the iterations and the optimiser's time.
    Posegraph(PosegraphArgs),
    /// The robot's network service: odometry on a source, each keyframe published on
    /// emr/FLEET/robot/ID/keyframe, the keyframes kept for backfill requests on
    /// emr/FLEET/robot/ID/keyframes, and a liveliness token on emr/FLEET/robot/ID/alive. Without
    /// --zenoh, --listen or --connect it is a loopback peer connecting to a station on
    /// tcp/127.0.0.1:7447 (`emr-station run`'s default), listening on nothing. When the
    /// source ends it keeps answering backfill requests until Ctrl-C or SIGTERM (unless
    /// --exit-when-done); either signal stops it cleanly (exit code 0) after publishing the keyframes
    /// already made.
    Run(RunArgs),
}

fn main() -> Result<()> {
    bus::init_logging();
    configure_allocator();
    match Cli::parse().command {
        Command::Sim(args) => cli::sim::simulate(args),
        Command::Convert(args) => cli::convert::convert(args),
        Command::Odometry(args) => cli::odometry::odometry(args),
        Command::Eval(args) => cli::eval::evaluate(&args),
        Command::Posegraph(args) => cli::posegraph::posegraph(&args),
        Command::Run(args) => cli::run::run(args),
    }
}
