//! The commands of `emr-eval`, one module each where they need more than a line.

mod codec;
mod load;
mod loops;
mod merge;
mod odometry;
mod packets;
mod posegraph;
mod report;
mod robustness;

use std::path::PathBuf;

use anyhow::Result;
use clap::Subcommand;
use edge::args::{SensorArg, SourceArgs, TuningArgs, scenario_values};
use edge::odometry::pipeline::{self, Tuning};
use load::LoadArgs;
use loops::LoopsArgs;
use merge::MergeArgs;
use report::ReportArgs;
use robustness::RobustnessArgs;

#[derive(Subcommand, Debug)]
pub enum Command {
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
    /// LiDAR simulator: sweeps and rays per second on one core and on all cores.
    Sim {
        /// LiDAR model [default: all].
        #[arg(long, value_enum)]
        sensor: Option<SensorArg>,
        /// Scenario whose robot 0 is simulated.
        #[arg(long, default_value = "warehouse-small", value_parser = scenario_values())]
        scenario: String,
        /// Sweeps timed per figure, spread over the sequence.
        #[arg(long, default_value_t = 50)]
        frames: usize,
    },
    /// Odometry: the scans are read into memory first, then registered `--runs` times on a
    /// one-thread pool; median and p95 milliseconds per scan of each run, and the ATE when the
    /// source has ground truth.
    Odometry {
        #[command(flatten)]
        source: Box<SourceArgs>,
        #[command(flatten)]
        tuning: TuningArgs,
        /// Scans read from the source.
        #[arg(long, default_value_t = 600)]
        frames: usize,
        /// Timed passes over the scans (each with a fresh odometry).
        #[arg(long, default_value_t = 3)]
        runs: usize,
    },
    /// Odometry robustness matrix: every k-th scan of KITTI 00 and of the simulator,
    /// starting mid-run; a car at 10 and 20 m/s; turning in place at 90 and 180 deg/s; sensors at
    /// 1, 2, 5 Hz; Ouster-like 64 and 128 beams; shuffled points. Per case: our ATE, whether the
    /// track held (final error below 5 % of the path or 0.1 m, and 5 deg), beside KISS-ICP on the
    /// same scans (scripts/compare_kiss_icp.py). Progress on stderr, the table on stdout.
    Robustness(RobustnessArgs),
    /// Pose-graph optimisation: the g2o benchmarks DIR/parking-garage.g2o and DIR/smallGrid3D.g2o
    /// (least squares, as GTSAM measures them) and a synthetic graph of laps around a ring with
    /// noisy odometry and 5 % loop edges (default Cauchy loop kernel, and least squares): poses,
    /// edges, initial and final error, iterations, median optimiser milliseconds (file reading
    /// excluded), and on the synthetic graph the ATE against the truth before and after.
    Posegraph {
        /// Directory of the g2o files.
        #[arg(long, default_value = "../shared/data/posegraph")]
        data: PathBuf,
        /// Poses of the synthetic graph.
        #[arg(long, default_value_t = 5000)]
        poses: usize,
        /// Timed runs per graph (the median is reported).
        #[arg(long, default_value_t = 3)]
        runs: usize,
        /// Also write the synthetic graph (its starting point) to this g2o file.
        #[arg(long)]
        write_synthetic: Option<PathBuf>,
    },
    /// Loop closure, the paper's comparison: MR (odometry only) against EMR (with loops)
    /// on the simulated robots that revisit places and on the aisles' identical rows: ATE of both,
    /// loops accepted, false loops (more than 0.3 m or 2 deg from the true relative pose), loop
    /// milliseconds per keyframe on one core.
    Loops(LoopsArgs),
    /// LiDAR packet decoding: every capture of DIR decoded from memory on one core, against the
    /// time the sensor took to send it.
    Packets {
        /// Directory of .pcap / .pcapng captures (Ouster metadata beside each as NAME.json).
        #[arg(default_value = "../shared/data/lidar_packets")]
        data: PathBuf,
        /// Timed passes per capture (the median is reported).
        #[arg(long, default_value_t = 50)]
        repeat: usize,
    },
    /// Fine registration (GICP, VGICP): median time per registration on one thread and on all, and
    /// the error against the reference pose, on DIR/{source,target}.ply and DIR/T_target_source.txt.
    Gicp {
        /// Directory of the cloud pair.
        #[arg(long, default_value = "../shared/data/gicp_pair")]
        data: PathBuf,
        /// Timed runs per figure (the median is reported).
        #[arg(long, default_value_t = 20)]
        runs: usize,
    },
    /// The station's pairwise global registration timed on SOURCE and TARGET (default: the KITTI 08
    /// reverse revisit in ../shared/data/kitti08_revisit, 001500.bin onto 000720.bin, with its
    /// reference).
    Merge(MergeArgs),
    /// A station under a simulated fleet: ROBOTS robots each publish a keyframe per scan at
    /// RATE_HZ for SECONDS (simulated scans at true poses, prepared before the clock starts) to an
    /// in-process station over loopback; when they are done the station catches up.
    ///
    /// Prints keyframes sent and held, the station's intake per second and largest backlog, merges
    /// and their times (median / p95 / max), each keyframe's latency from its arrival at the station
    /// to the first published global map holding it (and how many no map held), the merge queue's
    /// depth, the catch-up time and the process's resident memory (before publishing, at the end,
    /// peak). Progress on stderr.
    Load(LoadArgs),
    /// The paper's four systems side by side: MR-ALOAM, MR-FLOAM (no loops), EMR-ALOAM, EMR-FLOAM
    /// (loops), each run through the demo on the simulated scenarios. Writes OUT/report.md (ATE per
    /// robot, ms per scan, map points and bytes, merge time, loops), OUT/report.json, and each
    /// run's demo results in OUT/SCENARIO/SYSTEM. Progress on stderr.
    Report(ReportArgs),
    /// Global registration without an initial guess (FPFH + RANSAC, the scan defaults): median
    /// time of `cloud::global::align` and the error against the reference, on DIR/001500.bin onto
    /// DIR/000720.bin with DIR/T_000720_001500.txt (the KITTI 08 reverse revisit).
    Global {
        /// Directory of the scan pair.
        #[arg(long, default_value = "../shared/data/kitti08_revisit")]
        data: PathBuf,
        /// Timed runs (the median is reported).
        #[arg(long, default_value_t = 10)]
        runs: usize,
    },
}

