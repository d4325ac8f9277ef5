//! `emr-edge sim`, and the simulator as the other commands reach it (the only module of the
//! binary that names the simulator).
//!
//! Besides the KITTI layout, the sweeps can go out as the sensor's own UDP packets (VLP-16, or an
//! Ouster in the LEGACY profile): into a pcap capture (`--pcap`, with the Ouster metadata JSON
//! beside it) or sent to a loopback address (`--send`), paced as the sensor sends them.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use cloud::stopwatch::Stopwatch;
use edge::args::{SensorArg, scenario_values};
use sim::packets::pcap::{CaptureWriter, Network};
use sim::packets::udp::{Pace, UdpSender};
use sim::packets::{Encoder, PacketFormat, SensorClock};
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
    #[arg(long, required_unless_present_any = ["svg", "pcap", "send"])]
    out: Option<PathBuf>,
    /// Write the sweeps as the sensor's UDP packets into this pcap capture (vlp16, os64, os128);
    /// an Ouster's metadata goes beside it, the capture's name with `.json`.
    #[arg(long, value_name = "FILE")]
    pcap: Option<PathBuf>,
    /// Send the sweeps as the sensor's UDP packets to this address, which must be a loopback one
    /// (127.0.0.1:2368 for a VLP-16's usual port, 127.0.0.1:7502 for an Ouster's).
    #[arg(long, value_name = "ADDR:PORT")]
    send: Option<SocketAddr>,
    /// How fast --send sends: realtime (at the sensor's pace) or max (as fast as possible; a
    /// receiver may drop packets).
    #[arg(long, value_enum, default_value_t = RateArg::Realtime, requires = "send")]
    rate: RateArg,
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

/// How fast `--send` sends.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum RateArg {
    /// At the sensor's pace: each packet when the sensor would send it.
    Realtime,
    /// As fast as the socket takes them.
    Max,
}

