//! The station on ROS 2 (`emr-station run --ros2`): what it merges, as rmw_zenoh topics that rviz2
//! and any ROS 2 node using rmw_zenoh see with no bridge.
//!
//! | topic | type | QoS | what |
//! |---|---|---|---|
//! | `/emr/FLEET/map` | sensor_msgs/PointCloud2 | reliable, transient local, depth 1 | the global map in frame `map`: x y z intensity (float32), robot and session (uint32) per point |
//! | `/emr/FLEET/robotN/path` | nav_msgs/Path | reliable, transient local, depth 1 | robot N's keyframe poses at their best estimate, frame `robotN/odom` |
//! | `/tf` | tf2_msgs/TFMessage | reliable, volatile | `map` -> `robotN/odom` of each placed robot, every status period |
//! | `/emr/FLEET/status` | std_msgs/String | reliable, volatile | the station's status as JSON, every status period |
//!
//! FLEET is the fleet's name with `-` written `_`. A robot that restarted is shown by its newest
//! session, as in the live view; the map's points carry their session.

use std::collections::BTreeMap;

use bus::ros2::{Ros2Error, Ros2Node, Ros2Publisher, name_token};
use nalgebra::Isometry3;
use proto::ros2::keys::{Qos, TopicName};
use proto::ros2::messages::{
    Header, Path, PointCloud2, PoseStamped, StringMessage, TfMessage, Time, TransformStamped, xyzi_cloud,
};
use proto::ros2::{PATH, POINT_CLOUD2, STRING, TF_MESSAGE};
use proto::{Fleet, GlobalMap, MergeStatus, StationStatus};
use serde_json::json;
use tracing::warn;
use zenoh::Session;

use super::fleet_state::{FleetState, Member};
use super::merge_job::MapCloud;

/// The global map's frame.
pub const MAP_FRAME: &str = "map";

/// Robot `robot`'s odometry frame.
pub fn odom_frame(robot: u32) -> String {
    format!("robot{robot}/odom")
}

/// The label of points whose robot or session is not known (a map reloaded from the database,
/// which keeps no labels).
pub const UNKNOWN: u32 = u32::MAX;

/// The station's ROS 2 node and publishers.
pub struct StationRos2 {
    node: Ros2Node,
    namespace: String,
    map: Ros2Publisher<PointCloud2>,
    status: Ros2Publisher<StringMessage>,
    tf: Ros2Publisher<TfMessage>,
    paths: BTreeMap<u32, Ros2Publisher<Path>>,
    /// Each placed robot's newest session and its placement, as of the last map.
    placed: Vec<(u32, Isometry3<f64>)>,
}

/// Why the station's ROS 2 topics could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum StationRos2Error {
    /// The fleet's name makes no ROS 2 topic name.
    #[error("fleet {fleet}: {source}")]
    Name {
        /// The fleet.
        fleet: String,
        /// Why.
        source: proto::ros2::keys::NameError,
    },
    /// A node, publisher or token could not be declared.
    #[error(transparent)]
    Declare(#[from] Ros2Error),
}

impl StationRos2 {
    /// Declares node `emr_station` and its topics in ROS domain `domain`.
    pub async fn declare(session: &Session, fleet: &Fleet, domain: u32) -> Result<Self, StationRos2Error> {
        let namespace = format!("/emr/{}", name_token(fleet.as_str()));
        let topic = |name: &str| {
            TopicName::new(&format!("{namespace}/{name}"))
                .map_err(|source| StationRos2Error::Name { fleet: fleet.to_string(), source })
        };
        let node = Ros2Node::new(session, domain, &namespace, "emr_station").await?;
        let map = node.publisher(&topic("map")?, POINT_CLOUD2, Qos::LATCHED).await?;
        let status = node.publisher(&topic("status")?, STRING, Qos::DEFAULT).await?;
        let tf = node.publisher(&TopicName::new("/tf").expect("a valid name"), TF_MESSAGE, Qos::DEFAULT).await?;
        Ok(StationRos2 { node, namespace, map, status, tf, paths: BTreeMap::new(), placed: Vec::new() })
    }

