//! The odometry's configuration: one struct per stage, each field documented with its default,
//! and the two presets the command line offers ([`OdometryConfig::preset`]).
//!
//! The figures that justify a default come from runs on the simulator and KITTI; docs/benchmarks.md
//! lists them with the command that reproduces each, so the comments here only say why.

use cloud::Preset;
use cloud::gauss_newton::RotationScale;
use serde::{Deserialize, Serialize};

pub use super::aloam::{AloamConfig, Method};
pub use super::coarse::CoarseConfig;
pub use super::health::HealthConfig;
pub use super::motion_model::MotionModelConfig;
pub use crate::loops::LoopConfig;

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
    /// An occlusion candidate (see `occlusion_gap`) is a boundary when the two beams are closer
    /// than this (rad): a jump in range between nearly parallel beams. Default 0.1.
    pub occlusion_angle: f32,
    /// A point whose distance to both ring neighbours exceeds this × range² lies on a surface nearly
    /// parallel to the beam. Default 0.0002 (LOAM).
    pub parallel_beam_ratio: f32,
    /// Neighbours of a chosen edge closer than this (m) along the ring are suppressed. Default 0.2 m.
    pub suppression_gap: f32,
    /// Whether the near side of an occlusion boundary (an object's silhouette) may be an edge.
    /// Silhouettes of round objects move with the viewpoint. Default true (LOAM).
    pub silhouette_edges: bool,
    /// Smallest angle (degrees) between the beam and the surfaces on either side of an edge point:
    /// on a surface seen at a grazing angle the samples lie far apart, and the sharpest point
    /// there marks where a sample fell rather than a corner; as the robot moves such points slide
    /// along the surface and tilt the map (warehouse-small robot 2 took 0.25 deg of pitch in its
    /// first 3 m from a box face seen at 4 deg). Default 20; 0 turns the test off, as the outdoor
    /// preset does: outdoors edges are few, and without the grazing ones a car at 10 m/s lost its
    /// way in the robustness matrix (docs/decisions/grazing-edge-test-outdoors-and-variants.md).
    pub edge_min_incidence_deg: f32,
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
            edge_min_incidence_deg: 20.0,
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
    /// Voxels farther than this (m) from the robot are dropped (indoor 40, outdoor 100).
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
    /// A line neighbourhood's points must all lie within this (m) of the line. Default 0.05 m.
    pub max_line_deviation: f64,
    /// A line neighbourhood must rise at least this steeply (deg from the sensor's horizontal
    /// plane): flat lines are often a plane's edge seen along the ring.
    /// Default 0° (F-LOAM: every line); the presets use 60° indoor and 30° outdoor, see
    /// [`OdometryConfig::indoor`].
    pub min_line_elevation_deg: f64,
    /// A neighbourhood is a plane when all its points lie within this (m) of the fit. Default 0.05 m
    /// (F-LOAM: 0.2 m, which lets floor-and-box blends through).
    pub max_plane_deviation: f64,
    /// A plane neighbourhood must spread in two directions: λ_mid ≥ this × λ_max. Default 0.05.
    pub plane_spread: f64,
    /// A plane neighbourhood must be flat: λ_min ≤ this × (λ_min + λ_mid + λ_max). Default 0.01.
    pub max_surface_variation: f64,
    /// Expected spread of a clean plane fit (m), about the range noise: a fit scattering σ off its
    /// plane is weighted n² / (n² + σ²). Default 0.01 m.
    pub plane_noise: f64,
    /// From the second correspondence search on (the pose is then close), a plane match is dropped
    /// when its residual exceeds this many expected spreads: the range noise along the normal
    /// (`plane_noise` × the cosine between beam and normal) combined with the fit's own scatter.
    /// Neighbourhoods that blend two surfaces (floor and a box foot, two faces of a step) fit a
    /// plane the true pose misses by centimetres, and on one side only (what lies on the floor is
    /// above it), so they bias every scan the same way and the map tilts. Default 0 (off); the
    /// indoor preset uses 3, where it pays together with its 2 m min range and 0.6 m plane voxels.
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
    /// Stop when the update's rotation is below this (rad), with its translation below
    /// `convergence_translation`. Default 1e-5.
    pub convergence_rotation: f64,
    /// Fewer correspondences than this: keep the prediction. Default 30.
    pub min_matches: usize,
    /// An eigen-direction of the normal matrix (sensor frame, each rotation scaled to metres by its
    /// own lever arm, the features' RMS distance from its axis) is degenerate when its eigenvalue is
    /// below this × the sum of weights. Default 0.01: along a featureless corridor the axis
    /// measures 0.002-0.008 (noisy plane normals keep it off zero), the simulated warehouse scans
    /// 0.03-0.05 at the median (0.015-0.026 at the 5th percentile) and campus scans 0.07-0.09. The
    /// outdoor preset uses 0.002: on KITTI's HDL-64 streets most features lie on the ground, and
    /// the axis along the road measures 0.004-0.006 while it is well constrained.
    pub degeneracy_ratio: f64,
    /// How the degeneracy test puts rotations in metres: `per_axis` (default), each by the
    /// features' RMS distance from its axis, or `common`, all by their RMS distance from the
    /// sensor. With the common lever arm the indoor scans looking down an aisle flagged their
    /// roll (92-394 scans of a 1000-1800-scan simulated run), kept the prediction's roll rate
    /// and rolled the map over (aisles robot 1, 151 deg). The outdoor preset keeps `common`: there
    /// F-LOAM flags no scan either way, and A-LOAM's scan-to-scan step on the campus relies on its
    /// flags (0.79 m ATE over 250 sweeps against 2.0 m with `per_axis`).
    pub rotation_scale: RotationScale,
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
            rotation_scale: RotationScale::PerAxis,
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
    /// The odometry: `"floam"` (the default) or `"aloam"` ([`super::aloam`]: scan-to-scan every
    /// sweep, scan-to-map every `aloam.map_every` sweeps, linear deskewing).
    pub method: Method,
    /// A-LOAM's parameters, used with `method = "aloam"`.
    pub aloam: AloamConfig,
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
    /// How far the constant-velocity prediction is trusted.
    pub motion_model: MotionModelConfig,
    /// The coarse alignment used where it is not.
    pub coarse: CoarseConfig,
    /// When a fit is judged failed, and what is tried then.
    pub health: HealthConfig,
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
    /// the difference makes on a point 10 m away (m). Default 0.03 (0.17°): tighter costs more
    /// without a better trajectory, looser loses robots at the warehouse's corners.
    pub deskew_tolerance: f64,
    /// Loop closure (run beside the odometry by `emr-edge odometry` and `emr-edge run` unless
    /// `--no-loops`; the odometry itself does not use it).
    pub loops: LoopConfig,
}

