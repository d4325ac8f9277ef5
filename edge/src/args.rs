//! The argument groups that the command lines running the odometry share (`emr-edge` and the
//! benchmarks of `emr-eval`): the source, the odometry's configuration, the simulated sensor.

use std::path::PathBuf;

use clap::ValueEnum;
use clap::builder::{PossibleValue, PossibleValuesParser};
use cloud::Preset;
use sim::SensorKind;

use crate::odometry::Method;
use crate::odometry::pipeline::Tuning;
use crate::packets::ReturnChoice;
use crate::packets::velodyne::Model;
use crate::recording::{PacketOptions, RecordingOptions};
use crate::source::SourceSpec;

/// How the odometry is configured (shared by the commands that run it).
#[derive(clap::Args, Debug)]
pub struct TuningArgs {
    /// Odometry configuration (TOML; `emr-edge odometry --print-config` shows every key and its
    /// default). Keys left out keep the preset's values.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Preset the configuration starts from: indoor (warehouses, ranges under ~40 m) or outdoor.
    #[arg(long, default_value_t = Preset::Indoor)]
    pub preset: Preset,
    /// Turn motion compensation off: for recordings published already compensated (KITTI's).
    #[arg(long)]
    pub no_deskew: bool,
    /// Odometry: floam (scan-to-map every sweep) or aloam (scan-to-scan every sweep, scan-to-map
    /// every `aloam.map_every` sweeps) [default: the configuration's, floam].
    #[arg(long)]
    pub method: Option<Method>,
}

impl From<&TuningArgs> for Tuning {
    fn from(args: &TuningArgs) -> Self {
        Tuning { preset: args.preset, file: args.config.clone(), no_deskew: args.no_deskew, method: args.method }
    }
}

/// Where scans come from (shared by the commands that read a source).
#[derive(clap::Args, Debug)]
pub struct SourceArgs {
    /// The source: a directory of scans, a .bag, .mcap or .pcap/.pcapng file (pcap:FILE whatever
    /// its name), udp:ADDRESS:PORT for a live sensor, ros2:/TOPIC for a ROS 2 driver's
    /// PointCloud2 topic over rmw_zenoh, or sim:SCENARIO:ROBOT.
    input: SourceSpec,
    /// Topic of sensor_msgs/PointCloud2 in a bag or MCAP file [default: the only one].
    #[arg(long)]
    pub topic: Option<String>,
    #[command(flatten)]
    pub packets: PacketArgs,
    #[command(flatten)]
    pub sim: SimArgs,
    /// The ROS domain of a ros2: source.
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub ros2_domain: u32,
    /// How a ros2: source reaches its publisher [default: a peer connecting to tcp/127.0.0.1:7447].
    #[command(flatten)]
    pub network: bus::NetworkArgs,
}

impl SourceArgs {
    /// The source, a ros2: source on the network and domain given.
    pub fn input(&self) -> SourceSpec {
        self.input.clone().on_network(self.network.joining(bus::DEFAULT_PORT), self.ros2_domain)
    }

    /// How to read a recording or packets, as the user said.
    pub fn reading(&self) -> RecordingOptions {
        RecordingOptions { topic: self.topic.clone(), packets: self.packets.options(), ..RecordingOptions::default() }
    }
}

/// How LiDAR packets decode (pcap: and udp: sources).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct PacketArgs {
    /// Ouster sensor metadata (JSON, as the sensor or ouster-sdk writes it) [default: the
    /// capture's name with .json; without one, packets are read as a Velodyne's].
    #[arg(long, value_name = "JSON")]
    pub metadata: Option<PathBuf>,
    /// Velodyne calibration in velodyne_pointcloud's YAML format; an HDL-64E needs its own
    /// [default: the capture's name with .yaml, else the model's published table].
    #[arg(long, value_name = "YAML")]
    pub calibration: Option<PathBuf>,
    /// Velodyne model [default: from the packets' factory bytes]; an HDL-64E must be named, its
    /// packets do not say whether it is an S2 or an S3.
    #[arg(long, value_enum)]
    pub model: Option<Model>,
    /// Which return of a dual-return sensor to keep: first (the strongest, or an Ouster's first),
    /// second, or both.
    #[arg(long, value_enum, default_value_t = ReturnChoice::First)]
    pub returns: ReturnChoice,
    /// The sensor's data port in a capture that holds two [default: the port of the first
    /// rotation decoded]; a live source gets only the packets sent to its own port.
    #[arg(long)]
    pub port: Option<u16>,
}

impl PacketArgs {
    /// The decoder's settings.
    pub fn options(&self) -> PacketOptions {
        PacketOptions {
            metadata: self.metadata.clone(),
            calibration: self.calibration.clone(),
            model: self.model,
            returns: self.returns,
            port: self.port,
        }
    }
}

/// The simulated sensors of `sim:` sources (shared by the commands that read them).
#[derive(clap::Args, Debug)]
pub struct SimArgs {
    /// Seed of a simulated sensor's range noise and dropouts (`sim:` sources). A simulated run's
    /// figures are one sample of the noise: compare changes over several seeds.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

impl SimArgs {
    /// The simulated sensor's settings: the default VLP-16 with this seed.
    pub fn config(&self) -> sim::SimConfig {
        sim::SimConfig { seed: self.seed, ..sim::SimConfig::default() }
    }
}

/// The LiDAR models on the command line.
#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum SensorArg {
    /// Velodyne VLP-16: 16 beams, -15..+15 deg, 1800 columns, 100 m.
    Vlp16,
    /// HDL-64E-like: 64 beams, -24.9..+2 deg, 2083 columns, 120 m.
    Hdl64,
    /// Ouster-like: 64 beams, -45..+45 deg, 1024 columns, 0.3-100 m.
    Os64,
    /// Ouster-like: 128 beams, -45..+45 deg, 1024 columns, 0.3-100 m.
    Os128,
    /// Livox Avia-like solid state: a 70 x 77 deg view ahead drawn as a rosette, no rings,
    /// 4,800 points per 0.1 s sweep, 1-100 m.
    Avia,
}

impl From<SensorArg> for SensorKind {
    fn from(s: SensorArg) -> Self {
        match s {
            SensorArg::Vlp16 => SensorKind::Vlp16,
            SensorArg::Hdl64 => SensorKind::Hdl64,
            SensorArg::Os64 => SensorKind::Os64,
            SensorArg::Os128 => SensorKind::Os128,
            SensorArg::Avia => SensorKind::Avia,
        }
    }
}

/// The scenario names with their descriptions, so `--help` lists them.
pub fn scenario_values() -> PossibleValuesParser {
    PossibleValuesParser::new(sim::CATALOG.iter().map(|s| PossibleValue::new(s.name).help(s.description)))
}
