//! `emr-demo`: the robots and the station of EMR-FLOAM in one process. Thin: parses arguments, sets
//! up logging and calls the library.

mod live_options;

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use demo::{DemoConfig, DemoReport};
use edge::node::Rate;

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
    /// Stop ROBOT's edge after SCAN scans and start a new session of it 50 scans later, in an
    /// odometry frame of its own (a robot that reboots mid-mission): the station places both
    /// sessions, and summary.json gives each one's placement error.
    #[arg(long, value_name = "ROBOT@SCAN")]
    restart: Option<demo::Restart>,
    /// Output directory.
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    #[command(flatten)]
    live: live_options::LiveArgs,
}

fn main() -> Result<()> {
    bus::init_logging();
    // The station in this process frees large merge buffers all the time (see emr-station's main).
    cloud::memory::configure_allocator();
    let cli = Cli::parse();
    match cli.command {
        None => run_demo(cli.run)?,
        Some(Command::Run(args)) => run_demo(args)?,
    }
    Ok(())
}

fn run_demo(args: RunArgs) -> Result<()> {
    let RunArgs { scenario, robots, frames, realtime, seed, restart, out, live } = args;
    let mut config = DemoConfig {
        scenario,
        robots,
        frames,
        rate: if realtime { Rate::Realtime } else { Rate::Max },
        seed,
        restart,
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
    for r in report.robots.iter().filter(|r| r.sessions.len() > 1) {
        for s in &r.sessions {
            let placement = s.placement_error.map_or("-".into(), |(m, d)| format!("{:.1} cm {:.2} deg", m * 100.0, d));
            let floor = s.placement_floor.map_or("-".into(), |(m, d)| format!("{:.1} cm {:.2} deg", m * 100.0, d));
            println!(
                "robot {} session {}: {} scans, {} keyframes ({} in the map), {}, placement error {placement} (rigid floor {floor})",
                r.robot,
                s.session,
                s.frames,
                s.keyframes,
                s.in_map,
                if s.merged { "merged" } else { "unmerged" }
            );
        }
    }
    for path in &report.written {
        println!("wrote {}", path.display());
    }
}
