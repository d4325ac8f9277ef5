//! `emr-edge odometry`: the library's odometry pipeline with a progress bar.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Result;
use edge::live_view::EdgeView;
use edge::odometry::pipeline::{OdometryPipeline, Tuning};
use edge::source::SourceSpec;
use live::Live;

use super::{SourceArgs, TuningArgs, progress_bar};

/// Arguments of `emr-edge odometry`.
#[derive(clap::Args, Debug)]
pub struct OdometryArgs {
    #[command(flatten)]
    source: SourceArgs,
    /// Output directory (created if missing).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    tuning: TuningArgs,
    /// Stop after this many scans.
    #[arg(long)]
    max_frames: Option<usize>,
    /// Print the configuration that would be used (TOML) and exit.
    #[arg(long)]
    print_config: bool,
    /// Close loops (the default: EMR-FLOAM's EMR mode): Scan Context candidates, verified by
    /// registration and by consistency with the odometry and each other, in a keyframe pose graph.
    /// Also writes poses_odometry_kitti.txt (before the loops), graph.g2o and loops.json.
    #[arg(long, overrides_with = "no_loops")]
    loops: bool,
    /// Odometry only (the paper's MR mode): poses_kitti.txt is the odometry.
    #[arg(long, overrides_with = "loops")]
    no_loops: bool,
    /// Record the run to this MCAP file for Foxglove: per scan the sensor frame (/tf), per
    /// keyframe its cloud, the trajectory, the loops and a status (topics in docs/watching.md), stamped
    /// with the scans' times.
    #[arg(long, value_name = "FILE.mcap")]
    record: Option<PathBuf>,
    /// Robot id the recording's topics and frames are named after (/robotN/..., robotN).
    #[arg(long, default_value_t = 1, requires = "record")]
    robot: u32,
}

/// `emr-edge odometry`.
pub fn odometry(args: OdometryArgs) -> Result<()> {
    let config = Tuning::from(&args.tuning).load()?;
    if args.print_config {
        print!("{}", toml::to_string(&config)?);
        return Ok(());
    }
    let sim = args.source.sim.config();
    let input = args.source.input();
    let mut pipeline = OdometryPipeline::new(&input, args.source.reading(), args.max_frames, config, &sim, &args.out)?
        .with_loops(!args.no_loops);
    if matches!(input, SourceSpec::Udp(_) | SourceSpec::Ros2 { .. }) {
        // A live source has no end of its own: Ctrl-C ends it, and what was read is written.
        pipeline = pipeline.until(interrupt_on_signal()?);
    }
    let live = Arc::new(Live::new());
    if let Some(path) = &args.record {
        live.record_file(path)?;
    }
    let mut view = args.record.is_some().then(|| EdgeView::new(Arc::clone(&live), args.robot));
    let bar = progress_bar(pipeline.expected_scans(), "scans");
    let report = pipeline.run(|done| {
        bar.inc(1);
        if let Some(view) = &mut view {
            view.scan(done);
        }
    });
    bar.finish_and_clear();
    // Closed even after a failed run: the scans before the failure are worth looking at.
    live.close()?;
    println!("{}", report?.to_json()?);
    Ok(())
}

/// A flag set on SIGINT (Ctrl-C) or SIGTERM, by a thread of its own.
fn interrupt_on_signal() -> Result<Arc<AtomicBool>> {
    let flag = Arc::new(AtomicBool::new(false));
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let signal = runtime.block_on(async { bus::shutdown_signal() })?;
    let set = flag.clone();
    std::thread::Builder::new().name("signals".into()).spawn(move || {
        runtime.block_on(signal);
        tracing::info!("interrupted: ending the source, writing what was read");
        set.store(true, Ordering::Relaxed);
    })?;
    Ok(flag)
}
