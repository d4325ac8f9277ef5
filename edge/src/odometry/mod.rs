//! F-LOAM odometry (Wang et al., IROS 2021, section III) with the paper's two-stage distortion
//! compensation. One call per scan, in [`Odometry::register`]:
//!
//! 1. features: per-ring smoothness (eq. 1), 6 sectors, edges and planes ([`features`]);
//! 2. stage 1: constant-velocity motion from the last frame (eq. 2) moves each feature to the sweep
//!    end by its own timestamp (eq. 3) ([`deskew`]);
//! 3. pose: scan-to-local-map point-to-line / point-to-plane matching (eq. 4) ([`solver`]);
//! 4. stage 2: the distortion is recomputed with the estimated motion and the features are corrected
//!    again before they enter the map;
//! 5. local map: edge and plane voxel maps cropped around the robot, k-d trees ([`local_map`]);
//! 6. keyframes every N metres or M degrees, carrying the deskewed, downsampled cloud.
//!
//! Poses are those of the sensor at the END of each sweep, in the odometry frame (the sensor frame at
//! the end of the first sweep).

pub mod deskew;
pub mod features;
pub mod local_map;
pub mod solver;
pub mod stats;

use cloud::PointCloud;
use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

use deskew::SweepMotion;
use features::{FeatureError, Features};
use local_map::{FeatureMap, MAX_POINTS_PER_VOXEL, ScanLine};

/// Feature extraction parameters (F-LOAM's reference values unless noted).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct FeatureConfig {
    /// Points closer than this (m) are dropped: the robot itself, dust. Default 0.5 m indoor, 2 m outdoor.
    pub min_range: f32,
    /// Points farther than this (m) are dropped. Default 100 m.
    pub max_range: f32,
    /// Neighbours on each side for the smoothness (eq. 1). Default 5.
    pub neighbours: usize,
    /// Sectors per ring, so features spread around the sensor. Default 6.
    pub sectors: usize,
    /// Smoothness above which a point may become an edge. Default 0.1 (m²).
    pub edge_threshold: f32,
    /// Smoothness below which a point is a plane candidate. Default 0.1 (m²).
    pub plane_threshold: f32,
    /// Most edges per sector. Default 20 (F-LOAM); the indoor preset uses 10.
    pub max_edges_per_sector: usize,
    /// Two consecutive points farther apart than this (m) are an occlusion candidate. Default 0.3 m.
    pub occlusion_gap: f32,
    /// ... and an occlusion boundary when their beams are closer than this (rad). Default 0.1.
    pub occlusion_angle: f32,
    /// A point whose distance to both ring neighbours exceeds this × range² lies on a surface nearly
    /// parallel to the beam. Default 0.0002 (LOAM).
    pub parallel_beam_ratio: f32,
    /// Neighbours of a chosen edge closer than this (m) along the ring are suppressed. Default 0.2 m.
    pub suppression_gap: f32,
    /// Whether the near side of an occlusion boundary (an object's silhouette) may be an edge.
    /// Silhouettes of round objects move with the viewpoint. Default true (LOAM).
    pub silhouette_edges: bool,
    /// Edge features are thinned to one per voxel of this size (m), as F-LOAM downsamples its
    /// input to the map resolution. Default 0.2 m indoor, 0.4 m outdoor.
    pub edge_voxel: f32,
    /// Plane features are thinned to one per voxel of this size (m). Default 0.4 m indoor, 0.8 m outdoor.
    pub plane_voxel: f32,
}

impl Default for FeatureConfig {
    fn default() -> Self {
        FeatureConfig {
            min_range: 0.5,
            max_range: 100.0,
            neighbours: 5,
            sectors: 6,
            edge_threshold: 0.1,
            plane_threshold: 0.1,
            max_edges_per_sector: 20,
            occlusion_gap: 0.3,
            occlusion_angle: 0.1,
            parallel_beam_ratio: 0.0002,
            suppression_gap: 0.2,
            silhouette_edges: true,
            edge_voxel: 0.2,
            plane_voxel: 0.4,
        }
    }
}

