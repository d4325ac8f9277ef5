//! `emr-edge`: the robot side of EMR-FLOAM. Thin: parses arguments, sets up logging and calls the library.

mod bench;

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use bus::NetworkArgs;
use clap::builder::{PossibleValue, PossibleValuesParser};
use clap::{Parser, Subcommand, ValueEnum};
use cloud::Preset;
use cloud::trajectory::Trajectory;
use edge::memory::{RELEASE_EVERY, configure_allocator, peak_rss_mb, release_free_memory, rss_mb};
use edge::node::{self, NodeConfig, NodeSummary, Rate, SourceEnd};
use edge::odometry::stats::RunStats;
use edge::odometry::{Odometry, OdometryConfig};
use edge::recording::{self, RecordingOptions, RingModel, Spin, TimeModel};
use sim::{Scenario, SensorKind, SimConfig, Simulator};
use edge::source::{Source, SourceSpec};
use indicatif::{ProgressBar, ProgressStyle};
use proto::Fleet;

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
    /// Measure speed and size figures on real data (the numbers in the README).
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
    },
    /// Simulate one robot's LiDAR in a built-in scenario and write the sweeps in the KITTI layout:
    /// OUT/velodyne/NNNNNN.bin (raw, motion-distorted x y z intensity), OUT/poses.txt (ground truth
    /// at each sweep's end, first pose identity) and OUT/times.txt (sweep starts, first 0).
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

/// Arguments of `emr-edge run`.
#[derive(clap::Args, Debug)]
struct RunArgs {
    /// Fleet name: ASCII letters, digits, '-' and '_'.
    #[arg(long, value_parser = |s: &str| Fleet::new(s))]
    fleet: Fleet,
    /// Robot id within the fleet [default: ROBOT of a sim:SCENARIO:ROBOT source, which it must match].
    #[arg(long)]
    robot: Option<u32>,
    /// The source: a directory of scans, a .bag or .mcap file, or sim:SCENARIO:ROBOT.
    #[arg(long, value_name = "INPUT")]
    source: SourceSpec,
    /// Topic of sensor_msgs/PointCloud2 in a bag or MCAP file [default: the only one].
    #[arg(long)]
    topic: Option<String>,
    /// Pace: realtime plays scans at their stamps, max as fast as the odometry goes.
    #[arg(long, value_enum, default_value_t = RateArg::Realtime)]
    rate: RateArg,
    /// Stop reading after this many scans.
    #[arg(long)]
    max_frames: Option<usize>,
    #[command(flatten)]
    tuning: TuningArgs,
    /// Exit when the source ends instead of answering backfill requests until a signal.
    #[arg(long)]
    exit_when_done: bool,
    /// When the source ends, write {"robot", "frames", "keyframes", "published_bytes"} here (JSON):
    /// how scripts and the system tests learn that a robot is done while it keeps serving.
    #[arg(long, value_name = "FILE")]
    summary: Option<PathBuf>,
    #[command(flatten)]
    network: NetworkArgs,
}

/// Paces of `emr-edge run`.
#[derive(Clone, Copy, Debug, ValueEnum)]
enum RateArg {
    /// Scans at their stamps, as a live sensor delivers them.
    Realtime,
    /// As fast as the odometry goes.
    Max,
}

impl From<RateArg> for Rate {
    fn from(r: RateArg) -> Self {
        match r {
            RateArg::Realtime => Rate::Realtime,
            RateArg::Max => Rate::Max,
        }
    }
}

/// How the odometry is configured (shared by the commands that run it).
#[derive(clap::Args, Debug)]
struct TuningArgs {
    /// Odometry configuration (TOML; `emr-edge odometry --print-config` shows every key and its
    /// default). Keys left out keep the preset's values.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Preset the configuration starts from: indoor (warehouses, ranges under ~40 m) or outdoor.
    #[arg(long, default_value_t = Preset::Indoor)]
    preset: Preset,
    /// Turn motion compensation off: for recordings published already compensated (KITTI's).
    #[arg(long)]
    no_deskew: bool,
}

