//! The robot side as its users meet it, one test binary (one link instead of one per file):
//! each module is a topic, its tests against ground truth, reference decoders or real recordings.

mod capture;
mod cli_convert;
mod cli_live;
mod cli_odometry;
mod cli_packets;
mod cli_posegraph;
mod cli_sim;
mod loops;
mod node;
mod odometry_aloam;
mod odometry_degeneracy;
mod odometry_kitti;
mod odometry_sim;
mod packets_ouster;
mod packets_velodyne;
mod recordings;
mod ros2_source;
mod sim_packets;
