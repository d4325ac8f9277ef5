//! `emr-station`: the central station of EMR-FLOAM. Thin: parses arguments, sets up logging and calls
//! the libraries.

use std::path::{Path, PathBuf};

use std::time::Duration;

use anyhow::{Context, Result, bail};
use bus::Network;
use cloud::Preset;
use clap::{Parser, Subcommand, ValueEnum};
use edge::node::Rate;
use nalgebra::Isometry3;
use proto::{Fleet, keyexpr};
use station::demo::{self, DemoConfig, DemoReport};
use station::fleet_load::{self, LoadConfig};
use station::merge::files::{self, AlignMethod, Alignment};
use station::merge::{MapStatus, MergeConfig, MergeReport};
use station::pairwise::bench::{bench_merge_files, read_transform};
use station::service::{self, StationConfig, client};

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
    /// Merge robot maps (.pcd, .ply, .bin) into one global map, without initial guesses.
    ///
    /// Writes DIR/global_map.ply (binary little endian, in the reference map's frame) and
    /// DIR/transforms.json: per input map its `transform` (4x4 row-major, maps THAT MAP's points
    /// into the global frame; identity when unmerged), `confidence` (the overlap-aware score of
    /// the weakest tree edge to the reference, 1 for the reference, 0 unmerged) and `status`
    /// ("merged" or "unmerged"); per accepted pair an edge {a, b, transform, confidence, inliers}
    /// whose transform maps map b's points into map a's frame (a, b: 0-based input positions);
    /// and `timing_ms` per stage.
    Merge {
        /// The maps, at least one.
        #[arg(required = true)]
        maps: Vec<PathBuf>,
        /// Output directory (created if missing).
        #[arg(long)]
        out: PathBuf,
        /// Parameter preset: indoor (0.1 m features) or outdoor (0.4 m).
        #[arg(long, default_value_t = Preset::Outdoor)]
        preset: Preset,
        /// 0-based position of the map whose frame is the global frame (default: the centre of the
        /// spanning tree).
        #[arg(long)]
        reference: Option<usize>,
    },
    /// Register SOURCE onto TARGET; prints the 4x4 transform mapping SOURCE points into the
    /// TARGET frame (4 lines, row-major) and a confidence line.
    Align {
        /// The cloud to move.
        source: PathBuf,
        /// The cloud to align to.
        target: PathBuf,
        /// Initial guess for vgicp/gicp: a text file with a 4x4 matrix (16 numbers, row-major) or
        /// a KITTI 3x4 line (12 numbers). Ignored by `global`.
        #[arg(long)]
        init: Option<PathBuf>,
        /// global: features + RANSAC + VGICP, no guess needed; vgicp, gicp: fine registration
        /// from --init (identity by default).
        #[arg(long, value_enum, default_value_t = CliMethod::Global)]
        method: CliMethod,
        /// Parameter preset: indoor or outdoor.
        #[arg(long, default_value_t = Preset::Outdoor)]
        preset: Preset,
        /// Write the transformed SOURCE cloud here (.ply binary, .pcd binary or .bin by extension).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// The whole system on this machine, no set-up: the simulated two-robot warehouse, both edges
    /// and the station as tasks of one process talking over Zenoh on loopback. Ends by writing
    /// OUT/global_map.ply, OUT/placements.json, per robot its trajectory (estimated and ground
    /// truth, TUM, in the global frame) and OUT/summary.json (confidences, ATE per robot, timings).
    Demo {
        /// Simulated scenario with two or more robots.
        #[arg(long, default_value = "warehouse-large")]
        scenario: String,
        /// Robots of the scenario to run (1-based), comma-separated.
        #[arg(long, value_delimiter = ',', default_value = "1,2")]
        robots: Vec<u32>,
        /// Scans per robot [default: the whole scenario].
        #[arg(long)]
        frames: Option<usize>,
        /// Play scans at sensor speed (10 Hz) instead of as fast as the odometry goes.
        #[arg(long)]
        realtime: bool,
        /// Output directory.
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
    },
    /// Run the station service: collect every robot of the fleet over Zenoh, merge their maps and
    /// publish the global map (also answered to queries) and the station status. State persists
    /// in DATA_DIR/station.redb; SIGINT or SIGTERM commits the last batch and exits 0.
    Run {
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
        #[arg(long, default_value_t = 2000)]
        debounce_ms: u64,
        /// Longest a change waits for its merge, milliseconds.
        #[arg(long, default_value_t = 10000)]
        max_delay_ms: u64,
        #[command(flatten)]
        network: bus::NetworkArgs,
    },
    /// Print one line per sample on KEYEXPR (e.g. 'emr/demo/**'): key, message type and a summary.
    /// Without network options, connects to tcp/127.0.0.1:7447.
    Watch {
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
    },
    /// Fetch the latest global map from the fleet's station and write its cloud (.ply, .pcd or
    /// .bin by extension). Without network options, connects to tcp/127.0.0.1:7447.
    Save {
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
    },
    /// Benchmarks.
    #[command(subcommand)]
    Bench(Bench),
}

