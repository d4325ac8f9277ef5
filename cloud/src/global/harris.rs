//! Step 3 — Harris 3D keypoints on surface normals (PCL's `HarrisKeypoint3D`, method HARRIS).
//!
//! The 3D analogue of the Harris corner detector (Sipiran & Bustos 2011, as implemented in PCL):
//! the "structure tensor" of a point is the mean outer product of the unit normals in its
//! neighbourhood, `C = 1/n Σ nᵢ nᵢᵀ`; the response is `det(C) − k·trace(C)²`. With unit normals
//! `trace(C) = 1`, and like PCL we add `k` back so that a flat or cylindrical patch scores 0 and a
//! trihedral corner (normals split evenly over three axes) scores the maximum 1/27. Keypoints are
//! local maxima of the response within a suppression radius (non-maximum suppression).
//!
//! map_merge_3d's fixed threshold leaves small or smooth maps with too few keypoints to register;
//! here the count adapts: when fewer than `min_keypoints` maxima pass the threshold the strongest
//! sub-threshold maxima are added, and if there are still too few, one point per cell of a voxel
//! grid of the suppression radius fills in (uniform subsampling, as in Open3D's keypoint-free
//! pipeline).

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use rustc_hash::FxHashSet;

use super::error::FeatureError;
use super::normals::Surfels;
use crate::voxel::VoxelKey;

/// Settings of step 3.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HarrisConfig {
    /// Neighbourhood radius of the normal tensor, metres (default 1.2 = 3 × voxel).
    pub radius: f32,
    /// Harris sensitivity `k` (default 0.04, PCL's and Harris's classic value).
    pub k: f64,
    /// Minimum response of a keypoint (default 1e-3; the maximum is 1/27 ≈ 0.037).
    pub threshold: f64,
    /// Non-maximum suppression radius, metres (default 0.4 = one voxel). Small on purpose: keypoints
    /// are voxel centroids, so the "same" corner lands up to a voxel apart in two maps, and FPFH
    /// changes fast around corners; dense keypoints give every source keypoint a target one close
    /// by (measured on shifted grids: 0.4 m gives 3x the true matches of 1.2 m).
    pub nms_radius: f32,
    /// Lower the threshold, then subsample, until at least this many keypoints (default 2000).
    pub min_keypoints: usize,
    /// Keep at most the strongest this many keypoints (default 5000).
    pub max_keypoints: usize,
}

impl Default for HarrisConfig {
    fn default() -> Self {
        Self { radius: 1.2, k: 0.04, threshold: 1e-3, nms_radius: 0.4, min_keypoints: 2000, max_keypoints: 5000 }
    }
}

impl HarrisConfig {
    /// Checks radii and counts.
    pub fn validate(&self) -> Result<(), FeatureError> {
        let ok = |r: f32| r > 0.0 && r.is_finite();
        if !ok(self.radius) || !ok(self.nms_radius) || !self.k.is_finite() || self.max_keypoints == 0 {
            return Err(FeatureError::InvalidConfig("harris needs positive radii, a finite k and max_keypoints > 0"));
        }
        Ok(())
    }
}

/// The Harris response of every surfel (`det C − k·tr(C)² + k`, 0 on planes, 1/27 at corners).
pub fn harris_response(surfels: &Surfels, radius: f32, k: f64) -> Vec<f64> {
    (0..surfels.len())
        .into_par_iter()
        .map(|i| {
            if !surfels.has_normal(i) {
                return 0.0;
            }
            // Neighbours without a normal are left out of the mean.
            let (sum, count) = surfels
                .neighbours(i, radius, usize::MAX)
                .iter()
                .filter(|q| surfels.has_normal(q.index()))
                .fold((Matrix3::zeros(), 0usize), |(acc, count), q| {
                    let n: Vector3<f64> = surfels.normals[q.index()].cast();
                    (acc + n * n.transpose(), count + 1)
                });
            let c = sum / count.max(1) as f64;
            c.determinant() - k * c.trace().powi(2) + k
        })
        .collect()
}

/// Step 3: indices (into `surfels`) of the keypoints, strongest first.
pub fn detect_keypoints(surfels: &Surfels, config: &HarrisConfig) -> Vec<usize> {
    let response = harris_response(surfels, config.radius, config.k);
    let mut maxima = local_maxima(surfels, &response, config.nms_radius);
    maxima.sort_by(|&a, &b| response[b].total_cmp(&response[a]).then(a.cmp(&b)));
    let strong = maxima.iter().take_while(|&&i| response[i] > config.threshold).count();
    let wanted = config.min_keypoints.min(config.max_keypoints);
    // Lowering the threshold: take sub-threshold maxima, strongest first, up to the minimum.
    let mut keypoints: Vec<usize> = maxima.into_iter().take(strong.max(wanted)).collect();
    if keypoints.len() < wanted {
        fill_by_grid(surfels, config.nms_radius, wanted, &mut keypoints);
    }
    keypoints.truncate(config.max_keypoints);
    keypoints
}

/// Points whose response is the largest within `radius` (ties go to the lower index).
fn local_maxima(surfels: &Surfels, response: &[f64], radius: f32) -> Vec<usize> {
    (0..surfels.len())
        .into_par_iter()
        .filter(|&i| {
            surfels.has_normal(i)
                && surfels.neighbours(i, radius, usize::MAX).iter().all(|q| {
                    let (j, r) = (q.index(), response[q.index()]);
                    j == i || r < response[i] || (r == response[i] && i < j)
                })
        })
        .collect()
}

/// Adds one point per voxel of edge `cell` (the first in index order) until `wanted` are chosen.
fn fill_by_grid(surfels: &Surfels, cell: f32, wanted: usize, keypoints: &mut Vec<usize>) {
    let inv = 1.0 / cell;
    let mut taken: FxHashSet<VoxelKey> = keypoints.iter().map(|&i| VoxelKey::of(&surfels.points[i], inv)).collect();
    for (i, p) in surfels.points.iter().enumerate() {
        if keypoints.len() >= wanted {
            break;
        }
        if surfels.has_normal(i) && taken.insert(VoxelKey::of(p, inv)) {
            keypoints.push(i);
        }
    }
}
