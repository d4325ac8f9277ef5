//! The robot side of EMR-FLOAM: scan sources (simulator and recordings), odometry, keyframes, loop
//! closure and the keyframe pose graph.

pub mod args;
pub mod keyframe;
pub mod live_sensor;
pub mod live_view;
pub mod loops;
pub mod node;
pub mod odometry;
pub mod packets;
pub mod recording;
pub mod ros2_topic;
pub mod source;
pub mod wire;
