//! The odometry over a whole source, as `emr-edge odometry`, `emr-edge bench odometry` and the
//! tests run it: the configuration from a preset, a file and flags ([`Tuning`]); the scans
//! registered one by one ([`register`]); the trajectory evaluated against ground truth when the
//! source has it ([`evaluate`]); poses and figures written ([`OdometryPipeline::run`]). The one part
//! of the odometry that touches files.
//!
//! One error policy for every caller: a scan that cannot be decoded is skipped with a warning;
//! damage to a recording's container stops the reading and is an error, after the scans before it
//! were registered and, by [`OdometryPipeline::run`], written; a file that cannot be read or
//! written is an error naming it.

use std::borrow::Borrow;
use std::path::{Path, PathBuf};

use cloud::Preset;
use cloud::stopwatch::Stopwatch;
use cloud::trajectory::{self, Trajectory, TrajectoryError};
use nalgebra::Isometry3;
use serde::Serialize;

use super::config::OverlayError;
use super::stats::{RunStats, RunSummary};
use super::{Frame, Method, Odometry, OdometryConfig, OdometryError};
use crate::loops::LoopError;
use crate::loops::track::{LoopSummary, LoopTrack};
use crate::recording::{RecordingOptions, RingModel, Spin, TimeModel};
use crate::source::{Source, SourceError, SourceLosses, SourceScan, SourceSpec};
use cloud::memory::{MemoryTrace, MemoryWatch, peak_rss_mb};
use sim::SimConfig;

