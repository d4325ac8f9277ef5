//! What the workspace's tests share: a seeded generator for reproducible synthetic data, a
//! synthetic place, pose builders, a pose comparison, and the locator of the real LiDAR data.

mod data;
mod pose;
mod rng;
mod scene;

pub use data::shared_data;
pub use pose::{check_pose_close, pose_from_axis_angle, pose_from_yaw_deg};
pub use rng::Rng;
pub use scene::{boxes_around, yard, yard_seen_then_whole, yards_sharing_one};
