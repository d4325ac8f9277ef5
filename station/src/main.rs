//! `emr-station`: the central station of EMR-FLOAM. Thin: parses arguments, sets up logging and calls
//! the libraries.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand, ValueEnum};
use nalgebra::Isometry3;
use proto::{Fleet, keyexpr};
use station::merge::files::{self, AlignMethod, Alignment};
use station::merge::{MapStatus, MergeConfig, MergeReport};
use station::pairwise::bench::{bench_merge_files, read_transform};

/// The central station of EMR-FLOAM multi-robot LiDAR SLAM.
///
/// The station collects the keyframes that every robot of a fleet streams over Zenoh, finds where
/// the robots' maps overlap, fuses them into one global 3D map and publishes it with a confidence
/// score per robot. Today it offers map merging and registration on files and the inspection tools
/// below; the networked service arrives with the next releases.
#[derive(Parser, Debug)]
#[command(name = "emr-station", version, about, long_about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Print the Zenoh key expressions of a fleet: what to subscribe to from your own tools.
    Keys {
        /// Fleet name (ASCII letters, digits, '-' and '_').
        #[arg(long, default_value = "demo")]
        fleet: String,
        /// Robot id used in the per-robot keys.
        #[arg(long, default_value_t = 1)]
        robot: u32,
    },
    /// Read point-cloud files (.bin KITTI, .pcd, .ply) and print what they hold: points, channels,
    /// bounds and how many invalid (NaN/inf) points were dropped.
    Info {
        /// The files to read.
        #[arg(required = true)]
        files: Vec<PathBuf>,
    },
    /// Merge robot maps (.pcd, .ply, .bin) into one global map, without initial guesses.
    ///
    /// Writes DIR/global_map.ply (binary little endian, in the reference map's frame) and
    /// DIR/transforms.json: per input map its `transform` (4x4 row-major, maps THAT MAP's points
    /// into the global frame; identity when unmerged), `confidence` (the overlap-aware score of
    /// the weakest tree edge to the reference, 1 for the reference, 0 unmerged) and `status`
    /// ("merged" or "unmerged"); per accepted pair an edge {a, b, transform, confidence, inliers}
    /// whose transform maps map b's points into map a's frame (a, b: 0-based input positions);
    /// and `timing_ms` per stage.
    Merge {
        /// The maps, at least one.
        #[arg(required = true)]
        maps: Vec<PathBuf>,
        /// Output directory (created if missing).
        #[arg(long)]
        out: PathBuf,
        /// Parameter preset: indoor (0.1 m features) or outdoor (0.4 m).
        #[arg(long, value_enum, default_value_t = Preset::Outdoor)]
        preset: Preset,
        /// 0-based position of the map whose frame is the global frame (default: the centre of the
        /// spanning tree).
        #[arg(long)]
        reference: Option<usize>,
    },
    /// Register SOURCE onto TARGET; prints the 4x4 transform mapping SOURCE points into the
    /// TARGET frame (4 lines, row-major) and a confidence line.
    Align {
        /// The cloud to move.
        source: PathBuf,
        /// The cloud to align to.
        target: PathBuf,
        /// Initial guess for vgicp/gicp: a text file with a 4x4 matrix (16 numbers, row-major) or
        /// a KITTI 3x4 line (12 numbers). Ignored by `global`.
        #[arg(long)]
        init: Option<PathBuf>,
        /// global: features + RANSAC + VGICP, no guess needed; vgicp, gicp: fine registration
        /// from --init (identity by default).
        #[arg(long, value_enum, default_value_t = CliMethod::Global)]
        method: CliMethod,
        /// Parameter preset: indoor or outdoor.
        #[arg(long, value_enum, default_value_t = Preset::Outdoor)]
        preset: Preset,
        /// Write the transformed SOURCE cloud here (.ply binary, .pcd binary or .bin by extension).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Benchmarks.
    #[command(subcommand)]
    Bench(Bench),
}