/// Why a run of the odometry failed.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// The configuration file cannot be read.
    #[error("cannot read {}", path.display())]
    ReadConfig { path: PathBuf, source: std::io::Error },
    /// The configuration file is not TOML.
    #[error("{}: invalid TOML", path.display())]
    Toml { path: PathBuf, source: toml::de::Error },
    /// The configuration file's keys or values do not fit.
    #[error("{}: invalid configuration", path.display())]
    Config { path: PathBuf, source: toml::de::Error },
    /// The configuration is unusable, or a scan lacks a channel the odometry needs.
    #[error(transparent)]
    Odometry(#[from] OdometryError),
    /// The source cannot be opened, or its container is damaged.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// A scan the odometry could not register.
    #[error("scan {scan}")]
    Register { scan: usize, source: OdometryError },
    /// The output directory cannot be created.
    #[error("cannot create {}", path.display())]
    CreateDir { path: PathBuf, source: std::io::Error },
    /// An output file cannot be written.
    #[error("cannot write {}", path.display())]
    Write { path: PathBuf, source: std::io::Error },
    /// The trajectory cannot be compared with the ground truth.
    #[error(transparent)]
    Evaluate(#[from] TrajectoryError),
    /// The report cannot be serialised.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// The loop closure failed.
    #[error(transparent)]
    Loops(#[from] LoopError),
}

/// Where the odometry configuration comes from, applied in this order.
#[derive(Clone, Debug)]
pub struct Tuning {
    /// The preset the configuration starts from. Default indoor.
    pub preset: Preset,
    /// A TOML file whose keys replace the preset's. Default none.
    pub file: Option<PathBuf>,
    /// Motion compensation off, for recordings published already compensated. Default false.
    pub no_deskew: bool,
    /// The odometry method, replacing the file's and the preset's. Default none (keep theirs).
    pub method: Option<Method>,
}

impl Default for Tuning {
    fn default() -> Self {
        Tuning { preset: Preset::Indoor, file: None, no_deskew: false, method: None }
    }
}

impl Tuning {
    /// The configuration: the preset, then the file's keys, then the flags.
    pub fn load(&self) -> Result<OdometryConfig, PipelineError> {
        let mut config = OdometryConfig::preset(self.preset);
        if let Some(path) = &self.file {
            let text = std::fs::read_to_string(path)
                .map_err(|source| PipelineError::ReadConfig { path: path.clone(), source })?;
            config = config.overlay(&text).map_err(|e| match e {
                OverlayError::Toml(source) => PipelineError::Toml { path: path.clone(), source },
                OverlayError::Config(source) => PipelineError::Config { path: path.clone(), source },
            })?;
        }
        if self.no_deskew {
            config.deskew = false;
        }
        if let Some(method) = self.method {
            config.method = method;
        }
        Ok(config)
    }
}

/// How recordings are read for the odometry: rings and per-point times derived where missing.
///
/// Rings come from the point order where it is ring-major (exact and cheap, KITTI's layout) and
/// are clustered from elevations otherwise: on a 16-beam sensor voxel shapes
/// ([`super::voxel_features`], what a scan without any ring channel gets) see ring traces as lines
/// and lose the warehouse (0.55 m ATE against 0.16 m every 2nd scan, 6.3 m against 0.04 m every
/// 5th).
/// `reading` holds what the user chose (the topic, how packets decode); the channels are set here.
pub fn recording_options(reading: RecordingOptions, config: &OdometryConfig) -> RecordingOptions {
    RecordingOptions {
        rings: RingModel::Auto,
        times: TimeModel::Azimuth { period_s: config.scan_period, spin: Spin::Detect },
        ..reading
    }
}

/// Opens `input` for the odometry (`reading` picks a bag's or MCAP file's point clouds and says
/// how packets decode, `sim` configures a simulated sensor), at most `max_frames` scans.
pub fn open(
    input: &SourceSpec,
    reading: RecordingOptions,
    max_frames: Option<usize>,
    config: &OdometryConfig,
    sim: &SimConfig,
) -> Result<Source, SourceError> {
    Source::open(input, max_frames, sim, &recording_options(reading, config))
}

/// The scans of a source under the error policy: undecodable scans skipped with a warning (and
/// listed, [`Scans::skipped`]), reading stopped at damage, which [`Scans::finish`] reports.
pub struct Scans {
    source: Source,
    damage: Option<SourceError>,
    skipped: Vec<SkippedScan>,
    losses: SourceLosses,
}

/// A scan the source gave but could not decode.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct SkippedScan {
    /// What went wrong, naming the file or message.
    pub reason: String,
}

impl Scans {
    /// The scans of `source`.
    pub fn new(source: Source) -> Self {
        Scans { source, damage: None, skipped: Vec::new(), losses: SourceLosses::default() }
    }

    /// What the source lost so far.
    pub fn losses(&self) -> SourceLosses {
        self.losses
    }

    /// The scans skipped so far, in order.
    pub fn skipped(&self) -> &[SkippedScan] {
        &self.skipped
    }

    /// The damage that stopped the reading, as an error.
    pub fn finish(self) -> Result<(), SourceError> {
        self.damage.map_or(Ok(()), Err)
    }
}

impl Iterator for Scans {
    type Item = SourceScan;

    fn next(&mut self) -> Option<SourceScan> {
        if self.damage.is_some() {
            return None;
        }
        loop {
            match self.source.next()? {
                Ok(scan) => {
                    self.losses.count(&scan);
                    return Some(scan);
                }
                Err(e) if !e.is_fatal() => {
                    tracing::warn!("skipped: {e}");
                    self.skipped.push(SkippedScan { reason: e.to_string() });
                }
                Err(e) => {
                    self.damage = Some(e);
                    return None;
                }
            }
        }
    }
}

/// Every scan of a source, in memory (for benchmarks, which must not time the reading).
pub fn read_all(source: Source) -> Result<Vec<SourceScan>, SourceError> {
    let mut scans = Scans::new(source);
    let all: Vec<SourceScan> = scans.by_ref().collect();
    scans.finish()?;
    Ok(all)
}

/// One pass of the odometry over scans: what it estimated and what it measured.
#[derive(Clone, Debug)]
pub struct Pass {
    /// Estimated sensor poses at the sweep ends, with the sweeps' start stamps.
    pub estimate: Trajectory,
    /// The source's index of each registered scan (undecodable scans are skipped).
    pub scans: Vec<usize>,
    /// The source's ground-truth poses (world frame), when it knows them.
    pub truth: Vec<Isometry3<f64>>,
    /// Per-scan figures: wall time, stages, features, degeneracy.
    pub stats: RunStats,
    /// CPU time of the registering thread per scan, milliseconds (what other processes take from
    /// the machine does not count).
    pub cpu_ms: Vec<f64>,
}

impl Pass {
    /// Scans registered so far.
    pub fn len(&self) -> usize {
        self.estimate.poses.len()
    }

    /// Whether no scan was registered.
    pub fn is_empty(&self) -> bool {
        self.estimate.poses.is_empty()
    }
}

/// Registers `scans` in order with `odometry`, timing each; `observe` sees the pass and the frame
/// after every scan, and stops the pass with its error.
pub fn register<S: Borrow<SourceScan>>(
    odometry: &mut Odometry,
    scans: impl IntoIterator<Item = S>,
    mut observe: impl FnMut(&Pass, &Frame) -> Result<(), PipelineError>,
) -> Result<Pass, PipelineError> {
    let mut pass = Pass {
        estimate: Trajectory { poses: vec![], stamps: Some(vec![]) },
        scans: vec![],
        truth: vec![],
        stats: RunStats::default(),
        cpu_ms: vec![],
    };
    for scan in scans {
        let scan = scan.borrow();
        let (watch, cpu) = (Stopwatch::start(), thread_cpu_ms());
        let frame = odometry
            .register(&scan.cloud, scan.stamp)
            .map_err(|source| PipelineError::Register { scan: scan.index, source })?;
        if frame.lost {
            tracing::warn!(
                "scan {}: lost (no fit placed it on the map well; kept out of the map, pose from the best fit)",
                scan.index
            );
        }
        pass.stats.add(&frame, watch.elapsed_ms());
        pass.cpu_ms.push(thread_cpu_ms() - cpu);
        pass.estimate.poses.push(frame.pose);
        pass.estimate.stamps.get_or_insert_default().push(scan.stamp);
        pass.truth.extend(scan.ground_truth);
        pass.scans.push(scan.index);
        observe(&pass, &frame)?;
    }
    Ok(pass)
}

/// The trajectory against ground truth, both starting at the identity.
#[derive(Clone, Debug)]
pub struct Accuracy {
    /// The ground truth moved into the odometry frame (its first pose the identity).
    pub truth: Trajectory,
    /// Absolute trajectory error.
    pub ate: AteRmse,
    /// Length of the true path, metres.
    pub path_length_m: f64,
}

/// ATE RMSE, metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AteRmse {
    /// Poses compared as they are.
    pub unaligned: f64,
    /// After the best SE(3) alignment; none when a straight path leaves the rotation about it
    /// undetermined.
    pub aligned: Option<f64>,
}

