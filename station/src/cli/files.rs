//! `info`, `merge` and `align`: the station's computations on point-cloud files.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use cloud::Preset;
use cloud::formats::read_transform;
use nalgebra::Isometry3;
use station::merge::files::{self, AlignMethod, Alignment};
use station::merge::{MapStatus, MergeConfig, MergeReport, PairVerdict};

// `emr-station info`.
#[derive(Args, Debug)]
pub struct InfoArgs {
    /// The files to read.
    #[arg(required = true)]
    files: Vec<PathBuf>,
}

// `emr-station merge`.
#[derive(Args, Debug)]
pub struct MergeArgs {
    /// The maps, at least one.
    #[arg(required = true)]
    maps: Vec<PathBuf>,
    /// Output directory (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// Parameter preset: indoor (0.1 m features) or outdoor (0.4 m).
    #[arg(long, default_value_t = Preset::Outdoor)]
    preset: Preset,
    /// 0-based position of the map whose frame is the global frame (default: the centre of the
    /// spanning tree).
    #[arg(long)]
    reference: Option<usize>,
}

// `emr-station align`.
#[derive(Args, Debug)]
pub struct AlignArgs {
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
    #[arg(long, default_value_t = Preset::Outdoor)]
    preset: Preset,
    /// Write the transformed SOURCE cloud here (.ply binary, .pcd binary or .bin by extension).
    #[arg(long)]
    out: Option<PathBuf>,
}

/// Registration methods of `align`.
#[derive(Clone, Copy, Debug, ValueEnum)]
enum CliMethod {
    Global,
    Vgicp,
    Gicp,
}

pub fn info(args: InfoArgs) -> Result<()> {
    for f in &args.files {
        print_info(f)?;
    }
    Ok(())
}

pub fn merge(args: MergeArgs) -> Result<()> {
    let MergeArgs { maps, out, preset, reference } = args;
    let config = MergeConfig { reference, ..MergeConfig::preset(preset) };
    let report = files::merge_files(&maps, &out, &config)?;
    print_merge(&maps, &report, &out);
    Ok(())
}

pub fn align(args: AlignArgs) -> Result<()> {
    let AlignArgs { source, target, init, method, preset, out } = args;
    let init = init.as_deref().map(read_transform).transpose()?.unwrap_or_else(Isometry3::identity);
    let method = match method {
        CliMethod::Global => AlignMethod::Global,
        CliMethod::Vgicp => AlignMethod::Vgicp,
        CliMethod::Gicp => AlignMethod::Gicp,
    };
    let maps = files::read_maps(&[source, target])?;
    let result = files::align_pair(&maps[0], &maps[1], &init, method, &MergeConfig::preset(preset))?;
    print_alignment(&result);
    if let Some(out) = out {
        files::write_by_extension(&out, &maps[0].transformed(&result.transform.cast::<f32>()))?;
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
            PairVerdict::Edge(e) => {
                println!("pair {}-{}: edge, confidence {:.3}, {} inliers", p.a, p.b, e.confidence.score, e.inliers)
            }
            PairVerdict::Rejected { reason, .. } => {
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
        cloud::stopwatch::millis(report.timing.total)
    );
    println!("top view in {}", out.join("top_down.png").display());
}

fn print_alignment(a: &Alignment) {
    for row in files::matrix_rows(&a.transform) {
        println!("{:.9} {:.9} {:.9} {:.9}", row[0], row[1], row[2], row[3]);
    }
    let score = a.score.map_or("-".to_owned(), |s| format!("{s:.4}"));
    let inliers = a.inliers.map_or("-".to_owned(), |n| n.to_string());
    println!("confidence {score} overlap {:.4} fitness {:.3} inliers {inliers}", a.overlap, a.fitness);
}

fn print_info(path: &Path) -> Result<()> {
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
