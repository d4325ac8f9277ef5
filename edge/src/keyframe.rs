//! A keyframe: what the odometry hands to the loop closure and to the wire.

use cloud::PointCloud;
use nalgebra::Isometry3;

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