    /// A published global map: its points, each placed robot's path, and the placements on /tf.
    pub async fn map(&mut self, map: &GlobalMap, cloud: &MapCloud, state: &FleetState) {
        let stamp = map.stamp.as_ref().map(Time::from).unwrap_or_default();
        let message = map_cloud(cloud, stamp);
        if let Err(e) = self.map.put(&message).await {
            warn!("{e}");
        }
        let newest =
            |p: &&proto::RobotPlacement| state.newest_session(p.robot) == Some(Member::new(p.robot, p.session));
        self.placed = map
            .robots
            .iter()
            .filter(newest)
            .filter(|p| p.status() == MergeStatus::Merged)
            .filter_map(|p| Some((p.robot, Isometry3::try_from(p.transform.as_ref()?).ok()?)))
            .collect();
        for placement in map.robots.iter().filter(newest) {
            self.path(placement.robot, state, stamp).await;
        }
        self.transforms(stamp).await;
    }

    /// The station's periodic status, and the placements again (a transform is valid for a time:
    /// tf listeners need them repeated).
    pub async fn status(&self, status: &StationStatus) {
        let text = json!({
            "fleet": status.fleet,
            "robots": status.robots,
            "keyframes": status.keyframes,
            "merge_queue_depth": status.merge_queue_depth,
            "last_merge_ms": status.last_merge_ms,
            "estimating": status.estimating,
            "global_map_revision": status.global_map_revision,
            "malformed_payloads": status.malformed_payloads,
        });
        if let Err(e) = self.status.put(&StringMessage { data: text.to_string() }).await {
            warn!("{e}");
        }
        let stamp = status.stamp.as_ref().map(Time::from).unwrap_or_default();
        self.transforms(stamp).await;
    }

    /// Robot `robot`'s newest session's keyframe poses, in its odometry frame.
    async fn path(&mut self, robot: u32, state: &FleetState, stamp: Time) {
        let Some(r) = state.newest_session(robot).and_then(|m| state.robot(m)) else { return };
        let frame = odom_frame(robot);
        let poses = r
            .keyframes()
            .keys()
            .filter_map(|&seq| r.pose(seq))
            .map(|pose| PoseStamped { header: Header { stamp, frame_id: frame.clone() }, pose: (&pose).into() })
            .collect();
        let message = Path { header: Header { stamp, frame_id: frame }, poses };
        if !self.paths.contains_key(&robot) {
            let declared = match TopicName::new(&format!("{}/robot{robot}/path", self.namespace)) {
                Ok(topic) => self.node.publisher(&topic, PATH, Qos::LATCHED).await.map_err(|e| e.to_string()),
                Err(e) => Err(e.to_string()),
            };
            match declared {
                Ok(p) => drop(self.paths.insert(robot, p)),
                Err(e) => return warn!("robot {robot}'s path: {e}"),
            }
        }
        if let Err(e) = self.paths[&robot].put(&message).await {
            warn!("{e}");
        }
    }

    async fn transforms(&self, stamp: Time) {
        if self.placed.is_empty() {
            return;
        }
        let transforms = self
            .placed
            .iter()
            .map(|(robot, placement)| TransformStamped {
                header: Header { stamp, frame_id: MAP_FRAME.into() },
                child_frame_id: odom_frame(*robot),
                transform: placement.into(),
            })
            .collect();
        if let Err(e) = self.tf.put(&TfMessage { transforms }).await {
            warn!("{e}");
        }
    }
}

/// The map's points with their intensity (0 where the map has none), robot and session.
fn map_cloud(cloud: &MapCloud, stamp: Time) -> PointCloud2 {
    let points = &cloud.cloud.points;
    let label = |labels: &[u32], i: usize| labels.get(i).copied().unwrap_or(UNKNOWN);
    let rows = (0..points.len()).map(|i| {
        let p = points[i];
        let intensity = cloud.cloud.intensity.as_ref().map_or(0.0, |v| v[i]);
        ([p.x, p.y, p.z, intensity], vec![label(&cloud.robots, i), label(&cloud.sessions, i)])
    });
    xyzi_cloud(Header { stamp, frame_id: MAP_FRAME.into() }, &["robot", "session"], rows)
}