/// One local feature map's parameters.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MapConfig {
    /// Voxel edge (m). Defaults: edges 0.2 m indoor / 0.4 m outdoor, planes 0.4 / 0.8 m (F-LOAM).
    pub voxel_size: f32,
    /// Most points kept per voxel. Default 3.
    pub points_per_voxel: usize,
    /// A new point closer than this (m) to a point of its voxel is not added. Default voxel/4.
    pub min_point_distance: f32,
    /// Voxels farther than this (m) from the robot are dropped. Default 40 m indoor, 100 m outdoor.
    pub radius: f32,
    /// Scans between full rebuilds of the map's search tree (points added in between are searched
    /// through a small tree of their own). Default 10.
    #[serde(default = "default_rebuild_every")]
    pub rebuild_every: usize,
    /// The map's memory budget in voxels, allocated at start (with `points_per_voxel` points
    /// each, at most 4). When it is full, new voxels wait for the next rebuild, which keeps the
    /// nearest 90 %. Defaults: edges 100 000, planes 28 000 indoor / 50 000 outdoor (the simulated
    /// warehouses peak at 66 000 / 10 000, the campus at 80 000 / 29 000; each fills a power-of-two
    /// voxel table to its 7/8 load limit).
    pub max_voxels: usize,
}

fn default_rebuild_every() -> usize {
    10
}

/// Pose-estimation parameters.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct SolverConfig {
    /// Map neighbours per feature. Default 5 (F-LOAM).
    pub neighbours: usize,
    /// All neighbours must lie within this distance (m). Default 1 m (F-LOAM).
    pub max_neighbour_distance: f32,
    /// A neighbourhood is a line when λ_max > ratio × λ_mid. Default 3 (F-LOAM).
    pub line_ratio: f64,
    /// ... and when all its points lie within this (m) of the line. Default 0.05 m.
    pub max_line_deviation: f64,
    /// ... and when it rises at least this steeply (deg from the sensor's horizontal plane).
    /// Default 0° (F-LOAM: every line); the presets use 60° indoor and 30° outdoor, see
    /// [`OdometryConfig::indoor`].
    pub min_line_elevation_deg: f64,
    /// A neighbourhood is a plane when all its points lie within this (m) of the fit. Default 0.05 m
    /// (F-LOAM: 0.2 m, which lets floor-and-box blends through).
    pub max_plane_deviation: f64,
    /// ... and when it spreads in two directions: λ_mid ≥ this × λ_max. Default 0.05.
    pub plane_spread: f64,
    /// ... and when it is flat: λ_min ≤ this × (λ_min + λ_mid + λ_max). Default 0.01.
    pub max_surface_variation: f64,
    /// Expected spread of a clean plane fit (m), about the range noise: a fit scattering σ off its
    /// plane is weighted n² / (n² + σ²). Default 0.01 m.
    pub plane_noise: f64,
    /// From the second correspondence search on (the pose is then close), a plane match is dropped
    /// when its residual exceeds this many expected spreads: the range noise along the normal
    /// (`plane_noise` × the cosine between beam and normal) combined with the fit's own scatter.
    /// Neighbourhoods that blend two surfaces (floor and a box foot, two faces of a step) fit a
    /// plane the true pose misses by centimetres, and on one side only (what lies on the floor is
    /// above it): in the simulated warehouse they biased each scan 1.5 mm upward, which the map
    /// turned into a 0.8° tilt. Default 0 (off). With the indoor maps alone it barely changes the
    /// drift (0.70° against 0.72° after 500 scans); it pays with 2 m min range and 0.6 m plane voxels.
    pub plane_gate: f64,
    /// Huber kernel width on residuals (m). Default 0.1 (F-LOAM).
    pub huber: f64,
    /// Edge weight w₁ = σ / (σ + s): sharper edges count more. Default s = 0.1 (the edge threshold).
    pub edge_weight_scale: f32,
    /// Plane weight w₂ = s / (σ + s): flatter points count more. Default s = 0.1.
    pub plane_weight_scale: f32,
    /// Correspondence searches at most; each is followed by `inner_iterations` Gauss-Newton steps on
    /// the same lines and planes (F-LOAM: 2 searches, up to 4 solver steps). Default 4.
    pub max_iterations: usize,
    /// Gauss-Newton steps per correspondence search. Default 3.
    pub inner_iterations: usize,
    /// Stop when the update's translation is below this (m). Default 1e-4.
    pub convergence_translation: f64,
    /// ... and its rotation below this (rad). Default 1e-5.
    pub convergence_rotation: f64,
    /// Fewer correspondences than this: keep the prediction. Default 30.
    pub min_matches: usize,
    /// An eigen-direction of the normal matrix (sensor frame, rotations scaled to metres by the RMS
    /// lever arm) is degenerate when its eigenvalue is below this × the sum of weights. Default
    /// 0.01: along a featureless corridor the axis measures 0.002-0.008 (noisy plane normals keep it
    /// off zero), well-constrained warehouse and campus scans 0.06-0.08 at the median. The outdoor
    /// preset uses 0.002: on KITTI's HDL-64 streets most features lie on the ground, and the axis
    /// along the road measures 0.004-0.006 while it is well constrained.
    pub degeneracy_ratio: f64,
}