/// `estimate` against `truth` (world frame) when there is one true pose per estimated pose.
pub fn evaluate(truth: &[Isometry3<f64>], estimate: &[Isometry3<f64>]) -> Result<Option<Accuracy>, TrajectoryError> {
    if truth.len() != estimate.len() || truth.is_empty() {
        return Ok(None);
    }
    let first = truth[0].inverse();
    let truth = Trajectory { poses: truth.iter().map(|p| first * p).collect(), stamps: None };
    let unaligned = trajectory::ate(&truth.poses, estimate, false)?.rmse;
    let aligned = trajectory::ate(&truth.poses, estimate, true).ok().map(|a| a.rmse);
    let path_length_m = truth.length();
    Ok(Some(Accuracy { truth, ate: AteRmse { unaligned, aligned }, path_length_m }))
}

/// What `stats.json` holds: the run's figures, its memory and, with ground truth, its accuracy.
#[derive(Clone, Debug, Serialize)]
pub struct OdometryReport {
    /// Timing, features, degeneracy.
    #[serde(flatten)]
    pub summary: RunSummary,
    /// Peak resident memory of the process, MB.
    pub peak_rss_mb: Option<f64>,
    /// Resident memory along the run, MB: it must stay flat over long runs.
    pub rss_mb: MemoryTrace,
    /// ATE RMSE, when the source has ground truth.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ate_rmse_m: Option<AteRmse>,
    /// Length of the true path, when the source has ground truth.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub path_length_m: Option<f64>,
    /// Scans the source gave but could not be decoded, each with its file and reason.
    pub skipped_scans: Vec<SkippedScan>,
    /// What a packet source lost before decoding.
    pub source_losses: SourceLosses,
    /// With loop closure: its figures.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub loops: Option<LoopSummary>,
    /// With loop closure and ground truth: the ATE of the odometry before the loops (`ate_rmse_m`
    /// is then the optimised trajectory's).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub odometry_ate_rmse_m: Option<AteRmse>,
}

