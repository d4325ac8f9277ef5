//! The robot on ROS 2 (`emr-edge run --ros2`): its odometry and keyframe clouds as rmw_zenoh
//! topics, for the robot's own ROS 2 stack, with no bridge.
//!
//! | topic | type | what |
//! |---|---|---|
//! | `/emr/FLEET/robotN/odometry` | nav_msgs/Odometry | each scan's sensor pose, frame `robotN/odom`, child `robotN/lidar` |
//! | `/emr/FLEET/robotN/keyframe` | sensor_msgs/PointCloud2 | each keyframe's cloud (x y z intensity), in frame `robotN/odom` |
//!
//! Both reliable and volatile (ROS 2's default QoS); FLEET is the fleet's name with `-` written `_`.
//! The station's `/tf` places `robotN/odom` in `map`.

use bus::ros2::{Ros2Node, Ros2Publisher, name_token};
use cloud::PointCloud;
use nalgebra::Isometry3;
use proto::Fleet;
use proto::ros2::keys::{Qos, TopicName};
use proto::ros2::messages::{Header, Odometry, PointCloud2, PoseWithCovariance, Time, xyzi_cloud};
use proto::ros2::{ODOMETRY, POINT_CLOUD2};
use tracing::warn;
use zenoh::Session;

use super::NodeError;

/// The robot's ROS 2 node and publishers.
pub(super) struct EdgeRos2 {
    _node: Ros2Node,
    robot: u32,
    odometry: Ros2Publisher<Odometry>,
    keyframes: Ros2Publisher<PointCloud2>,
}

impl EdgeRos2 {
    /// Declares node `emr_edge` in namespace `/emr/FLEET/robotN` of ROS domain `domain`.
    pub(super) async fn declare(session: &Session, fleet: &Fleet, robot: u32, domain: u32) -> Result<Self, NodeError> {
        let namespace = format!("/emr/{}/robot{robot}", name_token(fleet.as_str()));
        let topic = |name: &str| {
            TopicName::new(&format!("{namespace}/{name}")).map_err(|e| NodeError::Ros2(format!("fleet {fleet}: {e}")))
        };
        let ros2 = |e: bus::ros2::Ros2Error| NodeError::Ros2(e.to_string());
        let node = Ros2Node::new(session, domain, &namespace, "emr_edge").await.map_err(ros2)?;
        let odometry = node.publisher(&topic("odometry")?, ODOMETRY, Qos::DEFAULT).await.map_err(ros2)?;
        let keyframes = node.publisher(&topic("keyframe")?, POINT_CLOUD2, Qos::DEFAULT).await.map_err(ros2)?;
        Ok(EdgeRos2 { _node: node, robot, odometry, keyframes })
    }

    /// A scan's sensor pose (sweep end) in the odometry frame; `stamp` is the sweep's, seconds.
    pub(super) async fn odometry(&self, stamp: f64, pose: &Isometry3<f64>) {
        let message = Odometry {
            header: Header { stamp: Time::from_secs_f64(stamp), frame_id: odom_frame(self.robot) },
            child_frame_id: format!("robot{}/lidar", self.robot),
            pose: PoseWithCovariance { pose: pose.into(), ..PoseWithCovariance::default() },
            ..Odometry::default()
        };
        if let Err(e) = self.odometry.put(&message).await {
            warn!("{e}");
        }
    }

    /// A keyframe's cloud (sensor frame at `pose`), published in the odometry frame.
    pub(super) async fn keyframe(&self, stamp: f64, pose: &Isometry3<f64>, cloud: &PointCloud) {
        let pose = pose.cast::<f32>();
        let rows = cloud.points.iter().enumerate().map(|(i, p)| {
            let q = pose * p;
            let intensity = cloud.intensity.as_ref().map_or(0.0, |v| v[i]);
            ([q.x, q.y, q.z, intensity], Vec::new())
        });
        let header = Header { stamp: Time::from_secs_f64(stamp), frame_id: odom_frame(self.robot) };
        if let Err(e) = self.keyframes.put(&xyzi_cloud(header, &[], rows)).await {
            warn!("{e}");
        }
    }
}

/// Robot `robot`'s odometry frame (the station's `/tf` child).
fn odom_frame(robot: u32) -> String {
    format!("robot{robot}/odom")
}
