//! The argument groups that the command lines running the odometry share (`emr-edge` and the
//! benchmarks of `emr-eval`): the source, the odometry's configuration, the simulated sensor.

use std::path::PathBuf;

use clap::ValueEnum;
use clap::builder::{PossibleValue, PossibleValuesParser};
use cloud::Preset;
use sim::SensorKind;

use crate::odometry::Method;
use crate::odometry::pipeline::Tuning;
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
    /// The source: a directory of scans, a .bag or .mcap file, or sim:SCENARIO:ROBOT.
    pub input: SourceSpec,
    /// Topic of sensor_msgs/PointCloud2 in a bag or MCAP file [default: the only one].
    #[arg(long)]
    pub topic: Option<String>,
    #[command(flatten)]
    pub sim: SimArgs,
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
}

impl From<SensorArg> for SensorKind {
    fn from(s: SensorArg) -> Self {
        match s {
            SensorArg::Vlp16 => SensorKind::Vlp16,
            SensorArg::Hdl64 => SensorKind::Hdl64,
            SensorArg::Os64 => SensorKind::Os64,
            SensorArg::Os128 => SensorKind::Os128,
        }
    }
}

/// The scenario names with their descriptions, so `--help` lists them.
pub fn scenario_values() -> PossibleValuesParser {
    PossibleValuesParser::new(sim::CATALOG.iter().map(|s| PossibleValue::new(s.name).help(s.description)))
}
