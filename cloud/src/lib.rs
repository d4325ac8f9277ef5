//! Point clouds shared by the edge and the station.
//!
//! Everything here is pure computation on in-memory data, except [`formats`], whose parsers work on
//! byte slices and whose thin `read_*`/`write_*` wrappers are the only functions that touch files.

pub mod alignment;
pub mod changed;
pub mod confidence;
pub mod eigen3;
pub mod formats;
pub mod gauss_newton;
pub mod global;
pub mod kdtree;
pub mod memory;
pub mod moments;
pub mod ordered_tree;
pub mod point_cloud;
pub mod pose_graph;
pub mod preset;
pub mod registration;
pub mod scan_context;
pub mod se3;
pub mod stats;
pub mod stopwatch;
pub mod trajectory;
pub mod visibility;
pub mod voxel;

pub use point_cloud::{Channels, PointCloud};
pub use preset::Preset;