impl Default for SolverConfig {
    fn default() -> Self {
        SolverConfig {
            neighbours: 5,
            max_neighbour_distance: 1.0,
            line_ratio: 3.0,
            max_line_deviation: 0.05,
            min_line_elevation_deg: 0.0,
            max_plane_deviation: 0.05,
            plane_spread: 0.05,
            max_surface_variation: 0.01,
            plane_noise: 0.01,
            plane_gate: 0.0,
            huber: 0.1,
            edge_weight_scale: 0.1,
            plane_weight_scale: 0.1,
            max_iterations: 4,
            inner_iterations: 3,
            convergence_translation: 1e-4,
            convergence_rotation: 1e-5,
            min_matches: 30,
            degeneracy_ratio: 0.01,
        }
    }
}

/// When a scan becomes a keyframe.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct KeyframeConfig {
    /// Travelled distance since the last keyframe (m). Default 1 m.
    pub distance: f64,
    /// Rotation since the last keyframe (deg). Default 15°.
    pub angle_deg: f64,
    /// The keyframe cloud is downsampled to this voxel (m). Default 0.1 m.
    pub voxel: f32,
}

impl Default for KeyframeConfig {
    fn default() -> Self {
        KeyframeConfig { distance: 1.0, angle_deg: 15.0, voxel: 0.1 }
    }
}

/// Everything the odometry needs; [`OdometryConfig::indoor`] and [`OdometryConfig::outdoor`] are the
/// documented presets (indoor is the default).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct OdometryConfig {
    /// Sweep duration (s): point times divided by it give sweep phases. Default 0.1 s (10 Hz).
    pub scan_period: f32,
    /// Feature extraction.
    pub features: FeatureConfig,
    /// The edge map.
    pub edge_map: MapConfig,
    /// The plane map.
    pub plane_map: MapConfig,
    /// Pose estimation.
    pub solver: SolverConfig,
    /// Keyframe selection.
    pub keyframes: KeyframeConfig,
    /// Distortion compensation on (both stages). Off only to measure what it buys. Default on.
    pub deskew: bool,
    /// Stage-1 compensations per scan at most. Stage 1 assumes the last sweep's motion (eq. 2);
    /// when the robot's turn rate changes within a sweep (a warehouse robot entering or leaving a
    /// corner: 3°/sweep to 0 in three sweeps) the features are compensated for a motion that did
    /// not happen, and the registration follows the prediction (3° off for a few sweeps in the
    /// simulated warehouse). When the estimated sweep motion differs from the one the features
    /// were compensated with by more than `deskew_tolerance`, they are compensated again with the
    /// estimate and the pose re-estimated from it. Default 3; 1 is the paper's single pass.
    pub deskew_rounds: usize,
    /// How far two sweep motions may differ before stage 1 is repeated: the largest displacement
    /// the difference makes on a point 10 m away (m). Default 0.03 (0.17°): in the simulated warehouse
    /// 0.03 took robot 1 from 2.6 / 6.2 cm ATE (aligned / not, one pass) to 0.9 / 4.3 cm, 0.01 and
    /// 0.02 gave 0.9 / 6.8 and 1.3 / 6.1 cm at more cost, 0.05 lost robot 2 of warehouse-large.
    pub deskew_tolerance: f64,
}

impl Default for OdometryConfig {
    fn default() -> Self {
        Self::indoor()
    }
}