#[derive(Subcommand, Debug)]
enum Bench {
    /// Time the pairwise global registration on SOURCE and TARGET (default: the KITTI 08 reverse
    /// revisit in ../shared/data/kitti08_revisit, 001500.bin onto 000720.bin, with its reference).
    Merge {
        /// Source cloud (moved onto the target).
        source: Option<PathBuf>,
        /// Target cloud.
        target: Option<PathBuf>,
        /// Reference transform (4x4 or KITTI 3x4 text) mapping source into target.
        #[arg(long)]
        reference: Option<PathBuf>,
        /// Runs to time.
        #[arg(long, default_value_t = 3)]
        runs: usize,
        /// Parameter preset: indoor or outdoor.
        #[arg(long, default_value_t = Preset::Outdoor)]
        preset: Preset,
    },
    /// A station under a simulated fleet: ROBOTS robots each publish a keyframe per scan at
    /// RATE_HZ (simulated scans at true poses, prepared before the clock starts) to an in-process
    /// station over loopback. Prints keyframes received per second, the largest backlog, merge
    /// times and how long the station takes to catch up, as JSON.
    Load {
        /// Robots publishing.
        #[arg(long, default_value_t = 8)]
        robots: usize,
        /// Keyframes per second per robot.
        #[arg(long, default_value_t = 10.0)]
        rate_hz: f64,
        /// Seconds of publishing.
        #[arg(long, default_value_t = 20.0)]
        seconds: f64,
        /// Scenario the robots come from.
        #[arg(long, default_value = "campus")]
        scenario: String,
    },
}

/// The merge configuration of a preset.
fn preset_config(preset: Preset) -> MergeConfig {
    match preset {
        Preset::Indoor => MergeConfig::indoor(),
        Preset::Outdoor => MergeConfig::outdoor(),
    }
}

/// Registration methods of `align`.
#[derive(Clone, Copy, Debug, ValueEnum)]
enum CliMethod {
    Global,
    Vgicp,
    Gicp,
}

/// The KITTI reverse-revisit pair, relative to the project root.
const KITTI_REVISIT: &str = "../shared/data/kitti08_revisit";

