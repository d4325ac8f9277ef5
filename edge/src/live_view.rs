//! One robot's live view (`emr-edge odometry --record`): per scan its sensor frame, per keyframe
//! its cloud, the keyframe trajectory and, with loop closure, the loops; on the topics of
//! [`live::topics`], so an edge recording and the station's look alike.

use std::sync::Arc;

use live::{Kind, Live, Stamp, topics};
use nalgebra::{Isometry3, Point3};
use serde_json::json;

use crate::odometry::pipeline::ScanDone;

/// How many times the trajectory is published over a run's keyframes, at most, besides after
/// each optimisation: publishing it at every keyframe would make a recording quadratic in length.
const TRAJECTORY_UPDATES: usize = 20;

/// Publishes one robot's odometry to a [`Live`].
pub struct EdgeView {
    live: Arc<Live>,
    robot: u32,
    /// Keyframe odometry poses so far (the trajectory without loop closure).
    keyframes: Vec<Isometry3<f64>>,
    /// The loop closure's optimisation count last published.
    revision: u64,
}

impl EdgeView {
    /// A view of robot `robot` (names its topics and frames) publishing to `live`.
    pub fn new(live: Arc<Live>, robot: u32) -> Self {
        EdgeView { live, robot, keyframes: Vec::new(), revision: 0 }
    }

    /// One scan done.
    pub fn scan(&mut self, done: &ScanDone<'_>) {
        let (robot, stamp) = (self.robot, Stamp::Seconds(done.stamp));
        let sensor = [(topics::sensor_frame(robot), done.frame.pose)];
        self.live.frames(&topics::robot_frame(robot), &sensor, Kind::Stream, stamp);
        let Some(keyframe) = &done.frame.keyframe else { return };
        self.live.keyframe(robot, &keyframe.pose, &keyframe.cloud, stamp);
        self.keyframes.push(keyframe.pose);
        let revision = done.loops.map_or(0, |t| t.closer().revision());
        let k = self.keyframes.len();
        if revision != self.revision || k.is_multiple_of((k / TRAJECTORY_UPDATES).max(1)) {
            self.revision = revision;
            self.shape(done, stamp);
        }
        self.live.robot_status(robot, stamp, || {
            json!({
                "robot": robot,
                "scans": done.scans,
                "keyframes": k,
                "loops": done.loops.map_or(0, |t| t.closer().loops().count()),
                "lost": done.frame.lost,
                "degenerate": done.frame.degenerate,
            })
        });
    }

    /// The trajectory (optimised with loop closure) and the loop lines.
    fn shape(&self, done: &ScanDone<'_>, stamp: Stamp) {
        let Some(track) = done.loops else {
            return self.live.trajectory(self.robot, &self.keyframes, stamp);
        };
        let poses = track.closer().poses();
        self.live.trajectory(self.robot, poses, stamp);
        let position = |k: usize| -> Option<Point3<f64>> { poses.get(k).map(|p| p.translation.vector.into()) };
        let segments: Vec<_> = track.closer().loops().filter_map(|l| Some([position(l.a)?, position(l.b)?])).collect();
        self.live.loops(self.robot, &segments, stamp);
    }
}
