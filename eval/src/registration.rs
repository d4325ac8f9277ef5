//! `emr-eval gicp`: registration time and accuracy on a cloud pair with a reference pose.

use std::fmt;
use std::path::{Path, PathBuf};

use nalgebra::Isometry3;

use cloud::PointCloud;
use cloud::formats::{FormatError, TransformError, read_cloud, read_transform};
use cloud::registration::{
    GaussianCloud, Method, RegistrationConfig, RegistrationError, RegistrationResult, align_gaussians,
};
use cloud::se3::{PoseError, pose_error};
use cloud::voxel::downsample;

/// Voxel edge both clouds are downsampled to before registration (small_gicp's default), metres.
pub const DOWNSAMPLING: f32 = 0.25;

/// Why the benchmark could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// A cloud could not be read.
    #[error(transparent)]
    Cloud(#[from] FormatError),
    /// The reference pose file could not be read or is not a rigid transform.
    #[error(transparent)]
    Reference(#[from] TransformError),
    /// A registration refused its input.
    #[error(transparent)]
    Registration(#[from] RegistrationError),
}

/// One timed variant: method, threads, what was timed.
pub struct Row {
    /// What ran, e.g. "VGICP 1 thread".
    pub label: String,
    /// Median and minimum wall time of the registration alone (clouds already prepared), ms.
    pub register_ms: Timing,
    /// Median and minimum wall time from the raw clouds (downsampling and covariances included), ms.
    pub pipeline_ms: Timing,
    /// Error of the estimate against the reference.
    pub error: PoseError,
    /// The estimate's figures (iterations, inliers, convergence).
    pub result: RegistrationResult,
}

/// Wall times of repeated runs, milliseconds.
#[derive(Clone, Copy, Debug)]
pub struct Timing {
    /// The median run.
    pub median: f64,
    /// The fastest run: the least disturbed by other load on the machine.
    pub min: f64,
}

/// All rows of one run.
pub struct Report {
    /// Directory read.
    pub data: PathBuf,
    /// Raw point counts (source, target).
    pub raw_points: (usize, usize),
    /// Downsampled point counts (source, target).
    pub points: (usize, usize),
    /// Timed runs per figure (the median is reported).
    pub runs: usize,
    /// Threads of the default rayon pool.
    pub threads: usize,
    /// One row per variant.
    pub rows: Vec<Row>,
}

/// Runs GICP and VGICP (coarse-to-fine and single-level) on DIR/{source,target}.ply, on one thread
/// and on all, `runs` times each, and compares with DIR/T_target_source.txt.
pub fn gicp(data: &Path, runs: usize) -> Result<Report, BenchError> {
    let runs = runs.max(1);
    let source_raw = read_cloud(&data.join("source.ply"))?.cloud;
    let target_raw = read_cloud(&data.join("target.ply"))?.cloud;
    let reference = read_transform(&data.join("T_target_source.txt"))?;
    let config = RegistrationConfig::default();
    let single_level = RegistrationConfig { coarse_levels: 0, ..config.clone() };
    let variants = [
        ("GICP", Method::Gicp, &config),
        ("VGICP [2r, r]", Method::Vgicp, &config),
        ("VGICP [r] (as small_gicp)", Method::Vgicp, &single_level),
    ];
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("a one-thread pool");
    let all = rayon::ThreadPoolBuilder::new().build().expect("a default pool");
    let mut rows = Vec::new();
    let mut points = (0, 0);
    for (pool, threads) in [(&one, "1 thread"), (&all, "all threads")] {
        for (name, method, config) in variants {
            let (source, target) = pool.install(|| prepare(&source_raw, &target_raw, config));
            points = (source.len(), target.len());
            let init = Isometry3::identity();
            let register = || align_gaussians(&source, &target, &init, method, config);
            let result = pool.install(register)?;
            let register_ms = median_ms(runs, || pool.install(register).map(|_| ()))?;
            let pipeline_ms = median_ms(runs, || {
                pool.install(|| {
                    let (s, t) = prepare(&source_raw, &target_raw, config);
                    align_gaussians(&s, &t, &init, method, config).map(|_| ())
                })
            })?;
            let error = pose_error(&result.transform, &reference);
            rows.push(Row { label: format!("{name}, {threads}"), register_ms, pipeline_ms, error, result });
        }
    }
    Ok(Report {
        data: data.to_owned(),
        raw_points: (source_raw.len(), target_raw.len()),
        points,
        runs,
        threads: all.current_num_threads(),
        rows,
    })
}

/// Downsamples both clouds and estimates their covariances.
fn prepare(source: &PointCloud, target: &PointCloud, config: &RegistrationConfig) -> (GaussianCloud, GaussianCloud) {
    let down = |c: &PointCloud| downsample(c, DOWNSAMPLING).expect("a positive constant voxel size");
    let (s, t) = rayon::join(|| down(source), || down(target));
    rayon::join(
        || GaussianCloud::new(&s.points, config.neighbours),
        || GaussianCloud::new(&t.points, config.neighbours),
    )
}

/// Median and minimum wall time of `runs` calls, milliseconds.
pub(crate) fn median_ms<E>(runs: usize, mut f: impl FnMut() -> Result<(), E>) -> Result<Timing, E> {
    let mut times = Vec::with_capacity(runs);
    for _ in 0..runs {
        let (result, took) = cloud::stopwatch::timed(&mut f);
        result?;
        times.push(cloud::stopwatch::millis(took));
    }
    let low = cloud::stats::Low::of(&times);
    Ok(Timing { median: low.median, min: low.min })
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "GICP/VGICP on {} (identity initial guess)", self.data.display())?;
        writeln!(
            f,
            "points: source {} -> {}, target {} -> {} after {DOWNSAMPLING} m voxels; median of {} runs; all threads = {}",
            self.raw_points.0, self.points.0, self.raw_points.1, self.points.1, self.runs, self.threads
        )?;
        writeln!(
            f,
            "{:<38} {:>17} {:>17} {:>7} {:>7} {:>5} {:>8} {:>9}",
            "variant", "register ms", "pipeline ms", "err cm", "err deg", "iter", "inliers", "converged"
        )?;
        for r in &self.rows {
            writeln!(
                f,
                "{:<38} {:>17} {:>17} {:>7.2} {:>7.3} {:>5} {:>8} {:>9}",
                r.label,
                r.register_ms.to_string(),
                r.pipeline_ms.to_string(),
                r.error.translation_m * 100.0,
                r.error.rotation_deg,
                r.result.iterations,
                r.result.inliers,
                r.result.converged
            )?;
        }
        write!(
            f,
            "times: median (min) ms; register = registration of prepared clouds; \
             pipeline = downsampling + covariances + registration"
        )
    }
}

impl fmt::Display for Timing {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:.2} ({:.2})", self.median, self.min)
    }
}
