//! The odometry robustness matrix: the classes of hard input the odometry meets on real
//! recordings, reproduced on data we have, run with our odometry and with KISS-ICP side by side.
//!
//! - [`case`]: a [`Case`] is scans with ground truth and how to run the odometry on them; its
//!   builders take every k-th KITTI scan ([`kitti_every`]), simulate a motion, a sensor and a rate
//!   ([`simulated`]), or shuffle a case's points and drop its ring and time channels ([`shuffled`]).
//! - [`matrix`]: the default cases as recipes, built only when run.
//! - [`run`]: our odometry on a case, and the verdict on any trajectory ([`judge`]): ATE, final
//!   error, and whether the track held ([`HoldCriterion`]).
//! - [`export`] writes a case in the KITTI layout, [`kiss`] runs KISS-ICP on it.
//! - [`report`]: the table.
//!
//! [`run_case`] puts them together for one case; `emr-eval robustness` loops over the matrix.

pub mod case;
pub mod export;
pub mod kiss;
pub mod matrix;
pub mod report;
pub mod run;

use std::path::PathBuf;

pub use case::{Case, CaseError, Motion, SimCase, kitti_every, shuffled, simulated};
pub use kiss::KissConfig;
pub use matrix::{Part, Planned, Recipe, matrix};
pub use report::{Row, Summary, Table};
pub use run::{HoldCriterion, Outcome, Verdict, judge, run_ours};

/// How the cases are run.
#[derive(Clone, Debug, PartialEq)]
pub struct RunOptions {
    /// When a track counts as held.
    pub criterion: HoldCriterion,
    /// KISS-ICP beside ours, when set.
    pub kiss: Option<KissConfig>,
    /// Each case's scans are written to OUT/NAME in the KITTI layout, our poses to
    /// OUT/NAME/ours/poses_kitti.txt and KISS-ICP's results to OUT/NAME/kiss, when set; KISS-ICP
    /// needs it.
    pub out: Option<PathBuf>,
}

/// Builds, runs and judges one case, its noise drawn from `seed` ([`Planned::seeded`]: the row of
/// a case that has one draw only, real scans, is its seed-0 run); a case that cannot be built or
/// run is a row with the error.
pub fn run_case(planned: &Planned, seed: u64, options: &RunOptions) -> Row {
    let seeded = planned.seeded(seed);
    let planned = seeded.as_ref().unwrap_or(planned);
    let failed = |reason: String| Row {
        name: planned.name.clone(),
        class: planned.class.into(),
        part: planned.part,
        seed,
        scans: 0,
        ours: Outcome::failed(reason),
        kiss: None,
    };
    let case = match planned.build() {
        Ok(case) => case,
        Err(e) => return failed(run::chain(&e)),
    };
    let written = options.out.as_ref().map(|out| out.join(format!("{}-seed-{seed}", case.name)));
    if let Some(dir) = &written
        && let Err(e) = export::write_kitti(&case, dir)
    {
        return failed(run::chain(&e));
    }
    let ours = run_ours(&case, &options.criterion);
    if let Some(dir) = &written
        && let Err(e) = export::write_poses(&ours.poses, &dir.join("ours"))
    {
        tracing::warn!("{}", run::chain(&e));
    }
    let kiss = match (&options.kiss, &written) {
        (Some(kiss), Some(dir)) => Some(kiss::run_kiss(kiss, &case, dir, &options.criterion)),
        _ => None,
    };
    Row { name: case.name, class: case.class, part: planned.part, seed, scans: case.scans.len(), ours, kiss }
}
