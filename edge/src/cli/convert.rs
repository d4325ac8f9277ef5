//! `emr-edge convert`: any source to the KITTI layout.

use std::path::PathBuf;

use anyhow::Result;
use edge::recording::{self, RecordingOptions};
use edge::source::SourceSpec;

use super::{SourceArgs, progress_bar};

/// Arguments of `emr-edge convert`.
#[derive(clap::Args, Debug)]
pub struct ConvertArgs {
    #[command(flatten)]
    source: SourceArgs,
    /// Output directory (created if missing; must not hold scans already).
    #[arg(long)]
    out: PathBuf,
    /// Convert at most this many scans.
    #[arg(long)]
    frames: Option<usize>,
}

/// `emr-edge convert`.
pub fn convert(args: ConvertArgs) -> Result<()> {
    match &args.source.input {
        SourceSpec::Sim { scenario, robot } => super::sim::convert(scenario, *robot, args.frames, &args.out),
        SourceSpec::Recording(path) => {
            let options = RecordingOptions { topic: args.source.topic.clone(), ..RecordingOptions::default() };
            let rec = recording::open(path, &options)?;
            let bar = progress_bar(None, "scans");
            let scans = rec.take(args.frames.unwrap_or(usize::MAX));
            let summary = recording::convert(scans, &args.out, |_| bar.inc(1))?;
            bar.finish_and_clear();
            println!(
                "wrote {} scans ({} points, {} invalid points dropped) to {}",
                summary.scans,
                summary.points,
                summary.dropped,
                args.out.display()
            );
            Ok(())
        }
    }
}