impl OdometryReport {
    /// The report as pretty JSON, keys in alphabetical order (as `stats.json` has always had them).
    pub fn to_json(&self) -> Result<String, serde_json::Error> {
        serde_json::to_string_pretty(&serde_json::to_value(self)?)
    }
}

/// The odometry over one source into one output directory: OUT/poses_kitti.txt (a line per scan,
/// sensor frame at the sweep end, first pose identity), OUT/poses_tum.txt (the same with stamps),
/// OUT/stats.json ([`OdometryReport`]) and, with ground truth, OUT/poses_gt_kitti.txt. With loop
/// closure ([`OdometryPipeline::with_loops`]) the poses are the optimised ones, and it also writes
/// OUT/poses_odometry_kitti.txt (before the loops), OUT/graph.g2o (the keyframe pose graph) and
/// OUT/loops.json ([`crate::loops::track::LoopsFile`]).
pub struct OdometryPipeline {
    source: Source,
    config: OdometryConfig,
    loops: bool,
    out: PathBuf,
}

impl OdometryPipeline {
    /// Opens the source ([`open`]) and creates the output directory; no loop closure.
    pub fn new(
        input: &SourceSpec,
        reading: RecordingOptions,
        max_frames: Option<usize>,
        config: OdometryConfig,
        sim: &SimConfig,
        out: &Path,
    ) -> Result<Self, PipelineError> {
        let source = open(input, reading, max_frames, &config, sim)?;
        std::fs::create_dir_all(out).map_err(|source| PipelineError::CreateDir { path: out.to_owned(), source })?;
        Ok(OdometryPipeline { source, config, loops: false, out: out.to_owned() })
    }

    /// The same with loop closure on (configured by the configuration's `loops`) or off (the
    /// paper's MR mode).
    pub fn with_loops(self, loops: bool) -> Self {
        OdometryPipeline { loops, ..self }
    }

    /// Ends the run early, with what it has, once `interrupt` is set (see [`Source::until`]).
    pub fn until(self, interrupt: std::sync::Arc<std::sync::atomic::AtomicBool>) -> Self {
        OdometryPipeline { source: self.source.until(interrupt), ..self }
    }

    /// How many scans the source will give, when known in advance.
    pub fn expected_scans(&self) -> Option<usize> {
        self.source.len
    }