#[derive(Subcommand, Debug)]
enum Bench {
    /// Time the pairwise global registration on SOURCE and TARGET (default: the KITTI 08 reverse
    /// revisit in ../shared/data/kitti08_revisit, 001500.bin onto 000720.bin, with its reference).
    Merge {
        /// Source cloud (moved onto the target).
        source: Option<PathBuf>,
        /// Target cloud.
        target: Option<PathBuf>,
        /// Reference transform (4x4 or KITTI 3x4 text) mapping source into target.
        #[arg(long)]
        reference: Option<PathBuf>,
        /// Runs to time.
        #[arg(long, default_value_t = 3)]
        runs: usize,
        /// Parameter preset: indoor or outdoor.
        #[arg(long, value_enum, default_value_t = Preset::Outdoor)]
        preset: Preset,
    },
}

/// Parameter presets.
#[derive(Clone, Copy, Debug, ValueEnum)]
enum Preset {
    Indoor,
    Outdoor,
}

impl Preset {
    fn config(self) -> MergeConfig {
        match self {
            Preset::Indoor => MergeConfig::indoor(),
            Preset::Outdoor => MergeConfig::outdoor(),
        }
    }
}

/// Registration methods of `align`.
#[derive(Clone, Copy, Debug, ValueEnum)]
enum CliMethod {
    Global,
    Vgicp,
    Gicp,
}

/// The KITTI reverse-revisit pair, relative to the project root.
const KITTI_REVISIT: &str = "../shared/data/kitti08_revisit";

fn main() -> Result<()> {
    // On a terminal, info; headless, only errors unless RUST_LOG says otherwise (as emr-edge).
    use std::io::IsTerminal;
    let default = if std::io::stderr().is_terminal() { "info" } else { "error" };
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| default.into()))
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Keys { fleet, robot } => print_keys(&Fleet::new(&fleet)?, robot),
        Command::Info { files } => {
            for f in &files {
                print_info(f)?;
            }
        }
        Command::Merge { maps, out, preset, reference } => {
            let config = MergeConfig { reference, ..preset.config() };
            let report = files::merge_files(&maps, &out, &config)?;
            print_merge(&maps, &report, &out);
        }
        Command::Align { source, target, init, method, preset, out } => {
            align(&source, &target, init.as_deref(), method, &preset.config(), out.as_deref())?
        }
        Command::Bench(Bench::Merge { source, target, reference, runs, preset }) => {
            bench_merge(source, target, reference, runs, preset)?
        }
    }
    Ok(())
}

fn print_merge(inputs: &[PathBuf], report: &MergeReport, out: &Path) {
    for (m, path) in report.maps.iter().zip(inputs) {
        match &m.status {
            MapStatus::Merged { confidence, hops, .. } => {
                println!("{}: merged (confidence {confidence:.3}, {hops} hops)", path.display())
            }
            MapStatus::Unmerged(reason) => println!("{}: unmerged ({reason})", path.display()),
        }
    }
    for p in &report.pairs {
        match &p.verdict {
            station::merge::PairVerdict::Edge(e) => {
                println!("pair {}-{}: edge, confidence {:.3}, {} inliers", p.a, p.b, e.confidence.score, e.inliers)
            }
            station::merge::PairVerdict::Rejected { reason, .. } => {
                println!("pair {}-{}: rejected ({reason})", p.a, p.b)
            }
        }
    }
    println!(
        "{} of {} maps merged, {} points in {} ({:.0} ms)",
        report.merged(),
        report.maps.len(),
        report.global_map.len(),
        out.join("global_map.ply").display(),
        report.timing.total.as_secs_f64() * 1e3
    );
}