impl OdometryConfig {
    /// Indoor preset (warehouses, offices: ranges under ~40 m): finer maps, as F-LOAM's indoor launch,
    /// and edge lines only when they rise 60° or more: indoors most shallow "lines" are floor-object
    /// junctions and shelf fronts, which a spinning LiDAR places in height only to its beam spacing
    /// (measured in the simulated warehouse: a −0.1°/scan pitch bias, gone with the filter). The
    /// outdoor preset keeps lines from 30° up: at 60° the campus roads lack constraints (1.1 m ATE
    /// over 600 scans), with every line the roll is biased on sloped ground (47 cm unaligned), at
    /// 30° 15 cm.
    pub fn indoor() -> Self {
        OdometryConfig {
            scan_period: 0.1,
            // Ten edges per sector, not F-LOAM's twenty: on the simulated warehouse (VLP-16) this
            // measured 2.7 / 13.0 cm ATE (aligned / not) against 3.0 / 13.4 cm, and 8.8 ms per
            // scan against 9.1.
            // Points nearer than 2 m are the lowest rings on rack feet, box bottoms and steps:
            // plane neighbourhoods there blend the floor with what stands on it, always above it,
            // and pulled each scan ~1.7 mm up (a 0.7° tilt of the map after 500 scans).
            features: FeatureConfig { max_edges_per_sector: 10, min_range: 2.0, ..FeatureConfig::default() },
            edge_map: MapConfig {
                voxel_size: 0.2,
                points_per_voxel: 3,
                min_point_distance: 0.05,
                radius: 40.0,
                rebuild_every: 10,
                max_voxels: 100_000,
            },
            // 0.6 m plane voxels: sparser patches span more scan lines, so fewer neighbourhoods
            // are two parallel ring traces (which fit a plane exactly, between two surfaces);
            // 0.8 m mixes the two faces of the warehouse's 0.4 m fire wall (0.3 m jumps).
            plane_map: MapConfig {
                voxel_size: 0.6,
                points_per_voxel: 3,
                min_point_distance: 0.15,
                radius: 40.0,
                rebuild_every: 10,
                max_voxels: 28_000,
            },
            solver: SolverConfig { min_line_elevation_deg: 60.0, plane_gate: 3.0, ..SolverConfig::default() },
            keyframes: KeyframeConfig::default(),
            deskew: true,
            deskew_rounds: 3,
            deskew_tolerance: 0.03,
        }
    }

    /// Outdoor preset (streets, campuses): F-LOAM's KITTI map resolution, longer crop.
    pub fn outdoor() -> Self {
        OdometryConfig {
            features: FeatureConfig {
                min_range: 2.0,
                edge_voxel: 0.4,
                plane_voxel: 0.8,
                max_edges_per_sector: 20,
                ..FeatureConfig::default()
            },
            edge_map: MapConfig {
                voxel_size: 0.4,
                points_per_voxel: 3,
                min_point_distance: 0.1,
                radius: 100.0,
                rebuild_every: 10,
                max_voxels: 100_000,
            },
            plane_map: MapConfig {
                voxel_size: 0.8,
                points_per_voxel: 3,
                min_point_distance: 0.2,
                radius: 100.0,
                rebuild_every: 10,
                max_voxels: 50_000,
            },
            keyframes: KeyframeConfig { distance: 2.0, angle_deg: 15.0, voxel: 0.2 },
            solver: SolverConfig { degeneracy_ratio: 0.002, min_line_elevation_deg: 30.0, ..SolverConfig::default() },
            ..Self::indoor()
        }
    }
}

/// A keyframe: the deskewed, downsampled scan at its pose.
#[derive(Clone, Debug)]
pub struct Keyframe {
    /// 0, 1, 2, ... in order.
    pub seq: u64,
    /// Index of the scan that made it.
    pub frame: usize,
    /// Sensor pose at the sweep end, odometry frame.
    pub pose: Isometry3<f64>,
    /// Motion-compensated cloud in the sweep-end sensor frame, voxel-downsampled.
    pub cloud: PointCloud,
}