/// Arguments of `emr-edge odometry`.
#[derive(clap::Args, Debug)]
struct OdometryArgs {
    #[command(flatten)]
    source: SourceArgs,
    /// Output directory (created if missing).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    tuning: TuningArgs,
    /// Stop after this many scans.
    #[arg(long)]
    max_frames: Option<usize>,
    /// Print the configuration that would be used (TOML) and exit.
    #[arg(long)]
    print_config: bool,
}

/// Arguments of `emr-edge eval`.
#[derive(clap::Args, Debug)]
struct EvalArgs {
    /// Ground-truth trajectory (KITTI: 12 numbers per line; TUM: stamp tx ty tz qx qy qz qw).
    #[arg(long)]
    gt: PathBuf,
    /// Estimated trajectory, same formats.
    #[arg(long)]
    est: PathBuf,
    /// TUM files: largest stamp difference (s) for two poses to be paired.
    #[arg(long, default_value_t = 0.02)]
    max_dt: f64,
}

/// Where scans come from (shared by the commands that read a source).
#[derive(clap::Args, Debug)]
struct SourceArgs {
    /// The source: a directory of scans, a .bag or .mcap file, or sim:SCENARIO:ROBOT.
    input: SourceSpec,
    /// Topic of sensor_msgs/PointCloud2 in a bag or MCAP file [default: the only one].
    #[arg(long)]
    topic: Option<String>,
}

/// Arguments of `emr-edge convert`.
#[derive(clap::Args, Debug)]
struct ConvertArgs {
    #[command(flatten)]
    source: SourceArgs,
    /// Output directory (created if missing; must not hold scans already).
    #[arg(long)]
    out: PathBuf,
    /// Convert at most this many scans.
    #[arg(long)]
    frames: Option<usize>,
}

/// Arguments of `emr-edge sim`.
#[derive(clap::Args, Debug)]
struct SimArgs {
    /// Scenario to simulate.
    #[arg(long, value_parser = scenario_values())]
    scenario: String,
    /// Robot to simulate: 1 is the scenario's first robot (robot ids on the wire start at 1 too).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    robot: u32,
    /// Output directory for the KITTI layout (created if missing).
    #[arg(long, required_unless_present = "svg")]
    out: Option<PathBuf>,
    /// Seed of the range noise and dropouts; the same seed gives bit-identical sweeps.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Sweeps to write [default: the whole scenario; beyond it the robot stays parked].
    #[arg(long)]
    frames: Option<usize>,
    /// LiDAR model.
    #[arg(long, value_enum, default_value_t = SensorArg::Vlp16)]
    sensor: SensorArg,
    /// Standard deviation of the Gaussian range noise, metres.
    #[arg(long, default_value_t = 0.01)]
    noise: f64,
    /// Probability that a return is lost.
    #[arg(long, default_value_t = 0.01)]
    dropout: f64,
    /// Also draw the world and every robot's path, top-down, into this SVG file.
    #[arg(long)]
    svg: Option<PathBuf>,
}

/// The LiDAR models on the command line.
#[derive(Clone, Copy, Debug, ValueEnum)]
enum SensorArg {
    /// Velodyne VLP-16: 16 beams, -15..+15 deg, 1800 columns, 100 m.
    Vlp16,
    /// HDL-64E-like: 64 beams, -24.9..+2 deg, 2083 columns, 120 m.
    Hdl64,
}

impl From<SensorArg> for SensorKind {
    fn from(s: SensorArg) -> Self {
        match s {
            SensorArg::Vlp16 => SensorKind::Vlp16,
            SensorArg::Hdl64 => SensorKind::Hdl64,
        }
    }
}

