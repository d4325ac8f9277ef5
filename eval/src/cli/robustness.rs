//! `emr-eval robustness`: the odometry robustness matrix, ours beside KISS-ICP.

use std::path::PathBuf;

use anyhow::{Result, bail};
use cloud::stopwatch::Stopwatch;
use eval::robustness::{self, HoldCriterion, KissConfig, Part, Row, RunOptions, Summary, Table};

/// Arguments of `emr-eval robustness`.
#[derive(clap::Args, Debug)]
pub struct RobustnessArgs {
    /// Run KISS-ICP beside ours, failing if python3 cannot import kiss_icp [default: when it can].
    #[arg(long, conflicts_with = "no_kiss")]
    kiss: bool,
    /// Ours only.
    #[arg(long)]
    no_kiss: bool,
    /// A small subset with few scans per case (a minute or two).
    #[arg(long)]
    quick: bool,
    /// Only the cases whose name contains this.
    #[arg(long = "case")]
    case: Option<String>,
    /// Only this part of the matrix: the cases the settings were tuned on, or the held-back ones,
    /// never tuned on [default: both].
    #[arg(long, value_enum)]
    part: Option<Part>,
    /// Runs each simulated or shuffled case with noise drawn from seeds 0..N and reports each
    /// case's spread over them (real scans run once).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    seeds: u64,
    /// Keep each case's scans here as OUT/NAME (KITTI layout: velodyne/NNNNNN.bin, poses.txt,
    /// times.txt), our poses in OUT/NAME/ours and KISS-ICP's in OUT/NAME/kiss [default: a
    /// temporary directory, removed case by case].
    #[arg(long)]
    out: Option<PathBuf>,
    /// The KITTI sequence directory (velodyne/, times.txt, poses_velodyne.txt).
    #[arg(long, default_value = "../shared/data/kitti00")]
    data: PathBuf,
}

/// `emr-eval robustness`.
pub fn robustness(args: RobustnessArgs) -> Result<()> {
    let planned: Vec<_> = robustness::matrix(&args.data, args.quick)
        .into_iter()
        .filter(|p| args.case.as_ref().is_none_or(|c| p.name.contains(c.as_str())))
        .filter(|p| args.part.is_none_or(|part| p.part == part))
        .collect();
    if planned.is_empty() {
        bail!("no case matches {:?}", args.case.unwrap_or_default());
    }
    let kiss = kiss(&args)?;
    let out =
        args.out.clone().unwrap_or_else(|| std::env::temp_dir().join(format!("emr-robustness-{}", std::process::id())));
    let options = RunOptions {
        criterion: HoldCriterion::default(),
        out: kiss.is_some().then_some(out.clone()).or(args.out.clone()),
        kiss,
    };
    // Each case at every seed it has a draw for: real scans once.
    let runs: Vec<(&robustness::Planned, u64)> =
        planned.iter().flat_map(|p| (0..args.seeds).filter(|&s| p.seeded(s).is_some()).map(move |s| (p, s))).collect();
    let mut rows = Vec::new();
    for (i, &(case, seed)) in runs.iter().enumerate() {
        let what = format!("[{}/{}] {} seed {seed}", i + 1, runs.len(), case.name);
        eprintln!("{what} ...");
        let watch = Stopwatch::start();
        let row = robustness::run_case(case, seed, &options);
        eprintln!("{what} {} in {:.0} s", summary(&row), watch.elapsed_ms() / 1e3);
        if args.out.is_none() {
            let _ = std::fs::remove_dir_all(out.join(format!("{}-seed-{seed}", row.name)));
        }
        rows.push(row);
    }
    if args.out.is_none() {
        let _ = std::fs::remove_dir(&out);
    }
    print!("{}\n{}", Table(&rows), Summary(&rows));
    Ok(())
}

/// KISS-ICP's runner, when it is to run.
fn kiss(args: &RobustnessArgs) -> Result<Option<KissConfig>> {
    let kiss = KissConfig::default();
    if args.no_kiss {
        return Ok(None);
    }
    let available = kiss.available();
    if args.kiss && !available {
        bail!("--kiss: {} cannot import kiss_icp (pip install kiss-icp==1.3.0)", kiss.python.display());
    }
    if !available {
        tracing::warn!("python3 cannot import kiss_icp: ours only (pip install kiss-icp==1.3.0)");
    }
    Ok(available.then_some(kiss))
}

/// One line on how a case went.
fn summary(row: &Row) -> String {
    let word = |o: &robustness::Outcome| match &o.verdict {
        Ok(v) if v.held => "held".to_owned(),
        Ok(_) => "lost".to_owned(),
        Err(e) => format!("error ({e})"),
    };
    let kiss = row.kiss.as_ref().map_or(String::new(), |k| format!(", KISS-ICP {}", word(k)));
    format!("({} scans): ours {}{kiss}", row.scans, word(&row.ours))
}
