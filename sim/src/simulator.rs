//! The scan generator: fires every ray of a sweep from the sensor pose at its own firing time.

use cloud::voxel::{InvalidVoxelSize, downsample};
use cloud::{Channels, PointCloud};
use nalgebra::{Isometry3, Point3, Vector3};
use rayon::prelude::*;
use rustc_hash::FxHashMap;

use crate::geometry::Ray;
use crate::noise::SplitMix;
use crate::scenario::Scenario;
use crate::sensor::SensorModel;
use crate::spin::SpinInPlace;
use crate::trajectory::Trajectory;

/// Simulator settings.
#[derive(Clone, Debug, PartialEq)]
pub struct SimConfig {
    /// Seed of every random draw (noise, dropouts). Default 0.
    pub seed: u64,
    /// The LiDAR. Default [`SensorModel::vlp16`].
    pub sensor: SensorModel,
    /// Standard deviation of the Gaussian range noise, metres. Default 0.01 (1 cm), a little
    /// better than the VLP-16's ±3 cm datasheet accuracy, which bounds the error rather than its
    /// standard deviation.
    pub range_noise: f64,
    /// Probability that a ray which hits a surface returns nothing. Default 0.01: real sensors lose
    /// a few returns on dark or shiny surfaces, and consumers must not assume a complete grid.
    pub dropout: f64,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self { seed: 0, sensor: SensorModel::vlp16(), range_noise: 0.01, dropout: 0.01 }
    }
}

/// Why a simulator cannot be set up.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SimError {
    /// The robot index is out of range (reported as 1-based robot ids, as users number robots).
    #[error("scenario {scenario} has {robots} robots (1 to {robots}); there is no robot {}", .robot + 1)]
    NoSuchRobot {
        /// Scenario name.
        scenario: String,
        /// How many robots it has.
        robots: usize,
        /// The index asked for.
        robot: usize,
    },
    /// A setting out of its valid range.
    #[error("invalid simulator setting: {0}")]
    BadConfig(String),
}

/// One simulated sweep.
#[derive(Clone, Debug, PartialEq)]
pub struct Scan {
    /// Frame index (0-based).
    pub frame: usize,
    /// Points in the sensor frame at each point's own firing time, with intensity (0..1), ring
    /// (0 = lowest beam) and time (seconds since `stamp`); in firing order, column by column.
    pub cloud: PointCloud,
    /// Sweep start, seconds on the scenario clock.
    pub stamp: f64,
    /// Sensor pose in the world frame at the end of the sweep (`stamp + period`).
    pub ground_truth: Isometry3<f64>,
}

/// One sweep as the sensor measured it, before the ranges became points: what a LiDAR puts in its
/// packets. Cell (column, beam) holds the return of beam `beam` (0 = lowest) fired in column
/// `column`; its point in [`Scan::cloud`] is `range · SensorModel::direction_at(beam, column, stamp)`.
#[derive(Clone, Debug, PartialEq)]
pub struct RangeImage {
    /// Frame index (0-based).
    pub frame: usize,
    /// Sweep start, seconds on the scenario clock (as [`Scan::stamp`]).
    pub stamp: f64,
    /// Beams per column.
    pub beams: usize,
    /// Seconds from `stamp` at which each column fires (all its beams at once).
    pub column_times: Vec<f64>,
    /// Column-major cells: `cells[column * beams + beam]`.
    cells: Vec<Option<RangeReturn>>,
}

/// One return of a [`RangeImage`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RangeReturn {
    /// Metres along the beam from the sensor origin, noise included.
    pub range: f64,
    /// As the cloud's intensity channel: `reflectivity · |cos(incidence)|`, 0..1.
    pub intensity: f32,
}

impl RangeImage {
    /// Columns of the sweep.
    pub fn columns(&self) -> usize {
        self.column_times.len()
    }

    /// The return of `beam` in `column`; `None` where the ray returned nothing or the cell does not
    /// exist.
    pub fn get(&self, column: usize, beam: usize) -> Option<RangeReturn> {
        if beam >= self.beams {
            return None;
        }
        self.cells.get(column * self.beams + beam).copied().flatten()
    }