/// What one scan produced.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Sensor pose at the sweep end in the odometry frame.
    pub pose: Isometry3<f64>,
    /// Edge features extracted.
    pub edges: usize,
    /// Plane features extracted (after thinning).
    pub planes: usize,
    /// Gauss-Newton iterations.
    pub iterations: usize,
    /// True when the pose problem was ill-conditioned and the motion prior was kept along some directions.
    pub degenerate: bool,
    /// Smallest eigenvalue of the pose problem's normal matrix over the sum of weights (1 for the
    /// first scan): how well the worst direction is constrained.
    pub conditioning: f64,
    /// The keyframe this scan made, if any.
    pub keyframe: Option<Keyframe>,
    /// Where the time went.
    pub timings: FrameTimings,
}

/// Wall time of the pipeline's stages for one scan, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct FrameTimings {
    /// Feature extraction and thinning.
    pub features: f64,
    /// Distortion compensation and pose estimation.
    pub registration: f64,
    /// Map insertion, crop and k-d tree rebuild, keyframe.
    pub map: f64,
}

/// Why a scan could not be registered.
#[derive(Debug, thiserror::Error)]
pub enum OdometryError {
    /// The scan lacks a channel the odometry needs.
    #[error(transparent)]
    Features(#[from] FeatureError),
    /// A configuration value is unusable.
    #[error("invalid configuration: {0}")]
    Config(String),
}

/// The F-LOAM odometry state of one robot.
pub struct Odometry {
    config: OdometryConfig,
    frames: usize,
    pose: Isometry3<f64>,
    motion: SweepMotion,
    edge_map: FeatureMap,
    plane_map: FeatureMap,
    last_keyframe: Option<Isometry3<f64>>,
    keyframes: u64,
}

impl Odometry {
    /// A fresh odometry; the first scan defines the odometry frame.
    pub fn new(config: OdometryConfig) -> Result<Self, OdometryError> {
        let positive = [
            ("scan_period", config.scan_period),
            ("edge_map.voxel_size", config.edge_map.voxel_size),
            ("plane_map.voxel_size", config.plane_map.voxel_size),
            ("features.edge_voxel", config.features.edge_voxel),
            ("features.plane_voxel", config.features.plane_voxel),
            ("keyframes.voxel", config.keyframes.voxel),
        ];
        if let Some((name, v)) = positive.iter().find(|(_, v)| !(*v > 0.0 && v.is_finite())) {
            return Err(OdometryError::Config(format!("{name} must be positive, got {v}")));
        }
        for (name, map) in [("edge_map", &config.edge_map), ("plane_map", &config.plane_map)] {
            if !(1..=MAX_POINTS_PER_VOXEL).contains(&map.points_per_voxel) || map.max_voxels == 0 {
                return Err(OdometryError::Config(format!(
                    "{name}: points_per_voxel must be 1 to {MAX_POINTS_PER_VOXEL} and max_voxels at least 1, got {} and {}",
                    map.points_per_voxel, map.max_voxels
                )));
            }
        }
        Ok(Odometry {
            edge_map: FeatureMap::new(config.edge_map.clone()),
            plane_map: FeatureMap::new(config.plane_map.clone()),
            config,
            frames: 0,
            pose: Isometry3::identity(),
            motion: SweepMotion::zero(),
            last_keyframe: None,
            keyframes: 0,
        })
    }

    /// The configuration in use.
    pub fn config(&self) -> &OdometryConfig {
        &self.config
    }

    /// Registers one scan (with ring and per-point time channels) and returns its pose.
    pub fn register(&mut self, scan: &PointCloud) -> Result<Frame, OdometryError> {
        // The stages' parallel loops hand their work to rayon's pool and wait for it: called from
        // a thread outside the pool, each loop costs a worker's wake-up and a hand-over back, a
        // dozen per scan. Run on a worker, the scan pays for one.
        rayon::scope(|_| self.register_on_pool(scan))
    }

