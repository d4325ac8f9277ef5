//! `emr-edge eval`: accuracy of a trajectory file against a ground-truth file.

use std::path::PathBuf;

use anyhow::{Context, Result};
use cloud::trajectory::Trajectory;

/// Arguments of `emr-edge eval`.
#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Ground-truth trajectory (KITTI: 12 numbers per line; TUM: stamp tx ty tz qx qy qz qw).
    #[arg(long)]
    gt: PathBuf,
    /// Estimated trajectory, same formats.
    #[arg(long)]
    est: PathBuf,
    /// TUM files: largest stamp difference (s) for two poses to be paired.
    #[arg(long, default_value_t = 0.02)]
    max_dt: f64,
}

/// `emr-edge eval`.
pub fn evaluate(args: &EvalArgs) -> Result<()> {
    let read = |p: &PathBuf| -> Result<Trajectory> {
        let text = std::fs::read_to_string(p).with_context(|| format!("cannot read {}", p.display()))?;
        Trajectory::parse(&text).with_context(|| format!("{}", p.display()))
    };
    let (gt, est) = (read(&args.gt)?, read(&args.est)?);
    let (g, e) = cloud::trajectory::pair(&gt, &est, args.max_dt)?;
    let unaligned = cloud::trajectory::ate(&g, &e, false)?;
    let aligned = cloud::trajectory::ate(&g, &e, true);
    let length = Trajectory { poses: g.clone(), stamps: None }.length();
    let rpe = cloud::trajectory::rpe(&g, &e, &cloud::trajectory::segment_lengths(length));
    println!("poses paired        {}", unaligned.pairs);
    println!("path length         {length:.3} m");
    println!("ATE RMSE unaligned  {:.4} m (mean {:.4}, max {:.4})", unaligned.rmse, unaligned.mean, unaligned.max);
    match aligned {
        Ok(a) => println!("ATE RMSE SE(3)      {:.4} m (mean {:.4}, max {:.4})", a.rmse, a.mean, a.max),
        // A straight path leaves the rotation about it undetermined.
        Err(e) => println!("ATE RMSE SE(3)      not computed: {e}"),
    }
    match rpe {
        Ok(r) => println!(
            "RPE                 {:.3} % translation, {:.3} deg/100 m over {} segments of {:?} m",
            r.translation_percent,
            r.rotation_deg_per_100m,
            r.segments,
            r.lengths.iter().map(|l| (l * 10.0).round() / 10.0).collect::<Vec<_>>()
        ),
        Err(e) => println!("RPE                 not computed: {e}"),
    }
    Ok(())
}
