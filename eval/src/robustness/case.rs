//! The cases of the matrix and their builders: real KITTI scans every k-th, simulated runs, and
//! either with its points shuffled.

use std::path::{Path, PathBuf};

use cloud::Preset;
use cloud::trajectory::{Trajectory, TrajectoryError};
use nalgebra::Point2;
use sim::noise::SplitMix;
use sim::{Scenario, SensorKind, SimConfig, SimError, Simulator, SpinInPlace, TrajectoryConfig, UnknownScenario};

use edge::odometry::OdometryConfig;
use edge::odometry::pipeline::{self, recording_options};
use edge::recording::{self, RecordingError};
use edge::source::{SourceError, SourceScan};

/// One hard input: scans with their ground truth, and how the odometry is to be set up for them.
#[derive(Clone, Debug)]
pub struct Case {
    /// Short unique name (the table's first column, what `--case` matches).
    pub name: String,
    /// The class of hard input it stands for: `every-k`, `car`, `spin`, `rate`, `sensor`, `shuffled`.
    pub class: String,
    /// The scans in order, each with `ground_truth: Some(world pose of the sensor at sweep end)`.
    pub scans: Vec<SourceScan>,
    /// The odometry preset.
    pub preset: Preset,
    /// Seconds per sweep (the sensor's revolution), not between scans: every k-th scan of a 10 Hz
    /// sensor still sweeps in 0.1 s.
    pub scan_period: f32,
    /// Motion compensation, for ours and KISS-ICP alike: off for KITTI, whose scans are published
    /// already compensated.
    pub deskew: bool,
    /// Ring and time channels a scan lacks are derived before our odometry sees it, as
    /// `emr-edge odometry` derives them for a recording ([`pipeline::recording_options`]); when
    /// false the scans reach the odometry as they are.
    pub derive_channels: bool,
}

impl Case {
    /// The ground-truth poses, world frame.
    pub fn truth(&self) -> Vec<nalgebra::Isometry3<f64>> {
        self.scans.iter().filter_map(|s| s.ground_truth).collect()
    }
}

