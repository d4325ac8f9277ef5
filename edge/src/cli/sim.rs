//! `emr-edge sim`, and the simulator as the other commands reach it (the only module of the
//! binary that names the simulator).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use cloud::stopwatch::Stopwatch;
use edge::args::{SensorArg, scenario_values};
use sim::{Scenario, SensorKind, SimConfig, Simulator};

use super::progress_bar;

/// Arguments of `emr-edge sim`.
#[derive(clap::Args, Debug)]
pub struct SimArgs {
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

/// Builds a scenario and reports its size and build time (the BVH build dominates).
fn load_scenario(name: &str) -> Result<Scenario> {
    let watch = Stopwatch::start();
    let scenario = Scenario::by_name(name)?;
    let world = scenario.world();
    eprintln!(
        "{name}: {} objects, {} BVH nodes, built in {:.0} ms; {} robots, {} frames",
        world.objects().len(),
        world.bvh_nodes(),
        watch.elapsed_ms(),
        scenario.robots().len(),
        scenario.frames()
    );
    Ok(scenario)
}

/// `emr-edge sim`: the SVG if asked, then the KITTI sequence if asked.
pub fn simulate(args: SimArgs) -> Result<()> {
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

/// `emr-edge convert` of a `sim:SCENARIO:ROBOT` source: the robot's sweeps with the default sensor.
pub fn convert(scenario: &str, robot: u32, frames: Option<usize>, out: &Path) -> Result<()> {
    let simulator = Simulator::new(load_scenario(scenario)?, robot as usize - 1, SimConfig::default())?;
    write_simulation(&simulator, frames, out)
}

/// Writes a simulated robot's sweeps in the KITTI layout, with a progress bar.
fn write_simulation(simulator: &Simulator, frames: Option<usize>, out: &Path) -> Result<()> {
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