    /// Returns in the image.
    pub fn returns(&self) -> usize {
        self.cells.iter().flatten().count()
    }
}

/// One return, before assembly into the cloud.
#[derive(Clone, Copy, Debug)]
struct Sample {
    point: [f32; 3],
    range: f64,
    intensity: f32,
}

/// Simulates one robot's LiDAR in a scenario.
#[derive(Clone, Debug)]
pub struct Simulator {
    scenario: Scenario,
    robot: usize,
    config: SimConfig,
    /// A turn in place that replaces the robot's route, see [`Simulator::spinning`].
    spin: Option<SpinInPlace>,
    /// (sin, cos) of each beam's elevation.
    elevations: Vec<(f64, f64)>,
    /// (sin, cos) of each column's azimuth.
    azimuths: Vec<(f64, f64)>,
}

impl Simulator {
    /// A simulator for robot `robot` (0-based) of `scenario`.
    pub fn new(scenario: Scenario, robot: usize, config: SimConfig) -> Result<Simulator, SimError> {
        let robots = scenario.robots().len();
        if robot >= robots {
            return Err(SimError::NoSuchRobot { scenario: scenario.name().to_owned(), robots, robot });
        }
        check(&config)?;
        let sensor = &config.sensor;
        let elevations = sensor.elevations.iter().map(|e| e.sin_cos()).collect();
        let azimuths = (0..sensor.columns).map(|c| sensor.azimuth(c).sin_cos()).collect();
        Ok(Simulator { scenario, robot, config, spin: None, elevations, azimuths })
    }

    /// The same robot standing still and turning in place as `spin` says, instead of driving its
    /// route: the sweeps, their ground truth and [`Simulator::pose_at`] follow the spin (the noise
    /// streams stay those of the robot).
    pub fn spinning(self, spin: SpinInPlace) -> Simulator {
        Simulator { spin: Some(spin), ..self }
    }

    /// The scenario.
    pub fn scenario(&self) -> &Scenario {
        &self.scenario
    }

    /// The robot index.
    pub fn robot(&self) -> usize {
        self.robot
    }

    /// The settings.
    pub fn config(&self) -> &SimConfig {
        &self.config
    }

    /// The robot's route (not followed while [`spinning`](Simulator::spinning)).
    pub fn trajectory(&self) -> &Trajectory {
        &self.scenario.robots()[self.robot]
    }

    /// Number of sweeps in the scenario at this sensor's rate.
    pub fn frames(&self) -> usize {
        let seconds = self.scenario.frames() as f64 / super::scenario::FRAME_RATE;
        (seconds / self.config.sensor.period).round() as usize
    }

    /// Sweep start of frame `frame`, seconds.
    pub fn stamp(&self, frame: usize) -> f64 {
        frame as f64 * self.config.sensor.period
    }

    /// Ground-truth sensor pose in the world frame at time `t`.
    pub fn pose_at(&self, t: f64) -> Isometry3<f64> {
        match &self.spin {
            Some(spin) => spin.pose(self.scenario.world().terrain(), t),
            None => self.trajectory().pose(t),
        }
    }

    /// Ground truth of frame `frame`: the sensor pose at the end of its sweep.
    pub fn ground_truth(&self, frame: usize) -> Isometry3<f64> {
        self.pose_at(self.stamp(frame) + self.config.sensor.period)
    }

    /// Simulates sweep `frame` (any index; past the scenario's end the robot is parked).
    pub fn scan(&self, frame: usize) -> Scan {
        self.scan_of(frame, &self.samples(frame))
    }

    /// Sweep `frame` as a range image: the same rays, noise and dropouts as [`Simulator::scan`]
    /// gives for the frame, before they become points.
    pub fn range_image(&self, frame: usize) -> RangeImage {
        self.range_image_of(frame, &self.samples(frame))
    }

