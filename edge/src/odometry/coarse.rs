//! Coarse alignment of a scan to the local map, for when the motion prediction cannot be trusted
//! (the first scans, after a gap, after a failed fit): VGICP from large voxels to small
//! ([`cloud::registration`], after Koide et al. 2021), whose basin is metres wide where the feature
//! matching's is its 1 m neighbour radius. Its result is only the start of the fine fit.

use cloud::registration::{self, GaussianCloud, Method, RegistrationConfig, VoxelSearch};
use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

/// Settings of the coarse alignment.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct CoarseConfig {
    /// Voxel edge of the finest level (m). Default 1 m: coarse is enough, the fine fit follows.
    pub voxel: f64,
    /// Coarser levels before it, each doubling voxel and reach. Default 2 (4 m, 2 m, 1 m).
    pub levels: usize,
    /// Correspondences farther than this at the finest level are ignored (m); it doubles with
    /// each coarser level. Default 1 m (4 m at the coarsest).
    pub max_correspondence: f64,
    /// Neighbours per point covariance. Default 10: features are sparse (one per voxel).
    pub neighbours: usize,
    /// Linearisations per level at most. Default 15.
    pub max_iterations: usize,
}

impl Default for CoarseConfig {
    fn default() -> Self {
        CoarseConfig { voxel: 1.0, levels: 2, max_correspondence: 1.0, neighbours: 10, max_iterations: 15 }
    }
}

impl CoarseConfig {
    /// This configuration with coarser levels added until the coarsest reaches `reach` metres
    /// (at most two more: 16 m voxels stop resolving a scene).
    pub fn reaching(&self, reach: f64) -> CoarseConfig {
        let mut config = self.clone();
        let coarsest = |c: &CoarseConfig| c.max_correspondence * f64::from(1u32 << c.levels.min(16));
        while coarsest(&config) < reach && config.levels < self.levels + 2 {
            config.levels += 1;
        }
        config
    }
}

/// The scan's feature points (already in the sweep-end frame) aligned to the map points from
/// `initial`, or `None` when either side is too small or degenerate to register.
pub fn align(
    source: &[Point3<f32>],
    map: &[Point3<f32>],
    initial: &Isometry3<f64>,
    config: &CoarseConfig,
) -> Option<Isometry3<f64>> {
    if source.len() < config.neighbours || map.len() < config.neighbours {
        return None;
    }
    let source = GaussianCloud::new(source, config.neighbours);
    let target = GaussianCloud::new(map, config.neighbours);
    align_gaussians(&source, &target, initial, config)
}

/// [`align`] on clouds whose covariances are already estimated (e.g. a target the caller also
/// uses for a fine fit).
pub fn align_gaussians(
    source: &GaussianCloud,
    target: &GaussianCloud,
    initial: &Isometry3<f64>,
    config: &CoarseConfig,
) -> Option<Isometry3<f64>> {
    let registration = RegistrationConfig {
        max_iterations: config.max_iterations,
        max_correspondence_distance: config.max_correspondence,
        neighbours: config.neighbours,
        voxel_resolution: config.voxel,
        coarse_levels: config.levels,
        // A point off by metres rarely falls in the voxel it belongs to: search the face neighbours.
        voxel_search: VoxelSearch::Direct7,
        ..RegistrationConfig::default()
    };
    let result = registration::align_gaussians(source, target, initial, Method::Vgicp, &registration).ok()?;
    (result.inliers >= config.neighbours).then_some(result.transform)
}