fn main() -> Result<()> {
    bus::init_logging();
    match Cli::parse().command {
        Command::Keys { fleet, robot } => print_keys(&Fleet::new(&fleet)?, robot),
        Command::Info { files } => {
            for f in &files {
                print_info(f)?;
            }
        }
        Command::Merge { maps, out, preset, reference } => {
            let config = MergeConfig { reference, ..preset_config(preset) };
            let report = files::merge_files(&maps, &out, &config)?;
            print_merge(&maps, &report, &out);
        }
        Command::Align { source, target, init, method, preset, out } => {
            align(&source, &target, init.as_deref(), method, &preset_config(preset), out.as_deref())?
        }
        Command::Bench(Bench::Load { robots, rate_hz, seconds, scenario }) => {
            let config = LoadConfig { robots, rate_hz, seconds, scenario, ..LoadConfig::new() };
            let report = runtime()?.block_on(fleet_load::run(config))?;
            println!("{}", serde_json::to_string_pretty(&report)?);
        }
        Command::Bench(Bench::Merge { source, target, reference, runs, preset }) => {
            bench_merge(source, target, reference, runs, preset)?
        }
        Command::Demo { scenario, robots, frames, realtime, out } => {
            let config = DemoConfig {
                scenario,
                robots,
                frames,
                rate: if realtime { Rate::Realtime } else { Rate::Max },
                out,
                ..DemoConfig::new()
            };
            let report =
                runtime()?.block_on(async { demo::run(config, signal()?).await.map_err(anyhow::Error::from) })?;
            print_demo(&report);
        }
        Command::Run { fleet, data_dir, preset, debounce_ms, max_delay_ms, network } => {
            let config = StationConfig {
                data_dir: Some(data_dir),
                merge: preset_config(preset),
                debounce: Duration::from_millis(debounce_ms),
                max_delay: Duration::from_millis(max_delay_ms),
                ..StationConfig::new(Fleet::new(&fleet)?)
            };
            let rt = runtime()?;
            rt.block_on(run_station(config, network.network(&[bus::DEFAULT_PORT])))?;
            // A merge still running on a blocking thread has nothing left to publish to.
            rt.shutdown_timeout(Duration::from_secs(1));
        }
        Command::Watch { keyexpr, count, json, network } => {
            runtime()?.block_on(watch(&keyexpr, count, json, network.joining(bus::DEFAULT_PORT)))?
        }
        Command::Save { fleet, out, transforms, timeout_s, network } => {
            let timeout = Duration::try_from_secs_f64(timeout_s).context("--timeout-s")?;
            let fleet = Fleet::new(&fleet)?;
            runtime()?.block_on(save(&fleet, &out, transforms.as_deref(), timeout, network.joining(bus::DEFAULT_PORT)))?
        }
    }
    Ok(())
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread().enable_all().build()?)
}

/// SIGINT or SIGTERM; call inside the runtime.
fn signal() -> Result<impl std::future::Future<Output = ()>> {
    bus::shutdown_signal().context("cannot handle SIGINT/SIGTERM")
}

async fn open(network: &Network) -> Result<zenoh::Session> {
    network.open().await.with_context(|| bus::describe(network))
}

