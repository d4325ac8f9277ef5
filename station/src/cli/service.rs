//! `run`, `watch`, `save` and `keys`: the networked station and the tools that look at it.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result};
use bus::Network;
use clap::Args;
use cloud::Preset;
use live::{Live, Sinks};
use proto::{Fleet, keyexpr};
use station::merge::MergeConfig;
use station::merge::files;
use station::service::{self, StationConfig, client};

// `emr-station keys`.
#[derive(Args, Debug)]
pub struct KeysArgs {
    /// Fleet name (ASCII letters, digits, '-' and '_').
    #[arg(long, default_value = "demo")]
    fleet: String,
    /// Robot id used in the per-robot keys.
    #[arg(long, default_value_t = 1)]
    robot: u32,
}

// `emr-station run`.
#[derive(Args, Debug)]
pub struct RunArgs {
    /// Fleet name.
    #[arg(long)]
    fleet: String,
    /// Where the database lives.
    #[arg(long, default_value = "station-data")]
    data_dir: PathBuf,
    /// Merge preset: outdoor (0.4 m features) or indoor (0.1 m). Outdoor is the default even for
    /// buildings: the robots' maps grow to whole floors, where 0.1 m features are slow (5 s per
    /// merge of two warehouse halls) and find too few matches on maps bent by odometry drift.
    #[arg(long, default_value_t = Preset::Outdoor)]
    preset: Preset,
    /// Quiet time after the last change before a merge starts, milliseconds.
    #[arg(long, default_value_t = 1000)]
    debounce_ms: u64,
    /// Longest a change waits for its merge, milliseconds: under a steady stream of keyframes the
    /// map is merged this often (a merge adds the newest points at the known placements and runs a
    /// bounded amount of registration, see the merge's `max_searches`).
    #[arg(long, default_value_t = 2000)]
    max_delay_ms: u64,
    /// Serve the live view over the Foxglove WebSocket protocol on this address (e.g.
    /// 127.0.0.1:8765; open it in Foxglove as ws://ADDR): the global map, the robots' frames,
    /// trajectories, keyframes, loops and statuses (topics in docs/watching.md).
    #[arg(long, value_name = "ADDR")]
    foxglove: Option<SocketAddr>,
    /// Record the same topics to this MCAP file.
    #[arg(long, value_name = "FILE.mcap")]
    record: Option<PathBuf>,
    #[command(flatten)]
    network: bus::NetworkArgs,
    /// ROS 2: the global map, each robot's path, /tf and the status as rmw_zenoh topics
    /// (`/emr/FLEET/map`, `/emr/FLEET/robotN/path`, `/tf`, `/emr/FLEET/status`; see the README).
    #[command(flatten)]
    ros2: bus::ros2::Ros2Args,
}

// `emr-station watch`.
#[derive(Args, Debug)]
pub struct WatchArgs {
    /// Key expression to subscribe to.
    keyexpr: String,
    /// Stop after this many samples.
    #[arg(long)]
    count: Option<usize>,
    /// One JSON object per line.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    network: bus::NetworkArgs,
}

// `emr-station save`.
#[derive(Args, Debug)]
pub struct SaveArgs {
    /// Fleet name.
    #[arg(long)]
    fleet: String,
    /// The cloud file to write.
    #[arg(long)]
    out: PathBuf,
    /// Also write the placements as JSON (per robot transform, confidence, status; tree edges).
    #[arg(long)]
    transforms: Option<PathBuf>,
    /// How long to wait for the station, seconds.
    #[arg(long, default_value_t = 10.0)]
    timeout_s: f64,
    #[command(flatten)]
    network: bus::NetworkArgs,
}

pub fn keys(args: KeysArgs) -> Result<()> {
    let fleet = Fleet::new(&args.fleet)?;
    let robot = args.robot;
    let rows = [
        (keyexpr::keyframe(&fleet, robot), "Keyframe", "edge"),
        (keyexpr::posegraph(&fleet, robot), "PoseGraphUpdate", "edge"),
        (keyexpr::keyframe_store(&fleet, robot), "queryable: KeyframeRequest -> Keyframe", "edge"),
        (keyexpr::alive(&fleet, robot), "liveliness token", "edge"),
        (keyexpr::global_map(&fleet), "GlobalMap (also a queryable)", "station"),
        (keyexpr::station_status(&fleet), "StationStatus", "station"),
        (keyexpr::all_robots(&fleet), "wildcard: every robot topic", "subscribers"),
    ];
    for (key, payload, from) in rows {
        println!("{key:<40} {payload:<42} {from}");
    }
    Ok(())
}

