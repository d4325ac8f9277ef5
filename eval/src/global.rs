//! `emr-eval global`: [`align`] timed on a scan pair, and its error against a reference.

use std::fmt;
use std::path::{Path, PathBuf};

use nalgebra::Isometry3;

use cloud::formats::{read_cloud, read_transform};
use cloud::global::{GlobalAlignment, GlobalConfig, GlobalError, align};
use cloud::se3::{PoseError, pose_error};

use crate::registration::{BenchError as InputError, Timing, median_ms};

/// Why the benchmark could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// A cloud or the reference could not be read.
    #[error(transparent)]
    Input(#[from] InputError),
    /// The registration refused the pair.
    #[error(transparent)]
    Global(#[from] GlobalError),
}

/// Figures of repeated registrations of one pair.
pub struct Report {
    /// The clouds: source, target.
    pub files: (PathBuf, PathBuf),
    /// Raw point counts: source, target.
    pub points: (usize, usize),
    /// Timed runs.
    pub runs: usize,
    /// Threads of the default rayon pool.
    pub threads: usize,
    /// Median and minimum wall time of [`align`], milliseconds.
    pub align_ms: Timing,
    /// The result (every run gives the same: the sampler is seeded).
    pub alignment: GlobalAlignment,
    /// Error of the transform, and of RANSAC's before the polish, against the reference.
    pub error: Option<(PoseError, PoseError)>,
}

/// Registers `source` onto `target` `runs` times (at least once) with `config`; `reference` is a
/// 4x4 row-major matrix mapping source points into the target frame.
pub fn global(
    source: &Path,
    target: &Path,
    reference: Option<&Path>,
    config: &GlobalConfig,
    runs: usize,
) -> Result<Report, BenchError> {
    let s = read_cloud(source).map_err(InputError::from)?.cloud;
    let t = read_cloud(target).map_err(InputError::from)?.cloud;
    let reference: Option<Isometry3<f64>> = reference.map(read_transform).transpose().map_err(InputError::from)?;
    let alignment = align(&s, &t, config)?;
    let runs = runs.max(1);
    let align_ms = median_ms(runs, || align(&s, &t, config).map(|_| ()))?;
    let error = reference.map(|r| (pose_error(&alignment.transform, &r), pose_error(&alignment.coarse_transform, &r)));
    Ok(Report {
        files: (source.to_owned(), target.to_owned()),
        points: (s.len(), t.len()),
        runs,
        threads: rayon::current_num_threads(),
        align_ms,
        alignment,
        error,
    })
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let a = &self.alignment;
        writeln!(
            f,
            "global registration of {} ({} points) onto {} ({} points), all threads = {}",
            self.files.0.display(),
            self.points.0,
            self.files.1.display(),
            self.points.1,
            self.threads
        )?;
        writeln!(f, "align: {} ms, median (min) of {} runs", self.align_ms, self.runs)?;
        writeln!(
            f,
            "keypoints {} / {}, correspondences {}, inliers {} ({:.1}%), RANSAC samples {}, fitness {:.3}, rmse {:.3} m",
            a.keypoints.0,
            a.keypoints.1,
            a.correspondences,
            a.inliers,
            a.inlier_ratio * 100.0,
            a.ransac_iterations,
            a.fitness,
            a.rmse
        )?;
        match &self.error {
            Some((e, c)) => write!(
                f,
                "error vs reference: {:.3} m, {:.3} deg (before polish {:.3} m, {:.3} deg)",
                e.translation_m, e.rotation_deg, c.translation_m, c.rotation_deg
            ),
            None => write!(f, "no reference given"),
        }
    }
}
