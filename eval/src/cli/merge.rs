//! `emr-eval merge`: the pairwise global registration timed on a pair of clouds.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use cloud::Preset;
use eval::merge::bench_merge_files;
use station::merge::MergeConfig;

/// The KITTI reverse-revisit pair, relative to the project root.
const KITTI_REVISIT: &str = "../shared/data/kitti08_revisit";

/// The arguments of `emr-eval merge`.
#[derive(clap::Args, Debug)]
pub struct MergeArgs {
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
    #[arg(long, default_value_t = Preset::Outdoor)]
    preset: Preset,
}

/// `emr-eval merge`.
pub fn merge(args: MergeArgs) -> Result<()> {
    let MergeArgs { source, target, reference, runs, preset } = args;
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
    let pairwise = MergeConfig::preset(preset).pairwise;
    let bench = bench_merge_files(&source, &target, reference.as_deref(), &pairwise, runs)
        .with_context(|| format!("benchmarking {} onto {}", source.display(), target.display()))?;
    print!("{bench}");
    Ok(())
}
