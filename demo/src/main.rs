//! `emr-demo`: the robots and the station of EMR-FLOAM in one process. Thin: parses arguments, sets
//! up logging and calls the library.

mod live_options;

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use demo::fleet_load::{self, LoadConfig};
use demo::report::{self, ReportConfig};
use demo::{DemoConfig, DemoReport};
use edge::node::Rate;
use station::joint::JointConfig;

/// The whole EMR-FLOAM system on this machine, no set-up.
///
/// With no command (or `run`): the simulated two-robot warehouse, both edges and the station as
/// tasks of one process talking over Zenoh on loopback. Ends by writing OUT/global_map.ply,
/// OUT/placements.json, per robot its trajectory (estimated and ground truth, TUM, in the global
/// frame), OUT/summary.json (confidences, ATE per robot, timings), OUT/top_down.png (the global
/// map from above with the trajectories) and OUT/error_over_distance.png.
#[derive(Parser, Debug)]
#[command(name = "emr-demo", version, about, long_about, args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the demo (what `emr-demo` with no command does).
    Run(RunArgs),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(Bench),
    /// The paper's four systems side by side: MR-ALOAM, MR-FLOAM (no loops), EMR-ALOAM, EMR-FLOAM
    /// (loops), each run through the demo on the simulated scenarios. Writes OUT/report.md (ATE per
    /// robot, ms per scan, map points and bytes, merge time, loops), OUT/report.json, and each
    /// run's demo results in OUT/SCENARIO/SYSTEM. Progress on stderr. (The issue asked for
    /// `emr-station report`; it lives here because only the demo links robot and station code.)
    Report(ReportArgs),
}

/// The report's flags.
#[derive(Args, Debug)]
struct ReportArgs {
    /// Output directory.
    #[arg(long, default_value = "out/report")]
    out: PathBuf,
    /// Scenario to run (repeatable) [default: warehouse-small, warehouse-large, campus, aisles].
    #[arg(long = "scenario")]
    scenarios: Vec<String>,
    /// Scans per robot [default: the whole scenario].
    #[arg(long)]
    frames: Option<usize>,
}

/// The demo's flags.
#[derive(Args, Debug)]
struct RunArgs {
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
    /// Seed of the simulated sensors' range noise and dropouts: one seed's figures are one
    /// sample of the noise, so judge a change over several.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output directory.
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    #[command(flatten)]
    live: live_options::LiveArgs,
}

#[derive(Subcommand, Debug)]
enum Bench {
    /// A station under a simulated fleet: ROBOTS robots each publish a keyframe per scan at
    /// RATE_HZ for SECONDS (simulated scans at true poses, prepared before the clock starts) to an
    /// in-process station over loopback; when they are done the station catches up.
    ///
    /// Prints keyframes sent and held, the station's intake per second and largest backlog, merges
    /// and their times (p50 / p95 / max), each keyframe's latency from its arrival at the station
    /// to the first published global map holding it (and how many no map held), the merge queue's
    /// depth, the catch-up time and the process's resident memory (before publishing, at the end,
    /// peak). Progress on stderr.
    Load {
        /// Robots publishing (at least 1).
        #[arg(long, default_value_t = 8)]
        robots: usize,
        /// Keyframes per second per robot (above 0).
        #[arg(long, default_value_t = 10.0)]
        rate_hz: f64,
        /// Seconds of publishing; each robot sends SECONDS × RATE_HZ keyframes (rounded, at least 1).
        #[arg(long, default_value_t = 20.0)]
        seconds: f64,
        /// Scenario the robots come from (robots beyond its own replay them from later in their runs).
        #[arg(long, default_value = "campus")]
        scenario: String,
        /// Print the figures as one JSON object on stdout's last line instead of text: robots, sent,
        /// received, mean_payload_bytes, received_per_s, max_backlog, queue_max, merges, merge_ms
        /// and latency_ms ({p50, p95, max}, nearest rank), unmapped, catch_up_s, merged_robots, all_merged_s,
        /// rss_mb ({start, end, peak}), and joint with --joint.
        #[arg(long)]
        json: bool,
        /// Then run the station's joint pose graph on the final map's robots and report its time,
        /// edges and keyframe RMSE against the truth, rigid and joint (JSON: joint {ms, edges_ms,
        /// consistency_ms, optimise_ms, robots, keyframes, registered, kept, joined, rigid_rmse_m,
        /// joint_rmse_m, edge_error_m, edge_error_deg}).
        #[arg(long)]
        joint: bool,
    },
}

