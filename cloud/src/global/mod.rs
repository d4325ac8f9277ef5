//! Global registration without an initial guess: FPFH features at Harris 3D keypoints, matched and
//! verified by RANSAC (the pipeline of map_merge_3d, Hörner 2016, made faster and more robust).
//! The station merges robot maps with it.
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
//! on two clouds' features. The transform maps SOURCE points into the TARGET frame; fine
//! registration (GICP / VGICP in [`crate::registration`]) is left to the caller. Bad input (empty
//! clouds, a few points, only NaN, identical points) gives an error, never a panic; the sampler is
//! seeded, so a call repeats exactly.

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

pub use config::GlobalConfig;
pub use error::FeatureError;
pub use estimate::{Estimate, EstimateTiming, NoModel, estimate};
pub use features::{FeatureTiming, Features};
pub use fpfh::{Fpfh, FpfhConfig};
pub use harris::HarrisConfig;
pub use matching::{Correspondence, MatchingConfig};
pub use normals::{NormalConfig, Orientation, Surfels};
pub use polish::PolishConfig;
pub use preprocess::{OutlierFilter, PreprocessConfig};
pub use ransac::RansacConfig;
