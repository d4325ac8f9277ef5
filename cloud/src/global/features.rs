//! Steps 1-4 on one cloud: what registration needs of it, computed once however many clouds it is
//! matched against.

use std::time::Duration;

use nalgebra::Point3;

use super::config::GlobalConfig;
use super::error::FeatureError;
use super::fpfh::{self, Fpfh};
use super::normals::{self, Surfels};
use super::{harris, preprocess};
use crate::PointCloud;
use crate::memory::{HeapSize, vec_bytes};
use crate::stopwatch::Stopwatch;

/// Wall time of the per-cloud steps.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FeatureTiming {
    /// Step 1.
    pub preprocess: Duration,
    /// Step 2.
    pub normals: Duration,
    /// Step 3.
    pub keypoints: Duration,
    /// Step 4.
    pub descriptors: Duration,
}

impl FeatureTiming {
    /// Sum of the four steps.
    pub fn total(&self) -> Duration {
        self.preprocess + self.normals + self.keypoints + self.descriptors
    }
}

/// Steps 1-4 of one cloud: surfels, keypoints and their descriptors.
pub struct Features {
    /// Downsampled, filtered points with normals (and their k-d tree); their neighbourhood lists
    /// are released once the features are made.
    pub surfels: Surfels,
    /// Indices into `surfels` of the keypoints that have a descriptor.
    pub keypoints: Vec<usize>,
    /// FPFH of each keypoint.
    pub descriptors: Vec<Fpfh>,
    /// Time spent per step.
    pub timing: FeatureTiming,
}

impl HeapSize for Features {
    fn heap_bytes(&self) -> usize {
        self.surfels.heap_bytes() + vec_bytes(&self.keypoints) + vec_bytes(&self.descriptors)
    }
}

impl Features {
    /// Runs steps 1-4 on `cloud`.
    pub fn compute(cloud: &PointCloud, config: &GlobalConfig) -> Result<Self, FeatureError> {
        config.validate()?;
        let mut timing = FeatureTiming::default();
        let mut watch = Stopwatch::start();
        let filtered = preprocess::preprocess(cloud, &config.preprocess)?;
        timing.preprocess = watch.lap();
        let surfels = normals::estimate_normals(&filtered, &config.normals, config.reach())?;
        timing.normals = watch.lap();
        let with_normals = surfels.with_normals();
        if with_normals < config.preprocess.min_points.max(3) {
            return Err(FeatureError::TooFewPoints {
                stage: "normal estimation",
                points: with_normals,
                needed: config.preprocess.min_points.max(3),
            });
        }
        let candidates = harris::detect_keypoints(&surfels, &config.keypoints);
        timing.keypoints = watch.lap();
        let described = fpfh::fpfh_at(&surfels, &candidates, &config.descriptors);
        let (keypoints, descriptors): (Vec<usize>, Vec<Fpfh>) =
            candidates.iter().zip(described).filter_map(|(&i, d)| Some((i, d?))).unzip();
        timing.descriptors = watch.lap();
        if keypoints.len() < 3 {
            return Err(FeatureError::TooFewPoints { stage: "descriptors", points: keypoints.len(), needed: 3 });
        }
        // Matching, RANSAC, scoring and polishing use the points, normals and tree only.
        let mut surfels = surfels;
        surfels.neighbourhoods.release();
        Ok(Self { surfels, keypoints, descriptors, timing })
    }

    /// Position of keypoint `k` (an index into [`Features::keypoints`]).
    pub fn keypoint(&self, k: usize) -> Point3<f32> {
        self.surfels.points[self.keypoints[k]]
    }

    /// Positions of all keypoints.
    pub fn keypoint_positions(&self) -> Vec<Point3<f32>> {
        (0..self.keypoints.len()).map(|k| self.keypoint(k)).collect()
    }
}
