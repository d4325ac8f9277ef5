//! `emr-edge run`: the robot's network service.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use bus::NetworkArgs;
use clap::ValueEnum;
use cloud::trajectory::Trajectory;
use edge::args::PacketArgs;
use edge::node::state_dir::StateDir;
use edge::node::{self, NodeConfig, NodeSummary, Rate, SourceEnd};
use edge::odometry::pipeline::{Tuning, recording_options};
use edge::recording::RecordingOptions;
use edge::source::SourceSpec;
use proto::Fleet;

use super::TuningArgs;

/// Arguments of `emr-edge run`.
#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// Fleet name: ASCII letters, digits, '-' and '_'.
    #[arg(long, value_parser = |s: &str| Fleet::new(s))]
    fleet: Fleet,
    /// Robot id within the fleet [default: ROBOT of a sim:SCENARIO:ROBOT source, which it must match].
    #[arg(long)]
    robot: Option<u32>,
    /// The source: a directory of scans, a .bag, .mcap or .pcap/.pcapng file (pcap:FILE whatever
    /// its name), udp:ADDRESS:PORT for a live sensor, ros2:/TOPIC for a ROS 2 driver's PointCloud2
    /// topic over rmw_zenoh (read on the robot's zenoh session: the driver's router or peer must
    /// be reachable through --connect, --listen or --zenoh), or sim:SCENARIO:ROBOT.
    #[arg(long, value_name = "INPUT")]
    source: SourceSpec,
    /// Topic of sensor_msgs/PointCloud2 in a bag or MCAP file [default: the only one].
    #[arg(long)]
    topic: Option<String>,
    #[command(flatten)]
    packets: PacketArgs,
    /// Pace: realtime plays scans at their stamps, max as fast as the odometry goes.
    #[arg(long, value_enum, default_value_t = RateArg::Realtime)]
    rate: RateArg,
    /// Skip the source's first N scans (a restart reproduced from a recording or the simulator:
    /// the robot starts there, in a new odometry frame).
    #[arg(long, value_name = "N", default_value_t = 0)]
    start_at: usize,
    /// Stop reading after this many scans (counted from --start-at).
    #[arg(long)]
    max_frames: Option<usize>,
    #[command(flatten)]
    tuning: TuningArgs,
    /// Odometry only (the paper's MR mode): no loop closure, no pose-graph updates. By default the
    /// robot closes its own loops and publishes the optimised keyframe poses on
    /// emr/FLEET/robot/ID/posegraph after each optimisation.
    #[arg(long)]
    no_loops: bool,
    /// Keep every keyframe on disk here too (the systemd unit's StateDirectory), so that after a
    /// crash or a reboot the station can still backfill what it missed; a damaged directory is set
    /// aside with a warning. Each start is a new session, numbered above those kept here.
    #[arg(long, value_name = "DIR")]
    state: Option<PathBuf>,
    /// Exit when the source ends instead of answering backfill requests until a signal.
    #[arg(long)]
    exit_when_done: bool,
    /// When the source ends, write {"robot", "session", "frames", "keyframes", "published_bytes",
    /// "loops", "posegraph_revision", "source_losses"} here (JSON):
    /// how scripts and the system tests learn that a robot is done while it keeps serving.
    #[arg(long, value_name = "FILE")]
    summary: Option<PathBuf>,
    /// When the source ends, write each registered scan's pose here, one KITTI line per scan
    /// (sensor at the sweep end, in this session's odometry frame, with the robot's own loop
    /// corrections applied): the trajectory `emr-edge eval --est` compares with a reference.
    #[arg(long, value_name = "FILE")]
    poses: Option<PathBuf>,
    #[command(flatten)]
    network: NetworkArgs,
    /// ROS 2: the odometry (`/emr/FLEET/robotN/odometry`) and keyframe clouds
    /// (`/emr/FLEET/robotN/keyframe`) as rmw_zenoh topics.
    #[command(flatten)]
    ros2: bus::ros2::Ros2Args,
}

/// Paces of `emr-edge run`.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum RateArg {
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