    /// Registers every scan (`progress` is shown each as it is done), writes the outputs and returns
    /// the report.
    pub fn run(self, mut progress: impl FnMut(&ScanDone<'_>)) -> Result<OdometryReport, PipelineError> {
        let mut track = self.loops.then(|| LoopTrack::new(self.config.loops.clone()));
        let mut odometry = Odometry::new(self.config)?;
        let mut memory = MemoryWatch::new(self.source.len);
        let mut scans = Scans::new(self.source);
        let pass = register(&mut odometry, scans.by_ref(), |pass, frame| {
            if let Some(track) = &mut track {
                track.observe(frame)?;
            }
            memory.observe(pass.len());
            let stamp = pass.estimate.stamps.as_ref().and_then(|s| s.last().copied()).unwrap_or(0.0);
            progress(&ScanDone { scans: pass.len(), frame, stamp, loops: track.as_ref() });
            Ok(())
        })?;
        let summary = pass.stats.summary();
        warn_unhealthy(&summary);
        for warning in scans.losses().warnings() {
            tracing::warn!("{warning}");
        }
        let peak_rss_mb = peak_rss_mb();
        let rss_mb = memory.finish();
        let mut estimate = pass.estimate.clone();
        if let Some(track) = &track {
            estimate.poses = track.corrected();
            write(&self.out.join("poses_odometry_kitti.txt"), &pass.estimate.to_kitti())?;
            write(&self.out.join("loops.json"), &serde_json::to_string_pretty(&track.file(&pass.scans))?)?;
            let graph = track.closer().graph().map_err(LoopError::from)?;
            write(&self.out.join("graph.g2o"), &cloud::pose_graph::g2o::write(&graph))?;
        }
        let accuracy = evaluate(&pass.truth, &estimate.poses)?;
        let odometry_accuracy = match &track {
            Some(_) => evaluate(&pass.truth, &pass.estimate.poses)?,
            None => None,
        };
        let report = OdometryReport {
            summary,
            peak_rss_mb,
            rss_mb,
            ate_rmse_m: accuracy.as_ref().map(|a| a.ate),
            path_length_m: accuracy.as_ref().map(|a| a.path_length_m),
            skipped_scans: scans.skipped().to_vec(),
            source_losses: scans.losses(),
            loops: track.as_ref().map(LoopTrack::summary),
            odometry_ate_rmse_m: odometry_accuracy.map(|a| a.ate),
        };
        if let Some(accuracy) = &accuracy {
            write(&self.out.join("poses_gt_kitti.txt"), &accuracy.truth.to_kitti())?;
        }
        write(&self.out.join("poses_kitti.txt"), &estimate.to_kitti())?;
        write(&self.out.join("poses_tum.txt"), &estimate.to_tum())?;
        write(&self.out.join("stats.json"), &report.to_json()?)?;
        scans.finish()?;
        Ok(report)
    }
}

/// Says so when a run's figures show it did not track ([`health_warnings`]).
pub fn warn_unhealthy(summary: &RunSummary) {
    for warning in health_warnings(summary) {
        tracing::warn!("{warning}");
    }
}

/// What a run's figures show it did not do well: scans nothing measured, scans lost, or a map that
/// stopped growing (one keyframe in a hundred scans or more).
pub fn health_warnings(summary: &RunSummary) -> Vec<String> {
    let frames = summary.frames;
    let mut warnings = Vec::new();
    if summary.unfitted_scans > 0 {
        warnings.push(format!(
            "{} of {frames} scans could not be fitted (too few matches, features or points): their poses are \
             the motion model's extrapolation, not measurements",
            summary.unfitted_scans
        ));
    }
    if summary.recoveries.lost > 0 {
        warnings.push(format!(
            "{} of {frames} scans were lost (no fit placed them on the map well)",
            summary.recoveries.lost
        ));
    }
    if frames >= 100 && summary.keyframes <= 1 {
        warnings.push(format!(
            "{} keyframe(s) in {frames} scans: the map did not grow (a sensor at rest, or odometry that is stuck)",
            summary.keyframes
        ));
    }
    warnings
}

/// One scan done, as [`OdometryPipeline::run`] shows it.
pub struct ScanDone<'a> {
    /// Scans registered so far.
    pub scans: usize,
    /// What the scan produced.
    pub frame: &'a Frame,
    /// The scan's stamp, seconds.
    pub stamp: f64,
    /// The loop closure after the scan, when it runs.
    pub loops: Option<&'a LoopTrack>,
}

/// Writes a text file, naming it in the error.
fn write(path: &Path, text: &str) -> Result<(), PipelineError> {
    std::fs::write(path, text).map_err(|source| PipelineError::Write { path: path.to_owned(), source })
}

/// CPU time the calling thread has used, milliseconds.
fn thread_cpu_ms() -> f64 {
    let mut t = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `t` is a valid timespec for the call to write; the clock id is a constant the
    // kernel always knows.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) };
    t.tv_sec as f64 * 1e3 + t.tv_nsec as f64 * 1e-6
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_without_measured_scans_or_a_growing_map_is_warned_about() {
        let mut summary = RunStats::default().summary();
        summary.frames = 300;
        summary.keyframes = 30;
        assert!(health_warnings(&summary).is_empty());
        summary.keyframes = 1;
        let stuck = "1 keyframe(s) in 300 scans: the map did not grow (a sensor at rest, or odometry that is stuck)";
        assert_eq!(health_warnings(&summary), [stuck]);
        summary.frames = 50;
        assert!(health_warnings(&summary).is_empty(), "a short run may make one keyframe");
        (summary.unfitted_scans, summary.recoveries.lost) = (3, 2);
        let warnings = health_warnings(&summary);
        assert!(warnings[0].starts_with("3 of 50 scans could not be fitted"), "{warnings:?}");
        assert!(warnings[1].starts_with("2 of 50 scans were lost"), "{warnings:?}");
    }
}
