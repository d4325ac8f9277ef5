//! `emr-edge convert`: any source to the KITTI layout.

use std::path::PathBuf;

use anyhow::{Result, bail};
use edge::recording::{self, ConvertSummary, RecordingError, Scan};
use edge::source::{Source, SourceSpec};

use super::{SourceArgs, progress_bar};

/// Arguments of `emr-edge convert`.
#[derive(clap::Args, Debug)]
pub struct ConvertArgs {
    #[command(flatten)]
    source: SourceArgs,
    /// Output directory (created if missing; must not hold scans already).
    #[arg(long)]
    out: PathBuf,
    /// Convert at most this many scans (required for a live udp: source).
    #[arg(long)]
    frames: Option<usize>,
    /// Skip the source's first N scans (counted before --frames).
    #[arg(long, value_name = "N", default_value_t = 0)]
    start_at: usize,
}

/// `emr-edge convert`.
pub fn convert(args: ConvertArgs) -> Result<()> {
    let reading = args.source.reading();
    let input = args.source.input();
    let summary = match &input {
        SourceSpec::Sim { scenario, robot } => {
            return super::sim::convert(scenario, *robot, args.start_at, args.frames, &args.out);
        }
        SourceSpec::Recording(path) => {
            let scans = recording::open(path, &reading)?.skip(args.start_at).take(args.frames.unwrap_or(usize::MAX));
            write(scans, &args)?
        }
        SourceSpec::Udp(_) | SourceSpec::Ros2 { .. } => {
            if args.frames.is_none() {
                bail!("{input} streams without end: say how many scans to convert with --frames N");
            }
            let source =
                Source::open(&input, args.frames, &args.source.sim.config(), &reading)?.starting_at(args.start_at);
            // A live sensor's undecodable packets are counted in its scans; a topic's undecodable
            // message is skipped with a warning.
            let scans = source.filter_map(|s| s.map_err(|e| tracing::warn!("skipped a scan: {e}")).ok()).map(|s| {
                Ok::<_, RecordingError>(Scan {
                    cloud: s.cloud,
                    stamp: s.stamp,
                    index: s.index,
                    dropped: 0,
                    gaps: s.gaps,
                    partial: s.partial,
                })
            });
            write(scans, &args)?
        }
    };
    println!(
        "wrote {} scans ({} points, {} invalid points dropped) to {}",
        summary.scans,
        summary.points,
        summary.dropped,
        args.out.display()
    );
    if summary.partial > 0 || summary.gaps > 0 {
        println!(
            "{} scans cover only part of a rotation; {} packets or columns were missing within scans",
            summary.partial, summary.gaps
        );
    }
    Ok(())
}

/// Writes the scans with a progress bar.
fn write(scans: impl Iterator<Item = Result<Scan, RecordingError>>, args: &ConvertArgs) -> Result<ConvertSummary> {
    let bar = progress_bar(args.frames, "scans");
    let summary = recording::convert(scans, &args.out, |_| bar.inc(1))?;
    bar.finish_and_clear();
    Ok(summary)
}