    /// Sweep `frame` both as a cloud and as a range image, its rays cast once.
    pub fn scan_and_range_image(&self, frame: usize) -> (Scan, RangeImage) {
        let samples = self.samples(frame);
        (self.scan_of(frame, &samples), self.range_image_of(frame, &samples))
    }

    /// Every ray of sweep `frame`, column by column.
    fn samples(&self, frame: usize) -> Vec<Option<Sample>> {
        let sensor = &self.config.sensor;
        let stamp = self.stamp(frame);
        let mut samples = vec![None; sensor.rays_per_scan()];
        samples
            .par_chunks_mut(sensor.beams())
            .enumerate()
            .for_each(|(column, out)| self.fire_column(frame, column, stamp, out));
        samples
    }

    fn scan_of(&self, frame: usize, samples: &[Option<Sample>]) -> Scan {
        Scan { frame, cloud: self.assemble(samples), stamp: self.stamp(frame), ground_truth: self.ground_truth(frame) }
    }

    fn range_image_of(&self, frame: usize, samples: &[Option<Sample>]) -> RangeImage {
        let sensor = &self.config.sensor;
        RangeImage {
            frame,
            stamp: self.stamp(frame),
            beams: sensor.beams(),
            column_times: (0..sensor.columns).map(|c| sensor.firing_time(c)).collect(),
            cells: samples.iter().map(|s| s.map(|s| RangeReturn { range: s.range, intensity: s.intensity })).collect(),
        }
    }

