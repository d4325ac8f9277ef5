//! Global registration without an initial guess: FPFH features at Harris 3D keypoints, matched and
//! verified by RANSAC (the pipeline of map_merge_3d, Hörner 2016, made faster and more robust).
//! The edge re-localises a scan in its local map with it; the station merges robot maps with it.
//!
//! 1. [`preprocess`]: finite points, voxel downsampling, outlier removal;
//! 2. [`normals`]: plane-fit normals with a frame-independent orientation;
//! 3. [`harris`]: Harris 3D keypoints with an adaptive count;
//! 4. [`fpfh`]: FPFH descriptors at the keypoints, over the whole downsampled cloud;
//! 5. [`matching`]: reciprocal k-nearest matching in descriptor space;
//! 6. [`ransac`]: RANSAC with edge-length pre-rejection and an adaptive iteration bound, Umeyama
//!    refit on all inliers;
//! 7. [`polish`]: a few point-to-plane steps on the downsampled clouds (decimetres to centimetres).
//!
//! Steps 1-4 depend on one cloud only: [`Features::compute`] runs them once per cloud, so that a
//! map matched against many scans (or many maps) is described once; [`estimate()`] runs steps 5-7
//! on two clouds' features; [`align`] does all of it for one pair and scores the result. The
//! transform maps SOURCE points into the TARGET frame; fine registration (GICP / VGICP in
//! [`crate::registration`]) is left to the caller. Bad input (empty clouds, a few points, only NaN,
//! identical points) gives an error, never a panic; the sampler is seeded, so a call repeats exactly.

pub mod config;
pub mod error;
pub mod estimate;
pub mod features;
pub mod fpfh;
pub mod harris;
pub mod matching;
pub mod normals;
pub mod polish;
pub mod preprocess;
pub mod ransac;

use std::fmt;

use nalgebra::Isometry3;
use rayon::prelude::*;

use crate::PointCloud;
use crate::kdtree::gate_radius;

pub use config::GlobalConfig;
pub use error::FeatureError;
pub use estimate::{Around, Estimate, EstimateTiming, NoModel, estimate, estimate_excluding};
pub use features::{FeatureTiming, Features};
pub use fpfh::{Fpfh, FpfhConfig};
pub use harris::HarrisConfig;
pub use matching::{Correspondence, MatchingConfig};
pub use normals::{NormalConfig, Orientation, Surfels};
pub use polish::PolishConfig;
pub use preprocess::{OutlierFilter, PreprocessConfig};
pub use ransac::RansacConfig;

/// Which of the two clouds an error is about.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    /// The cloud that is moved.
    Source,
    /// The cloud it is moved onto.
    Target,
}

impl fmt::Display for Role {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Role::Source => "source",
            Role::Target => "target",
        })
    }
}

/// Why [`align`] found no transform.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum GlobalError {
    /// A setting is out of range.
    #[error("{0}")]
    Config(FeatureError),
    /// A cloud has no points at all.
    #[error("the {0} cloud is empty")]
    Empty(Role),
    /// Too little of a cloud survived a step (non-finite points are dropped first, so a cloud of
    /// NaN ends here after "dropping non-finite points").
    #[error("{role} cloud: {error}")]
    Features {
        /// The cloud.
        role: Role,
        /// The step and the counts.
        error: FeatureError,
    },
    /// The descriptors agree on no transform.
    #[error(transparent)]
    NoModel(#[from] NoModel),
}

/// A transform found without an initial guess, and the evidence for it.
///
/// Whether to trust it is the caller's call: a right answer on a scan has tens to hundreds of
/// inliers and most of the scan within the polish gate (`fitness` above ~0.5), a wrong one a
/// handful of inliers and a low fitness.
#[derive(Clone, Debug, PartialEq)]
pub struct GlobalAlignment {
    /// Maps SOURCE points into the TARGET frame (RANSAC, then the point-to-plane polish).
    pub transform: Isometry3<f64>,
    /// RANSAC's transform before the polish.
    pub coarse_transform: Isometry3<f64>,
    /// Reciprocal descriptor correspondences RANSAC started from.
    pub correspondences: usize,
    /// Correspondences that agree with RANSAC's transform.
    pub inliers: usize,
    /// `inliers / correspondences`, in [0, 1].
    pub inlier_ratio: f64,
    /// Share of the downsampled source points that land within the polish gate
    /// ([`PolishConfig::max_distance`]) of a target point, in [0, 1] (Open3D's `fitness`).
    pub fitness: f64,
    /// Root mean square distance of those points to their nearest target point, metres.
    pub rmse: f64,
    /// Keypoints with a descriptor: source, target.
    pub keypoints: (usize, usize),
    /// Samples RANSAC drew.
    pub ransac_iterations: usize,
}

/// Registers `source` onto `target` without an initial guess: the transform mapping source points
/// into the target frame, with its RANSAC support and fitness.
pub fn align(source: &PointCloud, target: &PointCloud, config: &GlobalConfig) -> Result<GlobalAlignment, GlobalError> {
    config.validate().map_err(GlobalError::Config)?;
    for (cloud, role) in [(source, Role::Source), (target, Role::Target)] {
        if cloud.is_empty() {
            return Err(GlobalError::Empty(role));
        }
    }
    let (s, t) = rayon::join(|| Features::compute(source, config), || Features::compute(target, config));
    let s = s.map_err(|error| GlobalError::Features { role: Role::Source, error })?;
    let t = t.map_err(|error| GlobalError::Features { role: Role::Target, error })?;
    let found = estimate(&s, &t, config)?;
    let (fitness, rmse) = fitness(&s.surfels, &t.surfels, &found.transform, config.polish.max_distance);
    Ok(GlobalAlignment {
        transform: found.transform,
        coarse_transform: found.coarse_transform,
        correspondences: found.matches.len(),
        inliers: found.inliers.len(),
        inlier_ratio: found.inlier_ratio(),
        fitness,
        rmse,
        keypoints: (s.keypoints.len(), t.keypoints.len()),
        ransac_iterations: found.ransac_iterations,
    })
}

/// Share of `source` within `gate` of a `target` point after `transform`, and the RMS distance of
/// that share (0 when none is).
fn fitness(source: &Surfels, target: &Surfels, transform: &Isometry3<f64>, gate: f32) -> (f64, f64) {
    let t = transform.cast::<f32>();
    // Collected, then summed in order: the figure does not depend on the thread count.
    let close: Vec<f32> = source
        .points
        .par_iter()
        .filter_map(|p| {
            let q = t * p;
            target
                .tree
                .nearest_within(&[q.x, q.y, q.z], gate_radius(gate))
                .map(|n| n.dist_sq)
                .filter(|&d| d <= gate * gate)
        })
        .collect();
    if close.is_empty() {
        return (0.0, 0.0);
    }
    let mean_sq = close.iter().map(|&d| f64::from(d)).sum::<f64>() / close.len() as f64;
    (close.len() as f64 / source.len() as f64, mean_sq.sqrt())
}