impl Default for OdometryConfig {
    fn default() -> Self {
        Self::indoor()
    }
}

impl OdometryConfig {
    /// The preset named on the command line.
    pub fn preset(preset: Preset) -> Self {
        match preset {
            Preset::Indoor => Self::indoor(),
            Preset::Outdoor => Self::outdoor(),
        }
    }

    /// Indoor preset (warehouses, offices: ranges under ~40 m): finer maps, as F-LOAM's indoor launch,
    /// and edge lines only when they rise 60° or more: indoors most shallow "lines" are floor-object
    /// junctions and shelf fronts, which a spinning LiDAR places in height only to its beam spacing,
    /// and they bias the pitch. The outdoor preset keeps lines from 30° up: every line biases the
    /// roll on sloped ground (30° and 60° measure alike: docs/decisions/odometry-preset-values.md).
    pub fn indoor() -> Self {
        OdometryConfig {
            method: Method::Floam,
            aloam: AloamConfig::default(),
            scan_period: 0.1,
            // Ten edges per sector, not F-LOAM's twenty: as accurate in the warehouse, and faster.
            // Points nearer than 2 m are the lowest rings on rack feet, box bottoms and steps:
            // plane neighbourhoods there blend the floor with what stands on it, always above it,
            // and pull each scan up (the map tilts).
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
            motion_model: MotionModelConfig::default(),
            coarse: CoarseConfig::default(),
            health: HealthConfig::default(),
            deskew: true,
            deskew_rounds: 3,
            deskew_tolerance: 0.03,
            loops: LoopConfig::preset(Preset::Indoor),
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
                edge_min_incidence_deg: 0.0,
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
            solver: SolverConfig {
                degeneracy_ratio: 0.002,
                rotation_scale: RotationScale::Common,
                min_line_elevation_deg: 30.0,
                ..SolverConfig::default()
            },
            loops: LoopConfig::preset(Preset::Outdoor),
            ..Self::indoor()
        }
    }
}

/// A configuration file that does not fit [`OdometryConfig`].
#[derive(Debug, thiserror::Error)]
pub enum OverlayError {
    /// The text is not TOML.
    #[error("invalid TOML")]
    Toml(#[source] toml::de::Error),
    /// The keys or values do not fit the configuration.
    #[error("invalid configuration")]
    Config(#[source] toml::de::Error),
}

impl OdometryConfig {
    /// This configuration with the keys of `text` (TOML) replacing its own: keys left out keep
    /// their values here, so a file only needs what it changes.
    pub fn overlay(&self, text: &str) -> Result<Self, OverlayError> {
        // Plain numbers, booleans and tables: the configuration always round-trips through TOML.
        let own = toml::to_string(self).expect("the configuration serialises to TOML");
        let mut base: toml::Table = toml::from_str(&own).expect("serialised TOML parses");
        let overlay: toml::Table = toml::from_str(text).map_err(OverlayError::Toml)?;
        merge(&mut base, overlay);
        toml::Value::Table(base).try_into().map_err(OverlayError::Config)
    }
}

/// Recursively overlays `overlay` onto `base`.
fn merge(base: &mut toml::Table, overlay: toml::Table) {
    for (key, value) in overlay {
        match (base.get_mut(&key), value) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o),
            (_, v) => {
                base.insert(key, v);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_overlay_changes_only_its_keys() {
        let base = OdometryConfig::preset(Preset::Outdoor);
        let changed = base.overlay("deskew = false\n[solver]\nhuber = 0.2\n").unwrap();
        let expected = OdometryConfig {
            deskew: false,
            solver: SolverConfig { huber: 0.2, ..base.solver.clone() },
            ..base.clone()
        };
        assert_eq!(changed, expected);
        assert!(matches!(base.overlay("[solver]\nno_such_key = 1\n"), Err(OverlayError::Config(_))));
        assert!(matches!(base.overlay("deskew = "), Err(OverlayError::Toml(_))));
    }
}
