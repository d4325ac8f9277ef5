//! Where scans come from: the built-in simulator (`sim:SCENARIO:ROBOT`) or a recording (a directory
//! of scans, a ROS 1 bag, an MCAP file), behind one iterator.

use std::path::{Path, PathBuf};
use std::str::FromStr;

use cloud::PointCloud;
use nalgebra::Isometry3;
use sim::{Scenario, SimConfig, SimError, Simulator, UnknownScenario};

use crate::recording::{self, RecordingError, RecordingOptions};

/// A scan source named on the command line.
#[derive(Clone, Debug, PartialEq)]
pub enum SourceSpec {
    /// `sim:SCENARIO:ROBOT` (robot ids start at 1; `sim:SCENARIO` is robot 1).
    Sim {
        /// Scenario name.
        scenario: String,
        /// Robot id, 1-based.
        robot: u32,
    },
    /// A directory of scans, a `.bag` or an `.mcap` file.
    Recording(PathBuf),
}

/// A source specification that cannot be understood.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("invalid source {input:?}: {reason}")]
pub struct InvalidSource {
    /// What was given.
    pub input: String,
    /// Why it is not a source.
    pub reason: String,
}

impl std::fmt::Display for SourceSpec {
    /// As it is written on the command line.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SourceSpec::Sim { scenario, robot } => write!(f, "sim:{scenario}:{robot}"),
            SourceSpec::Recording(path) => write!(f, "{}", path.display()),
        }
    }
}

impl FromStr for SourceSpec {
    type Err = InvalidSource;

    fn from_str(s: &str) -> Result<Self, InvalidSource> {
        let Some(rest) = s.strip_prefix("sim:") else { return Ok(SourceSpec::Recording(PathBuf::from(s))) };
        let invalid = |reason: &str| InvalidSource { input: s.to_owned(), reason: reason.to_owned() };
        let (scenario, robot) = match rest.split_once(':') {
            Some((name, id)) => {
                (name, id.parse::<u32>().ok().filter(|r| *r >= 1).ok_or_else(|| invalid("robot ids are 1, 2, ..."))?)
            }
            None => (rest, 1),
        };
        if scenario.is_empty() {
            return Err(invalid("expected sim:SCENARIO:ROBOT, e.g. sim:warehouse-small:1"));
        }
        Ok(SourceSpec::Sim { scenario: scenario.to_owned(), robot })
    }
}

/// One sweep from any source.
#[derive(Clone, Debug)]
pub struct SourceScan {
    /// Points with whatever channels the source has (the simulator: intensity, ring, time).
    pub cloud: PointCloud,
    /// Sweep start, seconds.
    pub stamp: f64,
    /// Position in the source, 0-based.
    pub index: usize,
    /// Ground-truth sensor pose at the sweep end, in the world frame, when the source knows it.
    pub ground_truth: Option<Isometry3<f64>>,
}

/// Why a source could not be opened or read.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// The scenario name is unknown (the message lists the valid ones).
    #[error(transparent)]
    Scenario(#[from] UnknownScenario),
    /// The simulator refused its settings or robot.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// A recording could not be opened or read.
    #[error(transparent)]
    Recording(#[from] RecordingError),
}

impl SourceError {
    /// True when reading cannot go on after this error (a bad message is not fatal, a cut file is).
    pub fn is_fatal(&self) -> bool {
        match self {
            SourceError::Recording(e) => e.is_fatal(),
            _ => true,
        }
    }
}

/// An open source: an iterator of scans.
pub struct Source {
    inner: Inner,
    /// How many scans the source will give, when known in advance.
    pub len: Option<usize>,
    limit: Option<usize>,
    given: usize,
}

enum Inner {
    Sim { sim: Box<Simulator>, next: usize },
    Recording(Box<recording::Recording>),
}

impl Source {
    /// Opens a source; `frames` caps the number of scans, `sim` configures simulated sensors and
    /// `options` recordings (rings and times are derived there when a recording lacks them).
    pub fn open(
        spec: &SourceSpec,
        frames: Option<usize>,
        sim: &SimConfig,
        options: &RecordingOptions,
    ) -> Result<Self, SourceError> {
        match spec {
            SourceSpec::Sim { scenario, robot } => {
                let scenario = Scenario::by_name(scenario)?;
                let sim = Simulator::new(scenario, *robot as usize - 1, sim.clone())?;
                let len = frames.unwrap_or(sim.frames());
                Ok(Source {
                    inner: Inner::Sim { sim: Box::new(sim), next: 0 },
                    len: Some(len),
                    limit: Some(len),
                    given: 0,
                })
            }
            SourceSpec::Recording(path) => {
                let rec = recording::open(path, options)?;
                let len = match (frames, directory_len(path)) {
                    (Some(f), Some(n)) => Some(f.min(n)),
                    (f, n) => f.or(n),
                };
                Ok(Source { inner: Inner::Recording(Box::new(rec)), len, limit: frames, given: 0 })
            }
        }
    }
}

/// Scans in a directory source (known up front, for progress bars).
fn directory_len(path: &Path) -> Option<usize> {
    let dir = if path.join("velodyne").is_dir() { path.join("velodyne") } else { path.to_owned() };
    let n = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| e.ok())
        .filter(|e| {
            e.path()
                .extension()
                .and_then(|x| x.to_str())
                .is_some_and(|x| ["bin", "pcd", "ply"].contains(&x.to_ascii_lowercase().as_str()))
        })
        .count();
    (n > 0).then_some(n)
}

impl Iterator for Source {
    type Item = Result<SourceScan, SourceError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.limit.is_some_and(|l| self.given >= l) {
            return None;
        }
        let item = match &mut self.inner {
            Inner::Sim { sim, next } => {
                let s = sim.scan(*next);
                *next += 1;
                Ok(SourceScan { cloud: s.cloud, stamp: s.stamp, index: s.frame, ground_truth: Some(s.ground_truth) })
            }
            Inner::Recording(rec) => rec
                .next()?
                .map(|s| SourceScan { cloud: s.cloud, stamp: s.stamp, index: s.index, ground_truth: None })
                .map_err(SourceError::from),
        };
        self.given += item.is_ok() as usize;
        Some(item)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_sim_and_recording_specs() {
        assert_eq!("sim:campus:3".parse(), Ok(SourceSpec::Sim { scenario: "campus".into(), robot: 3 }));
        assert_eq!("sim:aisles".parse(), Ok(SourceSpec::Sim { scenario: "aisles".into(), robot: 1 }));
        assert_eq!("data/run.bag".parse(), Ok(SourceSpec::Recording("data/run.bag".into())));
        assert!("sim:campus:0".parse::<SourceSpec>().is_err());
        assert!("sim:campus:x".parse::<SourceSpec>().is_err());
        assert!("sim:".parse::<SourceSpec>().is_err());
    }

    #[test]
    fn sim_source_gives_ground_truth_and_stops() {
        let spec: SourceSpec = "sim:aisles:2".parse().unwrap();
        let scans: Vec<_> = Source::open(&spec, Some(3), &SimConfig::default(), &RecordingOptions::default())
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(scans.len(), 3);
        assert!(scans.iter().all(|s| s.ground_truth.is_some() && s.cloud.ring.is_some()));
        let err =
            Source::open(&"sim:aisles:3".parse().unwrap(), None, &SimConfig::default(), &RecordingOptions::default());
        assert!(err.err().unwrap().to_string().contains("has 2 robots"));
    }
}