    /// All sweeps of the scenario, in order.
    pub fn scans(&self) -> impl Iterator<Item = Scan> + '_ {
        (0..self.frames()).map(|f| self.scan(f))
    }

    /// The map a perfect odometry would make: every `stride`-th sweep, each point placed by the
    /// exact pose at its own firing time, expressed in the sensor frame at t = 0 (`pose_at(0.0)`
    /// in the world), voxel-downsampled per sweep and as a whole. Ground truth for map merging.
    pub fn exact_map(&self, stride: usize, voxel: f32) -> Result<PointCloud, InvalidVoxelSize> {
        let frames: Vec<usize> = (0..self.frames()).step_by(stride.max(1)).collect();
        self.exact_map_of(&frames, voxel)
    }

    /// [`Self::exact_map`] of the given sweeps only (e.g. the map of a run so far).
    pub fn exact_map_of(&self, frames: &[usize], voxel: f32) -> Result<PointCloud, InvalidVoxelSize> {
        let to_map = self.pose_at(0.0).inverse();
        let sweeps = frames
            .par_iter()
            .map(|&f| downsample(&PointCloud::from_points(self.undistorted(&self.scan(f), &to_map)), voxel))
            .collect::<Result<Vec<PointCloud>, _>>()?;
        downsample(&PointCloud::from_points(sweeps.into_iter().flat_map(|s| s.points).collect()), voxel)
    }

    /// `scan`'s points free of motion distortion, in the sensor frame at the end of its sweep (the
    /// frame of [`Scan::ground_truth`]): what a perfect deskewing gives.
    pub fn deskewed(&self, scan: &Scan) -> PointCloud {
        PointCloud::from_points(self.undistorted(scan, &scan.ground_truth.inverse()))
    }

    /// `scan`'s points, each moved from the sensor pose at its firing time into the frame that
    /// `to_frame` maps the world into.
    fn undistorted(&self, scan: &Scan, to_frame: &Isometry3<f64>) -> Vec<Point3<f32>> {
        let times = scan.cloud.time.as_deref().unwrap_or_default();
        // Points of one column share a firing time: one pose per column.
        let mut poses: FxHashMap<u32, Isometry3<f32>> = FxHashMap::default();
        scan.cloud
            .points
            .iter()
            .zip(times)
            .map(|(p, &t)| {
                let pose = poses
                    .entry(t.to_bits())
                    .or_insert_with(|| (to_frame * self.pose_at(scan.stamp + f64::from(t))).cast::<f32>());
                *pose * p
            })
            .collect()
    }

    /// Fires every beam of one column from the sensor pose at the column's firing time.
    fn fire_column(&self, frame: usize, column: usize, stamp: f64, out: &mut [Option<Sample>]) {
        let sensor = &self.config.sensor;
        let pose = self.pose_at(stamp + sensor.firing_time(column));
        let rotation = pose.rotation.to_rotation_matrix();
        let origin = Point3::from(pose.translation.vector);
        let (sa, ca) = self.azimuths[column];
        for (beam, slot) in out.iter_mut().enumerate() {
            let local = if sensor.has_rings() {
                let (se, ce) = self.elevations[beam];
                Vector3::new(ce * ca, ce * sa, se)
            } else {
                sensor.direction_at(beam, column, stamp)
            };
            let ray = Ray::new(origin, rotation * local);
            let key = (frame as u64, (column * sensor.beams() + beam) as u64);
            *slot = self.measure(&ray, &local, key);
        }
    }

    /// The return of one ray: true range plus noise, unless it misses, drops out or falls outside
    /// the sensor's range window. The point is `range · direction` in the sensor frame.
    fn measure(&self, ray: &Ray, local: &Vector3<f64>, (frame, index): (u64, u64)) -> Option<Sample> {
        let sensor = &self.config.sensor;
        let world = self.scenario.world();
        let hit = world.cast(ray, sensor.max_range)?;
        let mut rng = SplitMix::for_ray(self.config.seed, self.robot as u64, frame, index);
        let dropped = rng.chance(self.config.dropout);
        let range = hit.hit.t + self.config.range_noise * rng.gaussian();
        if dropped || range < sensor.min_range || range > sensor.max_range {
            return None;
        }
        let p = local * range;
        let reflectivity = world.objects()[hit.object as usize].reflectivity;
        let incidence = hit.hit.normal.dot(&ray.direction).abs() as f32;
        Some(Sample { point: [p.x as f32, p.y as f32, p.z as f32], range, intensity: reflectivity * incidence })
    }

    /// The returns in firing order as a cloud with intensity, ring and time channels (no ring
    /// channel for a sensor without rings).
    fn assemble(&self, samples: &[Option<Sample>]) -> PointCloud {
        let sensor = &self.config.sensor;
        let count = samples.iter().flatten().count();
        let mut cloud = PointCloud::with_capacity(count, Channels { intensity: true, ring: true, time: true });
        let (Some(intensity), Some(ring), Some(time)) = (&mut cloud.intensity, &mut cloud.ring, &mut cloud.time) else {
            return cloud;
        };
        for (i, s) in samples.iter().enumerate() {
            let Some(s) = s else { continue };
            let (column, beam) = (i / sensor.beams(), i % sensor.beams());
            cloud.points.push(Point3::from(s.point));
            intensity.push(s.intensity);
            ring.push(beam as u16);
            time.push(sensor.firing_time(column) as f32);
        }
        if !sensor.has_rings() {
            cloud.ring = None;
        }
        cloud
    }
}

/// Rejects settings the simulator cannot honour.
fn check(c: &SimConfig) -> Result<(), SimError> {
    let s = &c.sensor;
    let problem = if !(c.range_noise >= 0.0 && c.range_noise.is_finite()) {
        Some(format!("range noise {} m must be finite and not negative", c.range_noise))
    } else if !(0.0..=1.0).contains(&c.dropout) {
        Some(format!("dropout probability {} must lie in [0, 1]", c.dropout))
    } else if s.elevations.is_empty() || s.columns == 0 {
        Some("the sensor needs at least one beam and one column".to_owned())
    } else if s.elevations.len() > usize::from(u16::MAX) {
        Some(format!("{} beams do not fit the u16 ring channel", s.elevations.len()))
    } else if s.period <= 0.0 || !s.period.is_finite() || s.min_range < 0.0 || s.max_range <= s.min_range {
        Some("sensor period must be positive and 0 <= min_range < max_range".to_owned())
    } else {
        None
    };
    problem.map_or(Ok(()), |p| Err(SimError::BadConfig(p)))
}
