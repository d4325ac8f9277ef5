//! The station's live view (`emr-station run --foxglove`, `--record`): what it holds and merges,
//! published on the topics of [`live::topics`] as it changes. Only built when a [`Live`] is given
//! ([`super::StationConfig::live`]); with no client subscribed and no recording, the streamed
//! topics build nothing.
//!
//! The topics have one frame per robot: a robot that restarted is shown by its newest session.

use std::collections::BTreeMap;
use std::sync::Arc;

use live::{Kind, Live, Stamp, topics};
use nalgebra::{Isometry3, Point3};
use proto::{GlobalMap, MergeStatus, StationStatus};
use serde_json::json;

use super::client::memory_mb;
use super::fleet_state::{FleetState, Member, ReceivedKeyframe, RobotState};
use super::ingest::LoopEdge;
use super::merge_job::MapCloud;

/// Publishes the station's state to a [`Live`].
pub struct StationView {
    live: Arc<Live>,
    /// Loop edges of each robot's newest pose graph.
    loops: BTreeMap<u32, Vec<LoopEdge>>,
}

impl StationView {
    /// A view publishing to `live`.
    pub fn new(live: Arc<Live>) -> Self {
        StationView { live, loops: BTreeMap::new() }
    }

    /// A keyframe the station had not held (held already: `state` has it), of the robot's newest
    /// session.
    pub fn keyframe(&self, kf: &ReceivedKeyframe, state: &FleetState) {
        if state.newest_session(kf.robot) == Some(kf.member()) {
            self.live.keyframe(kf.robot, &kf.odom_pose, &kf.cloud, Stamp::Now);
        }
    }

    /// A pose-graph update of a robot session that changed its poses: its trajectory and loop
    /// edges, when it is the robot's newest session.
    pub fn poses(&mut self, member: Member, loops: Vec<LoopEdge>, state: &FleetState) {
        if state.newest_session(member.robot) != Some(member) {
            return;
        }
        self.loops.insert(member.robot, loops);
        if let Some(r) = state.robot(member) {
            self.robot_shape(member.robot, r);
        }
    }

    /// A published global map: the map, the robots' frames, trajectories, loops and statuses.
    pub fn map(&self, map: &GlobalMap, cloud: &MapCloud, state: &FleetState) {
        self.live.map(&cloud.cloud, &cloud.robots, Stamp::Now);
        let newest =
            |p: &&proto::RobotPlacement| state.newest_session(p.robot) == Some(Member::new(p.robot, p.session));
        let placed: Vec<(String, Isometry3<f64>)> = map
            .robots
            .iter()
            .filter(newest)
            .filter(|p| p.status() == MergeStatus::Merged)
            .filter_map(|p| Some((topics::robot_frame(p.robot), Isometry3::try_from(p.transform.as_ref()?).ok()?)))
            .collect();
        self.live.frames(topics::MAP_FRAME, &placed, Kind::Latched, Stamp::Now);
        for placement in map.robots.iter().filter(newest) {
            let robot = placement.robot;
            let held = state.robot(Member::new(robot, placement.session));
            self.live.robot_status(robot, Stamp::Now, || {
                json!({
                    "robot": robot,
                    "session": placement.session,
                    "revision": map.revision,
                    "status": if placement.status() == MergeStatus::Merged { "merged" } else { "unmerged" },
                    "confidence": placement.confidence,
                    "keyframes_in_map": placement.keyframes,
                    "keyframes_held": held.map_or(0, |r| r.keyframes().len()),
                    "pose_revision": held.and_then(RobotState::pose_revision),
                    "loops": self.loops.get(&robot).map_or(0, Vec::len),
                    "reference": robot == map.reference_robot && placement.session == map.reference_session,
                })
            });
            if let Some(r) = held {
                self.robot_shape(robot, r);
            }
        }
    }

    /// The station's periodic status.
    pub fn status(&self, status: &StationStatus, merges: u64) {
        self.live.station_status(Stamp::Now, || {
            json!({
                "fleet": status.fleet,
                "robots": status.robots,
                "keyframes": status.keyframes,
                "merge_queue_depth": status.merge_queue_depth,
                "merges": merges,
                "last_merge_ms": status.last_merge_ms,
                "estimating": status.estimating,
                "last_round_ms": status.last_round_ms,
                "global_map_revision": status.global_map_revision,
                "malformed_payloads": status.malformed_payloads,
                "memory_mb": memory_mb(&status.memory),
            })
        });
    }

    /// A robot's trajectory and loop lines at its best poses.
    fn robot_shape(&self, robot: u32, r: &RobotState) {
        let poses: Vec<Isometry3<f64>> = r.keyframes().keys().filter_map(|&seq| r.pose(seq)).collect();
        self.live.trajectory(robot, &poses, Stamp::Now);
        let position = |seq| -> Option<Point3<f64>> { r.pose(seq).map(|p| p.translation.vector.into()) };
        let segments: Vec<_> = self
            .loops
            .get(&robot)
            .into_iter()
            .flatten()
            .filter_map(|l| Some([position(l.from)?, position(l.to)?]))
            .collect();
        self.live.loops(robot, &segments, Stamp::Now);
    }
}
