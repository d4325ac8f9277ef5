//! The topics every program publishes (see [`crate::topics`]), one method each.

use cloud::PointCloud;
use foxglove::messages::{Color, FrameTransforms};
use nalgebra::{Isometry3, Point3};
use serde_json::Value;

use crate::{Kind, Live, Stamp, convert, topics};

/// Colour of loop-edge lines (orange: stands out on the default dark background).
const LOOP_COLOR: Color = Color { r: 1.0, g: 0.55, b: 0.0, a: 1.0 };

impl Live {
    /// The global map in `map`, each point labelled with the robot it came from (`robots`, one
    /// per point; the field is left out when the lengths differ).
    pub fn map(&self, cloud: &PointCloud, robots: &[u32], stamp: Stamp) {
        self.publish(topics::MAP, Kind::Latched, stamp, || {
            convert::point_cloud(
                topics::MAP_FRAME,
                &Isometry3::identity(),
                &cloud.points,
                Some(robots),
                stamp.timestamp(),
            )
        });
    }

    /// Frames placed in `parent`: `(child, transform)` pairs, the transform mapping child points
    /// into the parent frame. Latched or streamed as the caller's frames are a state or per scan.
    pub fn frames(&self, parent: &str, frames: &[(String, Isometry3<f64>)], kind: Kind, stamp: Stamp) {
        self.publish(topics::TF, kind, stamp, || FrameTransforms {
            transforms: frames
                .iter()
                .map(|(child, iso)| convert::frame_transform(parent, child, iso, stamp.timestamp()))
                .collect(),
        });
    }

    /// A keyframe of `robot` as it arrives: its cloud (sensor frame) placed at `pose` in the
    /// robot's odometry frame.
    pub fn keyframe(&self, robot: u32, pose: &Isometry3<f64>, cloud: &PointCloud, stamp: Stamp) {
        self.publish(&topics::keyframe(robot), Kind::Stream, stamp, || {
            convert::point_cloud(&topics::robot_frame(robot), pose, &cloud.points, None, stamp.timestamp())
        });
    }

    /// The trajectory of `robot`: its keyframe poses in its odometry frame.
    pub fn trajectory(&self, robot: u32, poses: &[Isometry3<f64>], stamp: Stamp) {
        self.publish(&topics::trajectory(robot), Kind::Latched, stamp, || {
            convert::poses_in_frame(&topics::robot_frame(robot), poses, stamp.timestamp())
        });
    }

    /// The loop edges of `robot`: a line between the two keyframe positions of each loop.
    pub fn loops(&self, robot: u32, segments: &[[Point3<f64>; 2]], stamp: Stamp) {
        let frame = topics::robot_frame(robot);
        self.publish(&topics::loops(robot), Kind::Latched, stamp, || {
            convert::lines(&frame, &format!("{frame}/loops"), segments, LOOP_COLOR, stamp.timestamp())
        });
    }

    /// The status of `robot` (JSON).
    pub fn robot_status(&self, robot: u32, stamp: Stamp, status: impl FnOnce() -> Value) {
        self.publish_json(&topics::status(robot), Kind::Latched, stamp, status);
    }

    /// The station's status (JSON).
    pub fn station_status(&self, stamp: Stamp, status: impl FnOnce() -> Value) {
        self.publish_json(topics::STATION_STATUS, Kind::Latched, stamp, status);
    }
}
