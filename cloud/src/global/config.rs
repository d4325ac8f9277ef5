//! Settings of the global registration: one struct per step, every radius scaled from one voxel size.

use super::error::FeatureError;
use super::fpfh::FpfhConfig;
use super::harris::HarrisConfig;
use super::matching::MatchingConfig;
use super::normals::{NormalConfig, Orientation};
use super::polish::PolishConfig;
use super::preprocess::PreprocessConfig;
use super::ransac::RansacConfig;

/// Settings of the whole pipeline, one struct per step.
///
/// Each step's own `Default` is the setting for whole robot maps at 0.4 m voxels
/// ([`GlobalConfig::for_resolution`]`(0.4)`, what the station merges with); the default of the
/// whole, [`GlobalConfig::scan`], is for one LiDAR scan.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GlobalConfig {
    /// Step 1.
    pub preprocess: PreprocessConfig,
    /// Step 2.
    pub normals: NormalConfig,
    /// Step 3.
    pub keypoints: HarrisConfig,
    /// Step 4.
    pub descriptors: FpfhConfig,
    /// Step 5.
    pub matching: MatchingConfig,
    /// Step 6.
    pub ransac: RansacConfig,
    /// Step 7; its distance gate is also the one [`super::GlobalAlignment::fitness`] counts with.
    pub polish: PolishConfig,
}

impl Default for GlobalConfig {
    fn default() -> Self {
        Self::scan()
    }
}

impl GlobalConfig {
    /// Every radius scaled from the voxel size `v` (Open3D's tutorial ratios: normals 2v, FPFH 5v);
    /// the counts are each step's defaults, sized for whole robot maps.
    pub fn for_resolution(v: f32) -> Self {
        let vd = f64::from(v);
        Self {
            preprocess: PreprocessConfig { voxel_size: v, min_spacing: 0.5 * v, ..PreprocessConfig::default() },
            normals: NormalConfig {
                radius: 2.0 * v,
                orientation: Orientation::LocalMass { radius: 5.0 * v },
                ..NormalConfig::default()
            },
            keypoints: HarrisConfig { radius: 3.0 * v, nms_radius: v, ..HarrisConfig::default() },
            descriptors: FpfhConfig { radius: 5.0 * v, ..FpfhConfig::default() },
            matching: MatchingConfig::default(),
            ransac: RansacConfig { inlier_distance: 2.5 * vd, min_edge: 2.5 * vd, ..RansacConfig::default() },
            polish: PolishConfig { max_distance: 2.0 * v, ..PolishConfig::default() },
        }
    }

    /// One LiDAR scan against another scan or a local map of a few hundred metres (the default):
    /// [`SCAN_VOXEL`] = 1 m voxels, so normals within 2 m, Harris within 3 m, FPFH and the
    /// orientation's mass within 5 m, RANSAC inliers within 2.5 m, the polish gate 2 m; 2000 to
    /// 5000 keypoints, as for maps.
    ///
    /// A 120k-point HDL-64 scan keeps about 3-4k surfels at 1 m. Measured on the KITTI pairs of
    /// `../shared/data` (08 reverse revisit, 00 scans 0 and 15, a scan onto a map of five others):
    /// 1 m voxels find more RANSAC inliers than finer ones (on the pair 11 m apart 70, against 58 at
    /// 0.75 m and 37 at 0.5 m) in half the time of 0.75 m and a third of 0.5 m, and 20 RANSAC seeds
    /// out of 20 land within 0.3 m; the polish on 1 m surfels leaves 0.05-0.2 m, which fine
    /// registration (GICP) takes from there.
    /// Halving the keypoints saves a fifth of the time and costs 40 % of the inliers.
    pub fn scan() -> Self {
        Self::for_resolution(SCAN_VOXEL)
    }

    /// The largest neighbourhood radius of steps 2-4: the reach of the shared neighbour lists.
    pub fn reach(&self) -> f32 {
        let mass = match self.normals.orientation {
            Orientation::LocalMass { radius } => radius,
            _ => 0.0,
        };
        [self.normals.radius, mass, self.keypoints.radius, self.keypoints.nms_radius, self.descriptors.radius]
            .into_iter()
            .fold(0.0, f32::max)
    }

    /// Checks every step's settings.
    pub fn validate(&self) -> Result<(), FeatureError> {
        self.preprocess.validate()?;
        self.normals.validate()?;
        self.keypoints.validate()?;
        self.descriptors.validate()?;
        self.matching.validate()?;
        self.ransac.validate()?;
        self.polish.validate()
    }
}

/// Voxel edge of [`GlobalConfig::scan`], metres.
pub const SCAN_VOXEL: f32 = 1.0;