impl From<RateArg> for Pace {
    fn from(rate: RateArg) -> Self {
        match rate {
            RateArg::Realtime => Pace::Realtime,
            RateArg::Max => Pace::Max,
        }
    }
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

/// `emr-edge sim`: the SVG if asked, then the KITTI sequence if asked, then the packets if asked.
pub fn simulate(args: SimArgs) -> Result<()> {
    // Settings are checked before the scenario is built, which takes a while.
    let packets = packet_output(&args)?;
    let scenario = load_scenario(&args.scenario)?;
    if let Some(path) = &args.svg {
        std::fs::write(path, sim::svg::render(&scenario))
            .with_context(|| format!("cannot write {}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    let config = SimConfig {
        seed: args.seed,
        sensor: SensorKind::from(args.sensor).model(),
        range_noise: args.noise,
        dropout: args.dropout,
    };
    let simulator = Simulator::new(scenario, args.robot as usize - 1, config)?;
    if let Some(out) = &args.out {
        write_simulation(&simulator, 0, args.frames, out)?;
    }
    match packets {
        Some(output) => output.run(&simulator, args.frames),
        None => Ok(()),
    }
}

/// Where the packets of `--pcap` and `--send` go, checked up front; `None` when neither is asked.
fn packet_output(args: &SimArgs) -> Result<Option<PacketOutput>> {
    if args.pcap.is_none() && args.send.is_none() {
        return Ok(None);
    }
    let kind = SensorKind::from(args.sensor);
    let Some(format) = PacketFormat::of(kind) else {
        bail!("--pcap and --send need a sensor that sends packets: vlp16, os64 or os128, not {kind}");
    };
    if let Some(target) = args.send
        && !target.ip().is_loopback()
    {
        bail!("--send {target}: only a loopback address (127.0.0.1, ::1) may receive simulated packets");
    }
    if let Some(pcap) = &args.pcap
        && (pcap.with_extension("json") == *pcap || pcap.with_extension("yaml") == *pcap)
    {
        bail!(
            "--pcap {}: the sensor's description goes beside the capture as .json or .yaml; name it .pcap",
            pcap.display()
        );
    }
    let encoder = Encoder::new(format, &kind.model(), SensorClock::default())?;
    Ok(Some(PacketOutput { encoder, pcap: args.pcap.clone(), send: args.send.map(|a| (a, args.rate.into())) }))
}

/// The packet outputs of one run.
struct PacketOutput {
    encoder: Encoder,
    pcap: Option<PathBuf>,
    send: Option<(SocketAddr, Pace)>,
}

impl PacketOutput {
    /// Simulates each sweep once and writes or sends its packets, in order.
    fn run(self, simulator: &Simulator, frames: Option<usize>) -> Result<()> {
        let frames = frames.unwrap_or(simulator.frames());
        let mut capture = match &self.pcap {
            Some(path) => Some(self.start_capture(path)?),
            None => None,
        };
        let mut sender = self.send.map(|(target, pace)| UdpSender::new(target, pace)).transpose()?;
        let bar = progress_bar(Some(frames), "sweeps");
        for frame in 0..frames {
            let packets = self.encoder.encode(&simulator.range_image(frame))?;
            if let Some(capture) = &mut capture {
                capture.write_all(&packets)?;
            }
            if let Some(sender) = &mut sender {
                sender.send_all(&packets)?;
            }
            bar.set_position(frame as u64 + 1);
        }
        bar.finish_and_clear();
        let count = frames * self.encoder.packets_per_sweep();
        let format = self.encoder.format().name();
        if let (Some(capture), Some(path)) = (capture, &self.pcap) {
            capture.finish()?;
            println!("wrote {frames} sweeps as {count} {format} packets to {}", path.display());
        }
        if let Some(sender) = sender {
            println!("sent {frames} sweeps as {} {format} packets to {}", sender.sent(), sender.target());
        }
        Ok(())
    }

    /// Creates the capture, and writes the sensor's description beside it: an Ouster's metadata
    /// (found there by the capture reader), a VLP-16's calibration (to pass as --calibration).
    fn start_capture(&self, path: &Path) -> Result<CaptureWriter<std::io::BufWriter<std::fs::File>>> {
        if let Some(json) = self.encoder.metadata_json() {
            let beside = path.with_extension("json");
            std::fs::write(&beside, json).with_context(|| format!("cannot write {}", beside.display()))?;
            eprintln!("wrote the sensor metadata to {}", beside.display());
        }
        if let Some(yaml) = self.encoder.calibration_yaml() {
            let beside = path.with_extension("yaml");
            std::fs::write(&beside, yaml).with_context(|| format!("cannot write {}", beside.display()))?;
            eprintln!(
                "wrote the simulated VLP-16's calibration to {0}: decode with --calibration {0} for the simulated \
                 points (without it, decoders add a real VLP-16's per-laser vertical offsets of up to 11 mm)",
                beside.display()
            );
        }
        Ok(CaptureWriter::create(path, Network::default())?)
    }
}

/// `emr-edge convert` of a `sim:SCENARIO:ROBOT` source: the robot's sweeps with the default sensor,
/// from sweep `start_at` on.
pub fn convert(scenario: &str, robot: u32, start_at: usize, frames: Option<usize>, out: &Path) -> Result<()> {
    let simulator = Simulator::new(load_scenario(scenario)?, robot as usize - 1, SimConfig::default())?;
    let left = simulator.frames().saturating_sub(start_at);
    if left == 0 {
        bail!("--start-at {start_at}: sim:{scenario}:{robot} has only {} sweeps", simulator.frames());
    }
    write_simulation(&simulator, start_at, Some(frames.map_or(left, |f| f.min(left))), out)
}

/// Writes a simulated robot's sweeps in the KITTI layout, with a progress bar.
fn write_simulation(simulator: &Simulator, start: usize, frames: Option<usize>, out: &Path) -> Result<()> {
    let frames = frames.unwrap_or(simulator.frames());
    let bar = progress_bar(Some(frames), "sweeps");
    let written = sim::write_kitti_from(simulator, out, start, frames, |done| bar.set_position(done as u64))?;
    bar.finish_and_clear();
    println!(
        "wrote {} sweeps ({:.0} points each on average) to {}",
        written.frames,
        written.points as f64 / written.frames.max(1) as f64,
        out.display()
    );
    Ok(())
}