/// `emr-edge run`: the node on its own runtime until the source ends or a signal comes.
pub fn run(args: RunArgs) -> Result<()> {
    let robot = robot_id(args.robot, &args.source)?;
    let network = args.network.joining(bus::DEFAULT_PORT);
    // A ros2: source is read on the robot's own session; only its domain is set here.
    let source = args.source.clone().on_network(network.clone(), args.ros2.ros2_domain);
    let odometry = Tuning::from(&args.tuning).load()?;
    let state = args.state.as_deref().and_then(|dir| StateDir::open(dir, robot));
    let session = node::new_session(state.as_ref().and_then(StateDir::newest_session));
    if let (Some(dir), Some(state)) = (&args.state, &state) {
        tracing::info!(
            "robot {robot}: session {session}; {} keyframes of earlier sessions in {}",
            state.keyframes(),
            dir.display()
        );
    }
    let config = NodeConfig {
        session,
        state: state.map(|s| Arc::new(std::sync::Mutex::new(s))),
        start_at: args.start_at,
        max_frames: args.max_frames,
        rate: args.rate.into(),
        recording: recording_options(
            RecordingOptions { topic: args.topic.clone(), packets: args.packets.options(), ..Default::default() },
            &odometry,
        ),
        odometry,
        loops: !args.no_loops,
        linger: !args.exit_when_done,
        on_source_end: source_end(args.summary.clone(), args.poses.clone(), robot, session),
        ros2_domain: args.ros2.publish_domain(),
        ..NodeConfig::new(args.fleet.clone(), robot, source)
    };
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().context("cannot start tokio")?;
    let summary = runtime.block_on(async {
        // Listen for the signals before anything slow, so that an early Ctrl-C still stops cleanly.
        let shutdown = bus::shutdown_signal().context("cannot handle SIGINT/SIGTERM")?;
        let mut shutdown = std::pin::pin!(shutdown);
        // The router may not be up yet: keep trying (a signal still stops the robot meanwhile).
        let joined = tokio::select! {
            joined = network.open_patiently() => joined,
            () = &mut shutdown => return Ok(None),
        };
        let session = joined.with_context(|| format!("cannot join {}", bus::describe(&network)))?;
        let summary = node::run(&session, config, shutdown).await;
        if let Err(e) = session.close().await {
            tracing::warn!("cannot close the zenoh session: {e}");
        }
        summary.map(Some).with_context(|| format!("robot {robot} of fleet {}", args.fleet))
    })?;
    let Some(summary) = summary else {
        tracing::info!("robot {robot}: stopped before it could join the fleet");
        return Ok(());
    };
    tracing::info!(
        "robot {robot}: {} scans, {} keyframes, {:.1} MB published",
        summary.frames,
        summary.keyframes,
        summary.published_bytes as f64 / 1e6
    );
    Ok(())
}

/// Writes the node's summary and its trajectory where asked, when the source ends.
fn source_end(summary: Option<PathBuf>, poses: Option<PathBuf>, robot: u32, session: u64) -> Option<SourceEnd> {
    if summary.is_none() && poses.is_none() {
        return None;
    }
    Some(SourceEnd(Arc::new(move |s: &NodeSummary| {
        // The trajectory first: a script that waits for the summary then finds both.
        if let Some(path) = &poses {
            let trajectory = Trajectory { poses: s.corrected_poses(), stamps: Some(s.stamps.clone()) };
            write_atomically(path, "trajectory", &trajectory.to_kitti());
        }
        if let Some(path) = &summary {
            let json = serde_json::json!({
                "robot": robot, "session": session, "frames": s.frames, "keyframes": s.keyframes, "published_bytes": s.published_bytes,
                "loops": s.loops, "posegraph_revision": s.posegraph_revision, "source_losses": s.source_losses,
            });
            write_atomically(path, "summary", &json.to_string());
        }
    })))
}

/// Writes `text` to `path` atomically (a reader never sees half a file).
fn write_atomically(path: &Path, what: &str, text: &str) {
    let partial = path.with_extension("partial");
    let written = std::fs::write(&partial, text).and_then(|()| std::fs::rename(&partial, path));
    if let Err(e) = written {
        tracing::error!("cannot write the {what} {}: {e}", path.display());
    }
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
        (None, SourceSpec::Udp(address)) => bail!("--robot is required with a live sensor (udp:{address})"),
        (None, spec @ SourceSpec::Ros2 { .. }) => bail!("--robot is required with a ROS 2 topic ({spec})"),
    }
}