fn main() -> Result<()> {
    bus::init_logging();
    // The station in this process frees large merge buffers all the time (see emr-station's main).
    cloud::memory::configure_allocator();
    let cli = Cli::parse();
    match cli.command {
        None => run_demo(cli.run)?,
        Some(Command::Run(args)) => run_demo(args)?,
        Some(Command::Report(args)) => run_report(args)?,
        Some(Command::Bench(Bench::Load { robots, rate_hz, seconds, scenario, json, joint })) => {
            let joint = joint.then(JointConfig::default);
            let config = LoadConfig { robots, rate_hz, seconds, scenario, joint, ..LoadConfig::new() };
            let report = runtime()?.block_on(fleet_load::run(config))?;
            if json {
                println!("{}", serde_json::to_string(&report)?);
            } else {
                println!("{report}");
            }
        }
    }
    Ok(())
}

fn run_demo(args: RunArgs) -> Result<()> {
    let RunArgs { scenario, robots, frames, realtime, seed, out, live } = args;
    let mut config = DemoConfig {
        scenario,
        robots,
        frames,
        rate: if realtime { Rate::Realtime } else { Rate::Max },
        seed,
        out,
        ..DemoConfig::new()
    };
    let report = runtime()?.block_on(async {
        let live = live.open(&config.out).await?;
        config.station.live = live.clone();
        let interrupt = bus::shutdown_signal().context("cannot handle SIGINT/SIGTERM")?;
        let report = demo::run(config, interrupt).await;
        if let Some(live) = live {
            live.finish().await?;
        }
        report.map_err(anyhow::Error::from)
    })?;
    print_demo(&report);
    Ok(())
}

fn run_report(args: ReportArgs) -> Result<()> {
    let mut config = ReportConfig { frames: args.frames, out: args.out, ..ReportConfig::default() };
    if !args.scenarios.is_empty() {
        config.scenarios = args.scenarios;
    }
    let started = std::time::Instant::now();
    let report = runtime()?.block_on(async {
        let interrupt = bus::shutdown_signal().context("cannot handle SIGINT/SIGTERM")?;
        report::run(&config, interrupt, |line| eprintln!("[{:>5.0} s] {line}", started.elapsed().as_secs_f64()))
            .await
            .map_err(anyhow::Error::from)
    })?;
    std::fs::create_dir_all(&config.out).with_context(|| format!("cannot create {}", config.out.display()))?;
    for (name, text) in [("report.md", report::markdown(&report)), ("report.json", report::json(&report))] {
        let path = config.out.join(name);
        std::fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread().enable_all().build()?)
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
        "robot  scans  keyframes  loops  status    confidence  placement error  rigid floor      odometry ATE aligned/unaligned  with loops  global ATE  joint ATE"
    );
    for r in &report.robots {
        let placement = r.placement_error.map_or("-".into(), |(m, d)| format!("{:.1} cm {:.2} deg", m * 100.0, d));
        let floor = r.placement_floor.map_or("-".into(), |(m, d)| format!("{:.1} cm {:.2} deg", m * 100.0, d));
        let global = r.global_ate.map_or("-".into(), |a| format!("{:.1} cm", a.rmse * 100.0));
        let joint = r.joint_ate.map_or("-".into(), |a| format!("{:.1} cm", a.rmse * 100.0));
        println!(
            "{:>5}  {:>5}  {:>9}  {:>5}  {:<8}  {:>10.3}  {:>15}  {floor:>15}   {:>13.1} / {:.1} cm   {:>4.1} / {:.1} cm  {global:>10}  {joint:>9}",
            r.robot,
            r.frames,
            r.keyframes,
            r.loops,
            if r.merged { "merged" } else { "unmerged" },
            r.confidence,
            placement,
            r.odometry_ate.0.rmse * 100.0,
            r.odometry_ate.1.rmse * 100.0,
            r.corrected_ate.0.rmse * 100.0,
            r.corrected_ate.1.rmse * 100.0,
        );
    }
    for path in &report.written {
        println!("wrote {}", path.display());
    }
}
