//! Simulated multi-robot LiDAR worlds: the default scan source of the demo and the tests, with
//! exact ground truth.
//!
//! A [`World`] is a set of analytic primitives (boxes, optionally turned about the vertical,
//! vertical cylinders, spheres, triangles, unbounded planes) with a binned-SAH [`bvh`] for ray
//! casting. A [`Scenario`] puts robots on smooth [`Trajectory`]s through a world; a [`Simulator`]
//! turns one robot's motion into LiDAR sweeps, or, [`spinning`](Simulator::spinning), a robot
//! turning in place ([`SpinInPlace`]). [`packets`] sends the sweeps as a real sensor would: as a
//! VLP-16's or an Ouster's UDP packets, into a pcap capture or to a loopback address.
//!
//! ```no_run
//! use sim::{Scenario, SimConfig, Simulator};
//! let scenario = Scenario::by_name("warehouse-small")?;
//! let sim = Simulator::new(scenario, 0, SimConfig { seed: 7, ..SimConfig::default() })?;
//! for scan in sim.scans().take(10) {
//!     println!("{} points, truth {}", scan.cloud.len(), scan.ground_truth.translation.vector);
//! }
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
//!
//! # Conventions
//!
//! - **Frames.** World: x east, y north, z up, metres. Sensor: x forward, y left, z up, the robot's
//!   heading projected onto the ground, `mount_height` above the ground along its normal.
//! - **Clock.** All robots of a scenario share one clock starting at 0. Scan `k` covers
//!   `[t_k, t_k + period)` with `t_k = k · period`; [`Scan::stamp`] is `t_k` (the sweep start).
//! - **Firing times.** Column `c` of `C` fires at `t_k + c/C · period`, azimuth `π − 2π·c/C` (the
//!   head spins clockwise from the back, as Velodynes do); a point's `time` channel is its firing
//!   time minus `t_k`, its `ring` the beam index (0 = lowest).
//! - **Motion distortion.** Each ray is cast from the sensor pose at its own firing time, and the
//!   point is expressed in the sensor frame *at that time* (`range · beam direction`), as a real
//!   spinning LiDAR reports it: a moving robot gets skewed sweeps.
//! - **Ground truth.** [`Scan::ground_truth`] is the world-frame sensor pose at the **end** of the
//!   sweep, `t_k + period`: the frame in which motion-compensated odometry (F-LOAM eq. 3) expresses
//!   a de-skewed scan. [`Simulator::pose_at`] gives the pose at any time. Files written by
//!   [`write_kitti`] re-base the poses so the first is the identity (`T_0⁻¹ · T_k`).
//! - **Noise.** Range noise is Gaussian along the ray (default σ = 1 cm); a hit is dropped with
//!   probability `dropout`; returns outside `[min_range, max_range]` are discarded. Intensity is
//!   `reflectivity · |cos(incidence)|` in 0..1, noise-free.
//! - **Determinism.** Every ray draws from its own SplitMix64 stream keyed by (seed, robot, frame,
//!   ray index), so a seed gives bit-identical sweeps with any number of threads.
//! - **Limits.** Robots do not see each other; worlds are static; beams of a column fire at the
//!   same instant; there are no multi-path or mixed-pixel returns.

pub mod bvh;
pub mod export;
pub mod geometry;
pub mod maps;
pub mod noise;
pub mod packets;
pub mod scenario;
pub mod sensor;
pub mod simulator;
pub mod spin;
pub mod svg;
pub mod trajectory;
pub mod world;
pub mod worlds;

pub use export::{ExportError, Written, write_kitti, write_kitti_from};
pub use geometry::{Aabb, Cuboid, Cylinder, Hit, Object, Plane, Ray, Shape, Sphere, Triangle};
pub use maps::{MapsError, RobotMaps};
pub use scenario::{CATALOG, FRAME_RATE, Scenario, ScenarioInfo, UnknownScenario, scenario_names};
pub use sensor::{SensorKind, SensorModel, UnknownSensor};
pub use simulator::{RangeImage, RangeReturn, Scan, SimConfig, SimError, Simulator};
pub use spin::SpinInPlace;
pub use trajectory::{Trajectory, TrajectoryConfig, TrajectoryError};
pub use world::{Terrain, Wave, World, WorldHit};