pub fn run(args: RunArgs) -> Result<()> {
    let RunArgs { fleet, data_dir, preset, debounce_ms, max_delay_ms, foxglove, record, network, ros2 } = args;
    let config = StationConfig {
        ros2_domain: ros2.publish_domain(),
        data_dir: Some(data_dir),
        merge: MergeConfig::preset(preset),
        debounce: Duration::from_millis(debounce_ms),
        max_delay: Duration::from_millis(max_delay_ms),
        ..StationConfig::new(Fleet::new(&fleet)?)
    };
    let rt = runtime()?;
    rt.block_on(async {
        let live = Live::open(&Sinks { foxglove, record }, "emr-station").await?;
        if let Some(addr) = live.as_ref().and_then(|l| l.address()) {
            println!("Foxglove: ws://{addr}");
        }
        let config = StationConfig { live: live.clone(), ..config };
        let ran = run_station(config, network.network(&[bus::DEFAULT_PORT])).await;
        if let Some(live) = live {
            live.finish().await?;
        }
        ran
    })?;
    // A merge still running on a blocking thread has nothing left to publish to.
    rt.shutdown_timeout(Duration::from_secs(1));
    Ok(())
}

pub fn watch(args: WatchArgs) -> Result<()> {
    let WatchArgs { keyexpr, count, json, network } = args;
    runtime()?.block_on(watch_samples(&keyexpr, count, json, network.joining(bus::DEFAULT_PORT)))
}

pub fn save(args: SaveArgs) -> Result<()> {
    let SaveArgs { fleet, out, transforms, timeout_s, network } = args;
    let timeout = Duration::try_from_secs_f64(timeout_s).context("--timeout-s")?;
    let fleet = Fleet::new(&fleet)?;
    runtime()?.block_on(save_map(&fleet, &out, transforms.as_deref(), timeout, network.joining(bus::DEFAULT_PORT)))
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread().enable_all().build()?)
}

async fn open(network: &Network) -> Result<zenoh::Session> {
    network.open().await.with_context(|| bus::describe(network))
}

async fn run_station(config: StationConfig, network: Network) -> Result<()> {
    let session = open(&network).await?;
    tracing::info!("station for fleet {} on {}", config.fleet, bus::describe(&network));
    // SIGINT or SIGTERM; set up inside the runtime.
    let interrupt = bus::shutdown_signal().context("cannot handle SIGINT/SIGTERM")?;
    let summary = service::run(session.clone(), config, interrupt).await?;
    tracing::info!(
        "stopped: {} keyframes from {} robots, {} merges, {} malformed payloads",
        summary.keyframes.values().sum::<usize>(),
        summary.keyframes.len(),
        summary.merges,
        summary.malformed
    );
    session.close().await.map_err(|e| anyhow::anyhow!("closing the zenoh session: {e}"))?;
    Ok(())
}

async fn watch_samples(keyexpr: &str, count: Option<usize>, json: bool, network: Network) -> Result<()> {
    let session = open(&network).await?;
    let subscriber =
        session.declare_subscriber(keyexpr).await.map_err(|e| anyhow::anyhow!("subscribing to {keyexpr}: {e}"))?;
    let mut seen = 0;
    while count.is_none_or(|n| seen < n) {
        let Ok(sample) = subscriber.recv_async().await else { break };
        let summary = client::summarize(sample.key_expr().as_str(), &sample.payload().to_bytes());
        if json {
            println!("{}", summary.to_json());
        } else {
            println!("{}", summary.to_line());
        }
        seen += 1;
    }
    Ok(())
}

async fn save_map(
    fleet: &Fleet,
    out: &Path,
    transforms: Option<&Path>,
    timeout: Duration,
    network: Network,
) -> Result<()> {
    let session = open(&network).await?;
    let (map, _) = client::fetch_global_map(&session, fleet, timeout).await?;
    let cloud = client::global_map_cloud(&map).context("decoding the global map's cloud")?;
    files::write_by_extension(out, &cloud)?;
    println!("global map revision {} of fleet {fleet}: {} points in {}", map.revision, cloud.len(), out.display());
    if let Some(path) = transforms {
        let text = serde_json::to_string_pretty(&client::placements_json(&map))?;
        std::fs::write(path, text + "\n").with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