fn align(
    source: &Path,
    target: &Path,
    init: Option<&Path>,
    method: CliMethod,
    config: &MergeConfig,
    out: Option<&Path>,
) -> Result<()> {
    let init = init.map(read_transform).transpose()?.unwrap_or_else(Isometry3::identity);
    let method = match method {
        CliMethod::Global => AlignMethod::Global,
        CliMethod::Vgicp => AlignMethod::Vgicp,
        CliMethod::Gicp => AlignMethod::Gicp,
    };
    let maps = files::read_maps(&[source.to_owned(), target.to_owned()])?;
    let result = files::align_pair(&maps[0], &maps[1], &init, method, config)?;
    print_alignment(&result);
    if let Some(out) = out {
        files::write_by_extension(out, &maps[0].transformed(&result.transform.cast::<f32>()))?;
    }
    Ok(())
}

fn print_alignment(a: &Alignment) {
    for row in files::matrix_rows(&a.transform) {
        println!("{:.9} {:.9} {:.9} {:.9}", row[0], row[1], row[2], row[3]);
    }
    let score = a.score.map_or("-".to_owned(), |s| format!("{s:.4}"));
    let inliers = a.inliers.map_or("-".to_owned(), |n| n.to_string());
    println!("confidence {score} overlap {:.4} fitness {:.3} inliers {inliers}", a.overlap, a.fitness);
}

fn bench_merge(
    source: Option<PathBuf>,
    target: Option<PathBuf>,
    reference: Option<PathBuf>,
    runs: usize,
    preset: Preset,
) -> Result<()> {
    let (source, target, reference) = match (source, target) {
        (Some(s), Some(t)) => (s, t, reference),
        (None, None) => {
            let dir = Path::new(KITTI_REVISIT);
            if !dir.is_dir() {
                bail!("{} not found: run from the project root or give SOURCE and TARGET", dir.display());
            }
            let reference = reference.unwrap_or_else(|| dir.join("T_000720_001500.txt"));
            (dir.join("001500.bin"), dir.join("000720.bin"), Some(reference))
        }
        _ => bail!("give both SOURCE and TARGET, or neither for the KITTI revisit pair"),
    };
    let bench = bench_merge_files(&source, &target, reference.as_deref(), &preset.config().pairwise, runs)
        .with_context(|| format!("benchmarking {} onto {}", source.display(), target.display()))?;
    print!("{bench}");
    Ok(())
}

fn print_keys(fleet: &Fleet, robot: u32) {
    let rows = [
        (keyexpr::keyframe(fleet, robot), "Keyframe", "edge"),
        (keyexpr::posegraph(fleet, robot), "PoseGraphUpdate", "edge"),
        (keyexpr::keyframe_store(fleet, robot), "queryable: KeyframeRequest -> Keyframe", "edge"),
        (keyexpr::alive(fleet, robot), "liveliness token", "edge"),
        (keyexpr::global_map(fleet), "GlobalMap (also a queryable)", "station"),
        (keyexpr::station_status(fleet), "StationStatus", "station"),
        (keyexpr::all_robots(fleet), "wildcard: every robot topic", "subscribers"),
    ];
    for (key, payload, from) in rows {
        println!("{key:<40} {payload:<42} {from}");
    }
}

fn print_info(path: &std::path::Path) -> Result<()> {
    let read = cloud::formats::read_cloud(path)?;
    let c = &read.cloud;
    let ch = c.channels();
    let (lo, hi) = c.points.iter().fold(([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]), |(lo, hi), p| {
        (std::array::from_fn(|i| lo[i].min(p[i])), std::array::from_fn(|i| hi[i].max(p[i])))
    });
    println!(
        "{}: {} points (dropped {} non-finite), intensity {}, ring {}, time {}",
        path.display(),
        c.len(),
        read.dropped_non_finite,
        yes_no(ch.intensity),
        yes_no(ch.ring),
        yes_no(ch.time)
    );
    if !c.is_empty() {
        println!("  bounds min {lo:.3?} max {hi:.3?}");
    }
    c.validate().with_context(|| format!("{}: inconsistent cloud", path.display()))?;
    Ok(())
}

fn yes_no(b: bool) -> &'static str {
    if b { "yes" } else { "no" }
}