/// The scenario names with their descriptions, so `--help` lists them.
fn scenario_values() -> PossibleValuesParser {
    PossibleValuesParser::new(sim::CATALOG.iter().map(|s| PossibleValue::new(s.name).help(s.description)))
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
    /// LiDAR simulator: sweeps and rays per second on one core and on all cores.
    Sim {
        /// LiDAR model [default: both].
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
        source: SourceArgs,
        #[command(flatten)]
        tuning: TuningArgs,
        /// Scans read from the source.
        #[arg(long, default_value_t = 600)]
        frames: usize,
        /// Timed passes over the scans (each with a fresh odometry).
        #[arg(long, default_value_t = 3)]
        runs: usize,
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
}

fn main() -> Result<()> {
    bus::init_logging();
    configure_allocator();
    match Cli::parse().command {
        Command::Bench { what: BenchCommand::Codec { data, step, repeat } } => {
            let report = bench::codec(&data, step, repeat)?;
            println!("{report}");
        }
        Command::Bench { what: BenchCommand::Sim { sensor, scenario, frames } } => {
            let scenario = load_scenario(&scenario)?;
            let sensors = sensor.map_or(SensorKind::ALL.to_vec(), |s| vec![s.into()]);
            for kind in sensors {
                println!("{}", sim::bench::run(&scenario, kind, frames)?);
            }
        }
        Command::Bench { what: BenchCommand::Odometry { source, tuning, frames, runs } } => {
            let config = odometry_config(&tuning)?;
            let options = recording_options(source.topic.clone(), &config);
            let scans = Source::open(&source.input, Some(frames), &SimConfig::default(), &options)?
                .collect::<Result<Vec<_>, _>>()?;
            println!("{}", bench::odometry(&scans, &config, runs)?);
        }
        Command::Bench { what: BenchCommand::Gicp { data, runs } } => {
            println!("{}", cloud::registration::bench::gicp(&data, runs)?);
        }
        Command::Sim(args) => simulate(args)?,
        Command::Convert(args) => convert(args)?,
        Command::Odometry(args) => odometry(args)?,
        Command::Eval(args) => evaluate(&args)?,
        Command::Run(args) => run(args)?,
    }
    Ok(())
}

/// Builds a scenario and reports its size and build time (the BVH build dominates).
fn load_scenario(name: &str) -> Result<Scenario> {
    let start = std::time::Instant::now();
    let scenario = Scenario::by_name(name)?;
    let world = scenario.world();
    eprintln!(
        "{name}: {} objects, {} BVH nodes, built in {:.0} ms; {} robots, {} frames",
        world.objects().len(),
        world.bvh_nodes(),
        start.elapsed().as_secs_f64() * 1e3,
        scenario.robots().len(),
        scenario.frames()
    );
    Ok(scenario)
}

/// `emr-edge sim`: the SVG if asked, then the KITTI sequence if asked.
fn simulate(args: SimArgs) -> Result<()> {
    let scenario = load_scenario(&args.scenario)?;
    if let Some(path) = &args.svg {
        std::fs::write(path, sim::svg::render(&scenario))
            .with_context(|| format!("cannot write {}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    let Some(out) = &args.out else { return Ok(()) };
    let config = SimConfig {
        seed: args.seed,
        sensor: SensorKind::from(args.sensor).model(),
        range_noise: args.noise,
        dropout: args.dropout,
    };
    write_simulation(&Simulator::new(scenario, args.robot as usize - 1, config)?, args.frames, out)
}

/// Writes a simulated robot's sweeps in the KITTI layout, with a progress bar.
fn write_simulation(simulator: &Simulator, frames: Option<usize>, out: &std::path::Path) -> Result<()> {
    let frames = frames.unwrap_or(simulator.frames());
    let bar = progress_bar(Some(frames), "sweeps");
    let written = sim::write_kitti(simulator, out, frames, |done| bar.set_position(done as u64))?;
    bar.finish_and_clear();
    println!(
        "wrote {} sweeps ({:.0} points each on average) to {}",
        written.frames,
        written.points as f64 / written.frames.max(1) as f64,
        out.display()
    );
    Ok(())
}

/// `emr-edge convert`.
fn convert(args: ConvertArgs) -> Result<()> {
    match &args.source.input {
        SourceSpec::Sim { scenario, robot } => {
            let simulator = Simulator::new(load_scenario(scenario)?, *robot as usize - 1, SimConfig::default())?;
            write_simulation(&simulator, args.frames, &args.out)
        }
        SourceSpec::Recording(path) => {
            let options = RecordingOptions { topic: args.source.topic.clone(), ..RecordingOptions::default() };
            let rec = recording::open(path, &options)?;
            let bar = progress_bar(None, "scans");
            let scans = rec.take(args.frames.unwrap_or(usize::MAX));
            let summary = recording::convert(scans, &args.out, |_| bar.inc(1))?;
            bar.finish_and_clear();
            println!(
                "wrote {} scans ({} points, {} invalid points dropped) to {}",
                summary.scans,
                summary.points,
                summary.dropped,
                args.out.display()
            );
            Ok(())
        }
    }
}

/// The odometry configuration: preset, then the file's keys, then flags.
fn odometry_config(args: &TuningArgs) -> Result<OdometryConfig> {
    let mut config = match args.preset {
        Preset::Indoor => OdometryConfig::indoor(),
        Preset::Outdoor => OdometryConfig::outdoor(),
    };
    if let Some(path) = &args.config {
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
        // Overlay the file on the preset: serialise the preset, merge the file's tables into it.
        let mut base: toml::Table = toml::from_str(&toml::to_string(&config)?)?;
        let overlay: toml::Table =
            toml::from_str(&text).with_context(|| format!("{}: invalid TOML", path.display()))?;
        merge(&mut base, overlay);
        config = toml::Value::Table(base)
            .try_into()
            .with_context(|| format!("{}: invalid configuration", path.display()))?;
    }
    if args.no_deskew {
        config.deskew = false;
    }
    Ok(config)
}

/// How recordings are read for the odometry: rings and per-point times derived where missing.
fn recording_options(topic: Option<String>, config: &OdometryConfig) -> RecordingOptions {
    RecordingOptions {
        topic,
        rings: RingModel::Auto,
        times: TimeModel::Azimuth { period_s: config.scan_period, spin: Spin::Detect },
        ..RecordingOptions::default()
    }
}

/// Recursively overlays `overlay` onto `base`.
fn merge(base: &mut toml::Table, overlay: toml::Table) {
    for (key, value) in overlay {
        match (base.get_mut(&key), value) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o),
            (_, v) => {
                base.insert(key, v);
            }
        }
    }
}

/// `emr-edge odometry`.
fn odometry(args: OdometryArgs) -> Result<()> {
    let config = odometry_config(&args.tuning)?;
    if args.print_config {
        print!("{}", toml::to_string(&config)?);
        return Ok(());
    }
    let options = recording_options(args.source.topic.clone(), &config);
    let source = Source::open(&args.source.input, args.max_frames, &SimConfig::default(), &options)?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("cannot create {}", args.out.display()))?;
    let bar = progress_bar(source.len, "scans");
    let mut odometry = Odometry::new(config)?;
    let mut stats = RunStats::default();
    let (mut rss_first, mut rss_half) = (None, None);
    let (half, total, mut rss_last) = (source.len.map(|n| n / 2), source.len, None);
    let (mut est, mut gt) = (Trajectory { poses: vec![], stamps: Some(vec![]) }, Trajectory::default());
    for scan in source {
        let scan = match scan {
            Ok(s) => s,
            Err(e) if !e.is_fatal() => {
                tracing::warn!("skipped: {e}");
                continue;
            }
            Err(e) => {
                bar.finish_and_clear();
                tracing::error!("{e}; writing the {} scans before it", est.poses.len());
                break;
            }
        };
        let start = std::time::Instant::now();
        let frame = odometry.register(&scan.cloud).with_context(|| format!("scan {}", scan.index))?;
        stats.add(&frame, start.elapsed().as_secs_f64() * 1e3);
        est.poses.push(frame.pose);
        est.stamps.get_or_insert_default().push(scan.stamp);
        gt.poses.extend(scan.ground_truth);
        if est.poses.len() == 1 {
            rss_first = rss_mb();
        }
        if Some(est.poses.len()) == half {
            rss_half = rss_mb();
        }
        if Some(est.poses.len()) == total {
            rss_last = rss_mb();
        }
        // The resident size is read before the trim: between two trims it is at its highest.
        if est.poses.len() % RELEASE_EVERY == 0 {
            release_free_memory();
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let summary = stats.summary();
    let mut json = serde_json::to_value(&summary)?;
    json["peak_rss_mb"] = serde_json::json!(peak_rss_mb());
    // Memory must stay flat over long runs: resident memory after the first scan and at the end.
    let rss_end = rss_last.or_else(rss_mb);
    json["rss_mb"] = serde_json::json!({"after_first_scan": rss_first, "half_way": rss_half, "end": rss_end});
    if gt.poses.len() == est.poses.len() && !gt.poses.is_empty() {
        let first = gt.poses[0].inverse();
        gt.poses.iter_mut().for_each(|p| *p = first * *p);
        write(&args.out.join("poses_gt_kitti.txt"), &gt.to_kitti())?;
        let unaligned = cloud::trajectory::ate(&gt.poses, &est.poses, false)?;
        // A straight path leaves the rotation about it undetermined: no aligned figure then.
        let aligned = cloud::trajectory::ate(&gt.poses, &est.poses, true).ok().map(|a| a.rmse);
        json["ate_rmse_m"] = serde_json::json!({"unaligned": unaligned.rmse, "aligned": aligned});
        json["path_length_m"] = serde_json::json!(gt.length());
    }
    write(&args.out.join("poses_kitti.txt"), &est.to_kitti())?;
    write(&args.out.join("poses_tum.txt"), &est.to_tum())?;
    write(&args.out.join("stats.json"), &serde_json::to_string_pretty(&json)?)?;
    println!("{}", serde_json::to_string_pretty(&json)?);
    Ok(())
}

/// `emr-edge run`: the node on its own runtime until the source ends or a signal comes.
fn run(args: RunArgs) -> Result<()> {
    let robot = robot_id(args.robot, &args.source)?;
    let odometry = odometry_config(&args.tuning)?;
    let config = NodeConfig {
        max_frames: args.max_frames,
        rate: args.rate.into(),
        recording: recording_options(args.topic.clone(), &odometry),
        odometry,
        linger: !args.exit_when_done,
        on_source_end: args.summary.clone().map(|path| summary_writer(path, robot)),
        ..NodeConfig::new(args.fleet.clone(), robot, args.source.clone())
    };
    let network = args.network.joining(bus::DEFAULT_PORT);
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().context("cannot start tokio")?;
    let summary = runtime.block_on(async {
        // Listen for the signals before anything slow, so that an early Ctrl-C still stops cleanly.
        let shutdown = bus::shutdown_signal().context("cannot handle SIGINT/SIGTERM")?;
        let session = network.open().await.with_context(|| format!("cannot join {}", bus::describe(&network)))?;
        let summary = node::run(&session, config, shutdown).await;
        if let Err(e) = session.close().await {
            tracing::warn!("cannot close the zenoh session: {e}");
        }
        summary.with_context(|| format!("robot {robot} of fleet {}", args.fleet))
    })?;
    tracing::info!(
        "robot {robot}: {} scans, {} keyframes, {:.1} MB published",
        summary.frames,
        summary.keyframes,
        summary.published_bytes as f64 / 1e6
    );
    Ok(())
}

/// Writes the node's summary to `path` atomically (a reader never sees half a file).
fn summary_writer(path: PathBuf, robot: u32) -> SourceEnd {
    SourceEnd(Arc::new(move |s: &NodeSummary| {
        let json = serde_json::json!({
            "robot": robot, "frames": s.frames, "keyframes": s.keyframes, "published_bytes": s.published_bytes,
        });
        let partial = path.with_extension("partial");
        let written = std::fs::write(&partial, json.to_string()).and_then(|()| std::fs::rename(&partial, &path));
        if let Err(e) = written {
            tracing::error!("cannot write the summary {}: {e}", path.display());
        }
    }))
}

/// The robot id: as given, or the simulated robot's, which a given id must match.
fn robot_id(given: Option<u32>, source: &SourceSpec) -> Result<u32> {
    match (given, source) {
        (Some(id), SourceSpec::Sim { robot, .. }) if id != *robot => {
            bail!("--robot {id} does not match the simulated robot of --source (robot {robot})")
        }
        (Some(id), _) => Ok(id),
        (None, SourceSpec::Sim { robot, .. }) => Ok(*robot),
        (None, SourceSpec::Recording(path)) => bail!("--robot is required with a recording ({})", path.display()),
    }
}

/// `emr-edge eval`.
fn evaluate(args: &EvalArgs) -> Result<()> {
    let read = |p: &PathBuf| -> Result<Trajectory> {
        let text = std::fs::read_to_string(p).with_context(|| format!("cannot read {}", p.display()))?;
        Trajectory::parse(&text).with_context(|| format!("{}", p.display()))
    };
    let (gt, est) = (read(&args.gt)?, read(&args.est)?);
    let (g, e) = cloud::trajectory::pair(&gt, &est, args.max_dt)?;
    let unaligned = cloud::trajectory::ate(&g, &e, false)?;
    let aligned = cloud::trajectory::ate(&g, &e, true);
    let length = Trajectory { poses: g.clone(), stamps: None }.length();
    let rpe = cloud::trajectory::rpe(&g, &e, &cloud::trajectory::segment_lengths(length));
    println!("poses paired        {}", unaligned.pairs);
    println!("path length         {length:.3} m");
    println!("ATE RMSE unaligned  {:.4} m (mean {:.4}, max {:.4})", unaligned.rmse, unaligned.mean, unaligned.max);
    match aligned {
        Ok(a) => println!("ATE RMSE SE(3)      {:.4} m (mean {:.4}, max {:.4})", a.rmse, a.mean, a.max),
        // A straight path leaves the rotation about it undetermined.
        Err(e) => println!("ATE RMSE SE(3)      not computed: {e}"),
    }
    match rpe {
        Ok(r) => println!(
            "RPE                 {:.3} % translation, {:.3} deg/100 m over {} segments of {:?} m",
            r.translation_percent,
            r.rotation_deg_per_100m,
            r.segments,
            r.lengths.iter().map(|l| (l * 10.0).round() / 10.0).collect::<Vec<_>>()
        ),
        Err(e) => println!("RPE                 not computed: {e}"),
    }
    Ok(())
}

/// Writes a text file, naming it in the error.
fn write(path: &std::path::Path, text: &str) -> Result<()> {
    std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))
}

/// A progress bar on stderr; indicatif draws nothing when stderr is not a terminal.
fn progress_bar(len: Option<usize>, unit: &str) -> ProgressBar {
    let bar = len.map_or_else(ProgressBar::new_spinner, |n| ProgressBar::new(n as u64));
    let template = if len.is_some() {
        format!("{{bar:40}} {{pos}}/{{len}} {unit} [{{elapsed}} < {{eta}}, {{per_sec}}]")
    } else {
        format!("{{spinner}} {{pos}} {unit} [{{elapsed}}, {{per_sec}}]")
    };
    if let Ok(style) = ProgressStyle::with_template(&template) {
        bar.set_style(style);
    }
    bar
}