/// `emr-eval COMMAND`.
pub fn run(command: Command) -> Result<()> {
    match command {
        Command::Codec { data, step, repeat } => println!("{}", codec::codec(&data, step, repeat)?),
        Command::Sim { sensor, scenario, frames } => {
            let scenario = sim::Scenario::by_name(&scenario)?;
            let sensors = sensor.map_or(sim::SensorKind::ALL.to_vec(), |s| vec![s.into()]);
            for kind in sensors {
                println!("{}", eval::simulator::run(&scenario, kind, frames)?);
            }
        }
        Command::Odometry { source, tuning, frames, runs } => {
            let config = Tuning::from(&tuning).load()?;
            let sim = source.sim.config();
            let scans =
                pipeline::read_all(pipeline::open(&source.input(), source.reading(), Some(frames), &config, &sim)?)?;
            println!("{}", odometry::odometry(&scans, &config, runs)?);
        }
        Command::Robustness(args) => robustness::robustness(args)?,
        Command::Posegraph { data, poses, runs, write_synthetic } => {
            println!("{}", posegraph::posegraph(&data, poses, runs, write_synthetic.as_deref())?)
        }
        Command::Loops(args) => loops::loops(args)?,
        Command::Merge(args) => merge::merge(args)?,
        Command::Load(args) => load::load(args)?,
        Command::Report(args) => report::report(args)?,
        Command::Packets { data, repeat } => println!("{}", packets::packets(&data, repeat)?),
        Command::Gicp { data, runs } => println!("{}", eval::registration::gicp(&data, runs)?),
        Command::Global { data, runs } => {
            let (source, target, reference) =
                (data.join("001500.bin"), data.join("000720.bin"), data.join("T_000720_001500.txt"));
            let config = cloud::global::GlobalConfig::default();
            println!("{}", eval::global::global(&source, &target, Some(&reference), &config, runs)?);
        }
    }
    Ok(())
}

/// The median of `values` (nearest rank, [`cloud::stats::Spread`]'s); NaN when there are none.
fn median(values: &[f64]) -> f64 {
    if values.is_empty() { f64::NAN } else { cloud::stats::Spread::of(values).median }
}

/// The runtime of the commands that run a station or robots in this process.
fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread().enable_all().build()?)
}