async fn run_station(config: StationConfig, network: Network) -> Result<()> {
    let session = open(&network).await?;
    tracing::info!("station for fleet {} on {}", config.fleet, bus::describe(&network));
    let summary = service::run(session.clone(), config, signal()?).await?;
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

async fn watch(keyexpr: &str, count: Option<usize>, json: bool, network: Network) -> Result<()> {
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

async fn save(fleet: &Fleet, out: &Path, transforms: Option<&Path>, timeout: Duration, network: Network) -> Result<()> {
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

fn print_merge(inputs: &[PathBuf], report: &MergeReport, out: &Path) {
    for (m, path) in report.maps.iter().zip(inputs) {
        match &m.status {
            MapStatus::Merged { confidence, hops, .. } => {
                println!("{}: merged (confidence {confidence:.3}, {hops} hops)", path.display())
            }
            MapStatus::Unmerged(reason) => println!("{}: unmerged ({reason})", path.display()),
        }
    }
    for p in &report.pairs {
        match &p.verdict {
            station::merge::PairVerdict::Edge(e) => {
                println!("pair {}-{}: edge, confidence {:.3}, {} inliers", p.a, p.b, e.confidence.score, e.inliers)
            }
            station::merge::PairVerdict::Rejected { reason, .. } => {
                println!("pair {}-{}: rejected ({reason})", p.a, p.b)
            }
        }
    }
    println!(
        "{} of {} maps merged, {} points in {} ({:.0} ms)",
        report.merged(),
        report.maps.len(),
        report.global_map.len(),
        out.join("global_map.ply").display(),
        report.timing.total.as_secs_f64() * 1e3
    );
}

fn align(
    source: &Path,
    target: &Path,
    init: Option<&Path>,
    method: CliMethod,
    config: &MergeConfig,
    out: Option<&Path>,
) -> Result<()> {
    let init = init.map(read_transform).transpose()?.unwrap_or_else(Isometry3::identity);
    let method = match method {
        CliMethod::Global => AlignMethod::Global,
        CliMethod::Vgicp => AlignMethod::Vgicp,
        CliMethod::Gicp => AlignMethod::Gicp,
    };
    let maps = files::read_maps(&[source.to_owned(), target.to_owned()])?;
    let result = files::align_pair(&maps[0], &maps[1], &init, method, config)?;
    print_alignment(&result);
    if let Some(out) = out {
        files::write_by_extension(out, &maps[0].transformed(&result.transform.cast::<f32>()))?;
    }
    Ok(())
}

fn print_alignment(a: &Alignment) {
    for row in files::matrix_rows(&a.transform) {
        println!("{:.9} {:.9} {:.9} {:.9}", row[0], row[1], row[2], row[3]);
    }
    let score = a.score.map_or("-".to_owned(), |s| format!("{s:.4}"));
    let inliers = a.inliers.map_or("-".to_owned(), |n| n.to_string());
    println!("confidence {score} overlap {:.4} fitness {:.3} inliers {inliers}", a.overlap, a.fitness);
}

fn bench_merge(
    source: Option<PathBuf>,
    target: Option<PathBuf>,
    reference: Option<PathBuf>,
    runs: usize,
    preset: Preset,
) -> Result<()> {
    let (source, target, reference) = match (source, target) {
        (Some(s), Some(t)) => (s, t, reference),
        (None, None) => {
            let dir = Path::new(KITTI_REVISIT);
            if !dir.is_dir() {
                bail!("{} not found: run from the project root or give SOURCE and TARGET", dir.display());
            }
            let reference = reference.unwrap_or_else(|| dir.join("T_000720_001500.txt"));
            (dir.join("001500.bin"), dir.join("000720.bin"), Some(reference))
        }
        _ => bail!("give both SOURCE and TARGET, or neither for the KITTI revisit pair"),
    };
    let bench = bench_merge_files(&source, &target, reference.as_deref(), &preset_config(preset).pairwise, runs)
        .with_context(|| format!("benchmarking {} onto {}", source.display(), target.display()))?;
    print!("{bench}");
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

/// The demo's results as a table.
fn print_demo(report: &DemoReport) {
    let map = &report.global_map;
    println!(
        "global map revision {}: {} points, reference robot {}, {:.1} s wall, {} merges (last {:.0} ms)",
        map.revision,
        map.cloud.as_ref().map_or(0, |c| c.points),
        map.reference_robot,
        report.wall_s,
        report.merge_ms.len(),
        report.merge_ms.last().copied().unwrap_or(0.0)
    );
    println!(
        "robot  scans  keyframes  status    confidence  placement error   odometry ATE aligned/unaligned  global ATE"
    );
    for r in &report.robots {
        let placement = r.placement_error.map_or("-".into(), |(m, d)| format!("{:.1} cm {:.2} deg", m * 100.0, d));
        let global = r.global_ate.map_or("-".into(), |a| format!("{:.1} cm", a.rmse * 100.0));
        println!(
            "{:>5}  {:>5}  {:>9}  {:<8}  {:>10.3}  {:>15}   {:>13.1} / {:.1} cm        {global:>10}",
            r.robot,
            r.frames,
            r.keyframes,
            if r.merged { "merged" } else { "unmerged" },
            r.confidence,
            placement,
            r.odometry_ate.0.rmse * 100.0,
            r.odometry_ate.1.rmse * 100.0,
        );
    }
    for path in &report.written {
        println!("wrote {}", path.display());
    }
}
