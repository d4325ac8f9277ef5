//! The point-cloud type: xyz in metres plus optional per-point channels, stored as parallel arrays.

use nalgebra::{Isometry3, Point3};

/// Which optional per-point channels a cloud carries.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Channels {
    /// Return strength, in the sensor's own units (KITTI: reflectance 0..1, Velodyne: 0..255).
    pub intensity: bool,
    /// Laser ring (beam) index, 0 = lowest beam.
    pub ring: bool,
    /// Seconds since the start of the sweep at which the point was measured.
    pub time: bool,
}

/// A point cloud: positions in metres and optional channels of the same length.
///
/// Invariant: every present channel has exactly `points.len()` entries and every position is finite.
/// Readers and the codec uphold it; [`PointCloud::validate`] checks it for data built by hand.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    /// Positions, metres, in the frame the cloud was expressed in.
    pub points: Vec<Point3<f32>>,
    /// Intensity per point, if the source had it.
    pub intensity: Option<Vec<f32>>,
    /// Ring (beam) index per point, if known.
    pub ring: Option<Vec<u16>>,
    /// Time within the sweep per point, seconds from the sweep start.
    pub time: Option<Vec<f32>>,
}

/// A channel whose length does not match the number of points, or a non-finite position.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum InvalidCloud {
    /// A channel has a different length from `points`.
    #[error("channel {channel} has {len} values for {points} points")]
    ChannelLength { channel: &'static str, len: usize, points: usize },
    /// A position is NaN or infinite.
    #[error("point {index} is not finite")]
    NonFinite { index: usize },
}

impl PointCloud {
    /// A cloud of bare positions.
    pub fn from_points(points: Vec<Point3<f32>>) -> Self {
        Self { points, ..Self::default() }
    }

    /// An empty cloud with room for `n` points and the given channels.
    pub fn with_capacity(n: usize, channels: Channels) -> Self {
        Self {
            points: Vec::with_capacity(n),
            intensity: channels.intensity.then(|| Vec::with_capacity(n)),
            ring: channels.ring.then(|| Vec::with_capacity(n)),
            time: channels.time.then(|| Vec::with_capacity(n)),
        }
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True when the cloud holds no point.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The channels present.
    pub fn channels(&self) -> Channels {
        Channels { intensity: self.intensity.is_some(), ring: self.ring.is_some(), time: self.time.is_some() }
    }

    /// Positions as plain `[x, y, z]` arrays, without copying (k-d trees and codecs want this).
    pub fn xyz(&self) -> &[[f32; 3]] {
        bytemuck::cast_slice(&self.points)
    }

    /// Appends point `i` of `other` (same channels expected; missing ones are filled with zero).
    pub fn push_from(&mut self, other: &PointCloud, i: usize) {
        self.points.push(other.points[i]);
        if let Some(v) = &mut self.intensity {
            v.push(other.intensity.as_ref().map_or(0.0, |s| s[i]));
        }
        if let Some(v) = &mut self.ring {
            v.push(other.ring.as_ref().map_or(0, |s| s[i]));
        }
        if let Some(v) = &mut self.time {
            v.push(other.time.as_ref().map_or(0.0, |s| s[i]));
        }
    }

    /// The points at `indices`, in that order, with their channels.
    pub fn select(&self, indices: &[usize]) -> PointCloud {
        // Channel by channel: a gather per channel without a branch or capacity check per point
        // (the codec reorders million-point maps through this; a push per point took twice as long).
        fn gather<T: Copy>(values: &[T], indices: &[usize]) -> Vec<T> {
            indices.iter().map(|&i| values[i]).collect()
        }
        PointCloud {
            points: gather(&self.points, indices),
            intensity: self.intensity.as_deref().map(|v| gather(v, indices)),
            ring: self.ring.as_deref().map(|v| gather(v, indices)),
            time: self.time.as_deref().map(|v| gather(v, indices)),
        }
    }

    /// Checks the invariant: channel lengths match and all positions are finite.
    pub fn validate(&self) -> Result<(), InvalidCloud> {
        let n = self.points.len();
        let lens = [
            ("intensity", self.intensity.as_ref().map(Vec::len)),
            ("ring", self.ring.as_ref().map(Vec::len)),
            ("time", self.time.as_ref().map(Vec::len)),
        ];
        for (channel, len) in lens {
            if let Some(len) = len.filter(|&l| l != n) {
                return Err(InvalidCloud::ChannelLength { channel, len, points: n });
            }
        }
        match self.points.iter().position(|p| !p.coords.iter().all(|c| c.is_finite())) {
            Some(index) => Err(InvalidCloud::NonFinite { index }),
            None => Ok(()),
        }
    }

    /// Drops points with a NaN or infinite coordinate (and their channel values); returns how many.
    pub fn retain_finite(&mut self) -> usize {
        let keep: Vec<usize> =
            (0..self.len()).filter(|&i| self.points[i].coords.iter().all(|c| c.is_finite())).collect();
        let dropped = self.len() - keep.len();
        if dropped > 0 {
            *self = self.select(&keep);
        }
        dropped
    }

    /// The cloud with every point mapped by `pose` (channels unchanged).
    pub fn transformed(&self, pose: &Isometry3<f32>) -> PointCloud {
        PointCloud { points: self.points.iter().map(|p| pose * p).collect(), ..self.clone() }
    }

    /// Appends all points of `other`; channels absent from `other` are filled with zero.
    pub fn extend(&mut self, other: &PointCloud) {
        for i in 0..other.len() {
            self.push_from(other, i);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn retain_finite_drops_bad_points_with_their_channels() {
        let mut c = PointCloud::with_capacity(3, Channels { intensity: true, ..Default::default() });
        c.points =
            vec![Point3::new(1.0, 2.0, 3.0), Point3::new(f32::NAN, 0.0, 0.0), Point3::new(4.0, 5.0, f32::INFINITY)];
        c.intensity = Some(vec![0.1, 0.2, 0.3]);
        assert_eq!(c.retain_finite(), 2);
        assert_eq!(c.points, vec![Point3::new(1.0, 2.0, 3.0)]);
        assert_eq!(c.intensity, Some(vec![0.1]));
        c.validate().unwrap();
    }

    #[test]
    fn validate_reports_channel_length() {
        let mut c = PointCloud::from_points(vec![Point3::origin(); 2]);
        c.ring = Some(vec![1]);
        assert_eq!(c.validate(), Err(InvalidCloud::ChannelLength { channel: "ring", len: 1, points: 2 }));
    }

    #[test]
    fn xyz_view_matches_points() {
        let c = PointCloud::from_points(vec![Point3::new(1.0, 2.0, 3.0), Point3::new(4.0, 5.0, 6.0)]);
        assert_eq!(c.xyz(), &[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    }
}
