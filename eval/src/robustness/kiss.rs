//! KISS-ICP (PyPI `kiss-icp`, through `scripts/compare_kiss_icp.py`) on a case written to disk.

use std::path::{Path, PathBuf};
use std::process::Command;

use cloud::trajectory::{Trajectory, TrajectoryError};

use super::case::Case;
use super::run::{HoldCriterion, Outcome, chain, judge};

/// How KISS-ICP is run.
#[derive(Clone, Debug, PartialEq)]
pub struct KissConfig {
    /// The Python interpreter. Default `python3`.
    pub python: PathBuf,
    /// The comparison script. Default `scripts/compare_kiss_icp.py` of this repository.
    pub script: PathBuf,
}

impl Default for KissConfig {
    fn default() -> Self {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/compare_kiss_icp.py");
        KissConfig { python: "python3".into(), script }
    }
}

/// Why KISS-ICP gave no poses.
#[derive(Debug, thiserror::Error)]
pub enum KissError {
    /// The interpreter could not be started.
    #[error("cannot run {}", python.display())]
    Spawn { python: PathBuf, source: std::io::Error },
    /// The script failed.
    #[error("{} exited with {status}: {stderr}", script.display())]
    Failed { script: PathBuf, status: std::process::ExitStatus, stderr: String },
    /// Its poses cannot be read.
    #[error("cannot read {}", path.display())]
    Read { path: PathBuf, source: std::io::Error },
    /// Its poses are not a KITTI pose file.
    #[error("{}", path.display())]
    Parse { path: PathBuf, source: TrajectoryError },
}

/// KISS-ICP's poses and speed on one directory of scans.
#[derive(Clone, Debug, PartialEq)]
pub struct KissRun {
    /// One pose per scan, the first the identity.
    pub poses: Trajectory,
    /// Median milliseconds per scan, as the script measured it.
    pub ms_per_scan: Option<f64>,
}

impl KissConfig {
    /// Whether the interpreter can import `kiss_icp`.
    pub fn available(&self) -> bool {
        Command::new(&self.python).args(["-c", "import kiss_icp"]).output().is_ok_and(|o| o.status.success())
    }

    /// Runs the script on the KITTI directory `scans` into `out`; `deskew` gives it per-point times
    /// from the azimuth.
    pub fn run(&self, scans: &Path, out: &Path, deskew: bool) -> Result<KissRun, KissError> {
        let mut command = Command::new(&self.python);
        command.arg(&self.script).arg(scans).arg(out);
        if deskew {
            command.arg("--deskew");
        }
        let output = command.output().map_err(|source| KissError::Spawn { python: self.python.clone(), source })?;
        if !output.status.success() {
            let stderr = String::from_utf8_lossy(&output.stderr);
            let tail = stderr.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("").to_owned();
            return Err(KissError::Failed { script: self.script.clone(), status: output.status, stderr: tail });
        }
        let path = out.join("poses_kitti.txt");
        let text = std::fs::read_to_string(&path).map_err(|source| KissError::Read { path: path.clone(), source })?;
        let poses = Trajectory::parse_kitti(&text).map_err(|source| KissError::Parse { path, source })?;
        let timing = std::fs::read_to_string(out.join("timing.txt")).unwrap_or_default();
        Ok(KissRun { poses, ms_per_scan: median_ms(&timing) })
    }
}

/// The `median_ms` figure of the script's timing.txt.
fn median_ms(timing: &str) -> Option<f64> {
    let words: Vec<&str> = timing.split_whitespace().collect();
    words.windows(2).find(|w| w[0] == "median_ms").and_then(|w| w[1].parse().ok())
}

/// KISS-ICP on `case`, already written to `scans` (see [`super::export::write_kitti`]), judged
/// like ours.
pub fn run_kiss(kiss: &KissConfig, case: &Case, scans: &Path, criterion: &HoldCriterion) -> Outcome {
    match kiss.run(scans, &scans.join("kiss"), case.deskew) {
        Ok(run) => Outcome {
            verdict: judge(&case.truth(), &run.poses.poses, criterion).map_err(|e| chain(&e)),
            ms_per_scan: run.ms_per_scan,
            lost: None,
            recoveries: None,
            poses: run.poses.poses,
        },
        Err(e) => Outcome::failed(chain(&e)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_median_of_the_timing_file() {
        assert_eq!(median_ms("scans 16 median_ms 36.412 mean_ms 40.1 median_cpu_ms 35.0\n"), Some(36.412));
        assert_eq!(median_ms(""), None);
    }
}
