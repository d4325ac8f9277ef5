//! The commands of `emr-edge`, one module each, and the argument groups they share.

pub mod bench;
pub mod convert;
pub mod eval;
pub mod odometry;
pub mod posegraph;
pub mod run;
pub mod sim;

use std::path::PathBuf;

use cloud::Preset;
use edge::odometry::Method;
use edge::odometry::pipeline::Tuning;
use edge::source::SourceSpec;
use indicatif::{ProgressBar, ProgressStyle};

/// How the odometry is configured (shared by the commands that run it).
#[derive(clap::Args, Debug)]
pub struct TuningArgs {
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
    /// Odometry: floam (scan-to-map every sweep) or aloam (scan-to-scan every sweep, scan-to-map
    /// every `aloam.map_every` sweeps) [default: the configuration's, floam].
    #[arg(long)]
    method: Option<Method>,
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
    input: SourceSpec,
    /// Topic of sensor_msgs/PointCloud2 in a bag or MCAP file [default: the only one].
    #[arg(long)]
    topic: Option<String>,
    #[command(flatten)]
    sim: SimArgs,
}

/// The simulated sensors of `sim:` sources (shared by the commands that read them).
#[derive(clap::Args, Debug)]
pub struct SimArgs {
    /// Seed of a simulated sensor's range noise and dropouts (`sim:` sources). A simulated run's
    /// figures are one sample of the noise: compare changes over several seeds.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

impl SimArgs {
    /// The simulated sensor's settings: the default VLP-16 with this seed.
    fn config(&self) -> ::sim::SimConfig {
        ::sim::SimConfig { seed: self.seed, ..::sim::SimConfig::default() }
    }
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