    /// [`Odometry::register`] on a worker of rayon's pool.
    fn register_on_pool(&mut self, scan: &PointCloud) -> Result<Frame, OdometryError> {
        let clock = std::time::Instant::now();
        let lap = |since: &mut std::time::Instant| {
            let ms = since.elapsed().as_secs_f64() * 1e3;
            *since = std::time::Instant::now();
            ms
        };
        let mut since = clock;
        let raw = features::extract(scan, self.config.scan_period, &self.config.features)?;
        let features_ms = lap(&mut since);
        // Stage 1: deskew with the predicted (previous) motion, predict the pose with it (eq. 2).
        let predicted = self.pose * cloud::se3::exp(&self.motion.0);
        let estimate = if self.frames == 0 {
            solver::Estimate {
                pose: Isometry3::identity(),
                iterations: 0,
                edge_matches: 0,
                plane_matches: 0,
                degenerate_directions: 0,
                min_eigen_ratio: 1.0,
            }
        } else {
            self.estimate(&raw, predicted)
        };
        let registration_ms = lap(&mut since);
        let previous = self.pose;
        self.pose = estimate.pose;
        self.motion = if self.frames == 0 { SweepMotion::zero() } else { SweepMotion::between(&previous, &self.pose) };
        // Stage 2: the estimated motion corrects the features before they enter the map.
        let corrected = if self.config.deskew { self.motion } else { SweepMotion::zero() };
        let index = self.frames;
        let placed = |f: &features::Feature| (corrected.compensate(&f.point, f.phase), ScanLine::new(index, f.ring));
        self.edge_map.insert(raw.edges.iter().map(placed), &self.pose);
        self.plane_map.insert(raw.planes.iter().map(placed), &self.pose);
        let centre = Point3::from(self.pose.translation.vector);
        self.edge_map.crop_and_rebuild(&centre);
        self.plane_map.crop_and_rebuild(&centre);
        let keyframe = self.keyframe(scan, &corrected);
        self.frames += 1;
        let timings = FrameTimings { features: features_ms, registration: registration_ms, map: lap(&mut since) };
        Ok(Frame {
            timings,
            pose: self.pose,
            edges: raw.edges.len(),
            planes: raw.planes.len(),
            iterations: estimate.iterations,
            degenerate: estimate.degenerate_directions > 0,
            conditioning: estimate.min_eigen_ratio,
            keyframe,
        })
    }

    /// Stage 1 and the pose (eq. 4): the features compensated with the predicted motion, then, while
    /// the estimate says the sweep moved otherwise, with the estimated one (see
    /// [`OdometryConfig::deskew_rounds`]).
    fn estimate(&self, raw: &Features, predicted: Isometry3<f64>) -> solver::Estimate {
        let mut searches = solver::Neighbourhoods::new(raw.edges.len(), raw.planes.len());
        let mut solve = |motion: &SweepMotion, from: Isometry3<f64>| {
            let edges = deskew::compensate(&raw.edges, motion);
            let planes = deskew::compensate(&raw.planes, motion);
            let (edge_map, plane_map) = (&self.edge_map, &self.plane_map);
            solver::estimate(&edges, &planes, edge_map, plane_map, from, &self.config.solver, &mut searches)
        };
        if !self.config.deskew {
            return solve(&SweepMotion::zero(), predicted);
        }
        let mut motion = self.motion;
        let mut estimate = solve(&motion, predicted);
        for _ in 1..self.config.deskew_rounds {
            let mut measured = SweepMotion::between(&self.pose, &estimate.pose);
            measured.0.fixed_rows_mut::<3>(0).copy_from(&motion.0.fixed_rows::<3>(0));
            if motion.difference_at(&measured, 10.0) <= self.config.deskew_tolerance {
                break;
            }
            motion = measured;
            estimate = solve(&motion, estimate.pose);
        }
        estimate
    }

    /// A keyframe when the robot moved or turned enough since the last one (the first scan always is).
    fn keyframe(&mut self, scan: &PointCloud, motion: &SweepMotion) -> Option<Keyframe> {
        let kc = &self.config.keyframes;
        if let Some(last) = &self.last_keyframe {
            let d = last.inverse() * self.pose;
            if d.translation.vector.norm() < kc.distance && d.rotation.angle().to_degrees() < kc.angle_deg {
                return None;
            }
        }
        let times = scan.time.as_deref().unwrap_or(&[]);
        let period = self.config.scan_period;
        let mut deskewed = scan.clone();
        if !motion.is_zero() {
            let table = motion.table();
            for (p, t) in deskewed.points.iter_mut().zip(times) {
                *p = table.compensate(p, t / period);
            }
        }
        let cloud = cloud::voxel::downsample(&deskewed, kc.voxel).unwrap_or(deskewed);
        self.last_keyframe = Some(self.pose);
        let seq = self.keyframes;
        self.keyframes += 1;
        Some(Keyframe { seq, frame: self.frames, pose: self.pose, cloud })
    }
}
