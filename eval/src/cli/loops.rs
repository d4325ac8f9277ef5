//! `emr-eval loops`: the paper's comparison, MR (odometry only) against EMR (odometry with loop
//! closure), on the simulated robots whose paths revisit places and on the aisles' trap.

use std::fmt::Write as _;
use std::path::PathBuf;

use anyhow::{Context, Result};
use cloud::Preset;
use cloud::stopwatch::Stopwatch;
use edge::loops::track::LoopTrack;
use edge::odometry::pipeline::{self, AteRmse};
use edge::odometry::{Odometry, OdometryConfig};
use edge::source::SourceSpec;

use edge::args::SimArgs;

/// Arguments of `emr-eval loops`.
#[derive(clap::Args, Debug)]
pub struct LoopsArgs {
    /// Sources to run (repeatable) [default: warehouse-small and warehouse-large robots 1-2,
    /// campus robots 1-3, aisles robots 1-2]. Campus sources use the outdoor preset, others indoor.
    #[arg(long = "source")]
    sources: Vec<SourceSpec>,
    /// Stop each source after this many scans.
    #[arg(long)]
    max_frames: Option<usize>,
    /// Configuration keys (TOML, as `emr-edge odometry --config`) laid over each source's preset,
    /// e.g. `[loops.consistency]` to try other bounds.
    #[arg(long)]
    config: Option<PathBuf>,
    #[command(flatten)]
    sim: SimArgs,
}

/// The default cases: every scenario robot, those that revisit places and those that do not (the
/// aisles' rows all look alike: a loop found there must still be right).
const CASES: [&str; 9] = [
    "sim:warehouse-small:1",
    "sim:warehouse-small:2",
    "sim:warehouse-large:1",
    "sim:warehouse-large:2",
    "sim:campus:1",
    "sim:campus:2",
    "sim:campus:3",
    "sim:aisles:1",
    "sim:aisles:2",
];

/// `emr-eval loops`: per source, one pass of the odometry with the loop closure beside it on a
/// one-thread pool; MR is the odometry's trajectory, EMR the optimised one.
pub fn loops(args: LoopsArgs) -> Result<()> {
    let sources: Vec<SourceSpec> = if args.sources.is_empty() {
        CASES.iter().map(|c| c.parse()).collect::<Result<_, _>>().context("a built-in case")?
    } else {
        args.sources
    };
    let mut table = String::from(
        "| source | scans | path | MR ATE | EMR ATE | loops | false loops | worst loop error | odometry between them, worst | rejected: registered + not (right after all) | loop ms/keyframe (median, p95) | optimisations (total ms) |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    let sim = args.sim.config();
    for source in &sources {
        let name = source.to_string();
        let preset = if name.contains("campus") { Preset::Outdoor } else { Preset::Indoor };
        let mut config = OdometryConfig::preset(preset);
        if let Some(path) = &args.config {
            let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
            config = config.overlay(&text).with_context(|| format!("{}: invalid configuration", path.display()))?;
        }
        let mut track = LoopTrack::new(config.loops.clone());
        let mut odometry = Odometry::new(config.clone())?;
        let scans = pipeline::Scans::new(pipeline::open(source, Default::default(), args.max_frames, &config, &sim)?);
        let watch = Stopwatch::start();
        // One core, as a robot's computer would give it.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
        let pass = pool.install(|| {
            pipeline::register(&mut odometry, scans, |pass, frame| {
                if pass.len() % 200 == 0 {
                    eprintln!("{name}: {} scans, {:.0} s", pass.len(), watch.elapsed_ms() / 1e3);
                }
                Ok(track.observe(frame)?)
            })
        })?;
        let mr = pipeline::evaluate(&pass.truth, &pass.estimate.poses)?
            .with_context(|| format!("{name}: no ground truth"))?;
        let emr = pipeline::evaluate(&pass.truth, &track.corrected())?.context("ground truth")?;
        let judged = track.judge(&mr.truth.poses);
        let s = track.summary();
        writeln!(
            table,
            "| {name} | {} | {:.0} m | {} | {} | {} | {} | {:.1} cm, {:.2} deg | {:.1} cm, {:.2} deg | {} + {} ({}) | {:.1}, {:.1} | {} ({:.0}) |",
            pass.len(),
            mr.path_length_m,
            ate(&mr.ate),
            ate(&emr.ate),
            judged.loops,
            judged.false_loops,
            judged.worst_translation_m * 100.0,
            judged.worst_rotation_deg,
            judged.worst_odometry_translation_m * 100.0,
            judged.worst_odometry_rotation_deg,
            s.rejected - s.unreachable,
            s.unreachable,
            judged.missed,
            s.detect_ms_median,
            s.detect_ms_p95,
            s.optimisations,
            s.optimise_ms_total,
        )?;
        eprintln!("{name}: done in {:.0} s", watch.elapsed_ms() / 1e3);
    }
    println!("{table}");
    Ok(())
}

/// ATE as the table shows it: unaligned (both start at the identity), centimetres.
fn ate(a: &AteRmse) -> String {
    format!("{:.1} cm", a.unaligned * 100.0)
}