/// Why a case could not be built.
#[derive(Debug, thiserror::Error)]
pub enum CaseError {
    /// The scans could not be read.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// A KITTI directory could not be opened.
    #[error(transparent)]
    Recording(#[from] RecordingError),
    /// The ground-truth file cannot be read.
    #[error("cannot read {}", path.display())]
    ReadTruth { path: PathBuf, source: std::io::Error },
    /// The ground-truth file is not a KITTI pose file.
    #[error("{}", path.display())]
    ParseTruth { path: PathBuf, source: TrajectoryError },
    /// A scan without a ground-truth pose.
    #[error("{}: no pose for scan {index}", path.display())]
    NoTruth { path: PathBuf, index: usize },
    /// The scenario is unknown.
    #[error(transparent)]
    Scenario(#[from] UnknownScenario),
    /// The simulator refused its settings.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// The simulated motion cannot be built.
    #[error(transparent)]
    Motion(#[from] sim::TrajectoryError),
    /// Nothing to register: the selection is empty.
    #[error("the case has no scans")]
    Empty,
}

/// Scans `start`, `start + every`, ... of a KITTI sequence directory (DIR/velodyne/NNNNNN.bin,
/// DIR/times.txt, DIR/poses_velodyne.txt), read as the odometry reads recordings (rings from the
/// scan order, times from azimuth), with the poses of DIR/poses_velodyne.txt as ground truth and
/// the stamps of DIR/times.txt. Scans are counted in file-name order, which is KITTI's index.
pub fn kitti_every(dir: &Path, start: usize, every: usize) -> Result<Case, CaseError> {
    let every = every.max(1);
    let truth_path = dir.join("poses_velodyne.txt");
    let truth = read_truth(&truth_path)?;
    let options = recording_options(Default::default(), &OdometryConfig::preset(Preset::Outdoor));
    let mut scans = Vec::new();
    for scan in recording::open(dir, &options)? {
        let scan = scan?;
        if !picked(scan.index, start, every) {
            continue;
        }
        let pose = truth.poses.get(scan.index).copied();
        let pose = pose.ok_or_else(|| CaseError::NoTruth { path: truth_path.clone(), index: scan.index })?;
        scans.push(SourceScan {
            cloud: scan.cloud,
            stamp: scan.stamp,
            index: scan.index,
            ground_truth: Some(pose),
            gaps: 0,
            partial: false,
            dropped_before: 0,
        });
    }
    non_empty(Case {
        name: format!("kitti-{start}-every-{every}"),
        class: "every-k".into(),
        scans,
        preset: Preset::Outdoor,
        scan_period: 0.1,
        deskew: false,
        derive_channels: true,
    })
}

/// Whether scan `index` is one of `start`, `start + every`, ...
fn picked(index: usize, start: usize, every: usize) -> bool {
    index >= start && (index - start).is_multiple_of(every)
}

/// A KITTI pose file.
fn read_truth(path: &Path) -> Result<Trajectory, CaseError> {
    let text =
        std::fs::read_to_string(path).map_err(|source| CaseError::ReadTruth { path: path.to_owned(), source })?;
    Trajectory::parse_kitti(&text).map_err(|source| CaseError::ParseTruth { path: path.to_owned(), source })
}

/// The case, unless it has no scans.
fn non_empty(case: Case) -> Result<Case, CaseError> {
    if case.scans.is_empty() { Err(CaseError::Empty) } else { Ok(case) }
}

/// How the simulated sensor moves.
#[derive(Clone, Debug, PartialEq)]
pub enum Motion {
    /// Robot `robot` (0-based) of a built-in scenario, along its route.
    Route {
        /// Scenario name.
        scenario: String,
        /// Robot index, 0-based.
        robot: usize,
    },
    /// A car on the campus roads at `speed` m/s on the straights, already at speed at the first
    /// scan ([`Scenario::campus_car`]).
    Car {
        /// Cruise speed, m/s.
        speed: f64,
    },
    /// Standing at `at` (x, y) in a scenario's world and turning in place at `deg_per_s` from the
    /// first scan on ([`SpinInPlace`]).
    Spin {
        /// Scenario whose world it stands in.
        scenario: String,
        /// Where it stands, world x and y.
        at: [f64; 2],
        /// Yaw rate, degrees per second.
        deg_per_s: f64,
    },
}

/// A simulated case: a motion, a sensor at a rate, and which sweeps become scans.
#[derive(Clone, Debug, PartialEq)]
pub struct SimCase {
    /// How the sensor moves. Default robot 0 of `warehouse-small` along its route.
    pub motion: Motion,
    /// The LiDAR. Default VLP-16.
    pub sensor: SensorKind,
    /// Revolutions per second. Default 10.
    pub rate_hz: f64,
    /// Time of the first scan's sweep start, seconds from the scenario start: mid-run, the
    /// odometry starts with no prior on a moving robot. Default 40.
    pub start_s: f64,
    /// Every k-th sweep is a scan. Default 1.
    pub every: usize,
    /// Scans in the case. Default 150.
    pub scans: usize,
    /// The odometry preset. Default indoor.
    pub preset: Preset,
    /// Noise and dropout seed. Default 0.
    pub seed: u64,
    /// The scans written already compensated, as KITTI publishes its scans: every point moved to
    /// where the sensor stands at the sweep's end (the simulator's exact deskewing), rings kept,
    /// per-point times dropped. Default false (the sensor's raw sweeps).
    pub compensated: bool,
}

impl Default for SimCase {
    fn default() -> Self {
        SimCase {
            motion: Motion::Route { scenario: "warehouse-small".into(), robot: 0 },
            sensor: SensorKind::Vlp16,
            rate_hz: 10.0,
            start_s: 40.0,
            every: 1,
            scans: 150,
            preset: Preset::Indoor,
            seed: 0,
            compensated: false,
        }
    }
}

/// The simulated case: `spec.scans` sweeps of the sensor at `spec.rate_hz`, every `spec.every`-th
/// from the one starting at `spec.start_s`, with the simulator's exact ground truth.
pub fn simulated(spec: &SimCase) -> Result<Case, CaseError> {
    let sim = simulator(spec)?;
    let first = (spec.start_s * spec.rate_hz).round() as usize;
    let frames = (0..spec.scans).map(|i| first + i * spec.every.max(1));
    let scans = frames.map(|f| sim.scan(f)).map(|scan| {
        if spec.compensated {
            let points = sim.deskewed(&scan).points;
            let cloud = cloud::PointCloud { points, time: None, ..scan.cloud.clone() };
            SourceScan::from(sim::Scan { cloud, ..scan })
        } else {
            SourceScan::from(scan)
        }
    });
    let scans = scans.collect();
    non_empty(Case {
        name: format!("sim-{}-{}hz-every-{}", spec.sensor, spec.rate_hz, spec.every),
        class: "sim".into(),
        scans,
        preset: spec.preset,
        scan_period: (1.0 / spec.rate_hz) as f32,
        deskew: true,
        derive_channels: true,
    })
}

/// The simulator `spec` describes.
fn simulator(spec: &SimCase) -> Result<Simulator, CaseError> {
    let sensor = spec.sensor.model().at_rate(spec.rate_hz);
    let config = SimConfig { seed: spec.seed, sensor, ..SimConfig::default() };
    match &spec.motion {
        Motion::Route { scenario, robot } => Ok(Simulator::new(Scenario::by_name(scenario)?, *robot, config)?),
        Motion::Car { speed } => Ok(Simulator::new(Scenario::campus_car(*speed)?, 0, config)?),
        Motion::Spin { scenario, at, deg_per_s } => {
            // The sensor as high as on the scenarios' robots.
            let mount_height = TrajectoryConfig::default().mount_height;
            let spin =
                SpinInPlace { position: Point2::from(*at), heading: 0.0, rate: deg_per_s.to_radians(), mount_height };
            Ok(Simulator::new(Scenario::by_name(scenario)?, 0, config)?.spinning(spin))
        }
    }
}

/// `case` with every scan's points in a random order (seeded) and its ring and time channels
/// removed: a recording that keeps neither the firing order nor per-point times. Positions and
/// intensities are kept.
pub fn shuffled(case: Case, seed: u64) -> Case {
    let mut rng = SplitMix::new(seed);
    let scans = case.scans.into_iter().map(|s| SourceScan { cloud: shuffle(&s.cloud, &mut rng), ..s }).collect();
    Case { name: format!("{}-shuffled", case.name), class: "shuffled".into(), scans, ..case }
}

/// The points of `cloud` permuted (Fisher-Yates), without ring and time channels.
fn shuffle(cloud: &cloud::PointCloud, rng: &mut SplitMix) -> cloud::PointCloud {
    let mut order: Vec<usize> = (0..cloud.len()).collect();
    for i in (1..order.len()).rev() {
        let j = ((rng.uniform() * (i + 1) as f64) as usize).min(i);
        order.swap(i, j);
    }
    let mut out = cloud.select(&order);
    out.ring = None;
    out.time = None;
    out
}

/// The scans as the odometry is to see them: channels derived where the case asks for it.
pub(super) fn prepared(case: &Case) -> Vec<SourceScan> {
    let config = OdometryConfig { scan_period: case.scan_period, ..OdometryConfig::preset(case.preset) };
    let options = pipeline::recording_options(Default::default(), &config);
    let mut scans = case.scans.clone();
    if case.derive_channels {
        let mut channels = recording::ChannelDeriver::new(options);
        scans.iter_mut().for_each(|s| channels.derive(&mut s.cloud));
    }
    scans
}
