//! ROS 2 over Zenoh without a bridge: what rmw_zenoh puts on the wire, so that ROS 2 nodes (rviz2,
//! `ros2 topic echo`, a LiDAR driver) and the fleet see each other directly.
//!
//! - [`messages`]: the message types and their CDR payloads.
//! - [`RosType`]: each type's name, DDS name and RIHS01 type hash, which rmw_zenoh puts in every key.
//! - [`keys`]: a topic's data key expression, the liveliness tokens that announce a node and its
//!   publishers (what `ros2 topic list` and rviz2 read), and the attachment (sequence number,
//!   source time, publisher id) every sample carries.
//!
//! Pure: no I/O, no networking (the publishers are `bus::ros2`'s).

pub mod keys;
pub mod messages;

/// A ROS 2 message type as rmw_zenoh names it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RosType {
    /// `package/msg/Name`.
    pub name: &'static str,
    /// The DDS type name: `package::msg::dds_::Name_`.
    pub dds: &'static str,
    /// RIHS01 hash of the type description (REP 2011), the same in Humble, Jazzy and Kilted for
    /// every type here (checked against rosbags' type stores in `tests/tests/ros2_wire.rs`).
    pub hash: &'static str,
}

/// sensor_msgs/msg/PointCloud2.
pub const POINT_CLOUD2: RosType = RosType {
    name: "sensor_msgs/msg/PointCloud2",
    dds: "sensor_msgs::msg::dds_::PointCloud2_",
    hash: "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5",
};

/// nav_msgs/msg/Path.
pub const PATH: RosType = RosType {
    name: "nav_msgs/msg/Path",
    dds: "nav_msgs::msg::dds_::Path_",
    hash: "RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b",
};

/// nav_msgs/msg/Odometry.
pub const ODOMETRY: RosType = RosType {
    name: "nav_msgs/msg/Odometry",
    dds: "nav_msgs::msg::dds_::Odometry_",
    hash: "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
};

/// tf2_msgs/msg/TFMessage.
pub const TF_MESSAGE: RosType = RosType {
    name: "tf2_msgs/msg/TFMessage",
    dds: "tf2_msgs::msg::dds_::TFMessage_",
    hash: "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
};

/// std_msgs/msg/String.
pub const STRING: RosType = RosType {
    name: "std_msgs/msg/String",
    dds: "std_msgs::msg::dds_::String_",
    hash: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
};

/// Every type the fleet publishes or reads.
pub const TYPES: [RosType; 5] = [POINT_CLOUD2, PATH, ODOMETRY, TF_MESSAGE, STRING];
