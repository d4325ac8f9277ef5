//! The EMR-FLOAM wire format: protobuf messages (package `emr.v1`), the Zenoh key-expression scheme
//! and the point-cloud codec.
//!
//! The messages are generated from `proto/emr/v1/messages.proto` at build time (protox + prost-build,
//! no protoc needed); subscribers in other languages compile the same file with their own toolchain.

pub mod codec;
pub mod keyexpr;
mod pose;
pub mod ros2;
mod scan_context;
mod timestamp;

pub use keyexpr::{Fleet, Topic};
pub use pose::InvalidPose;
pub use scan_context::InvalidScanContext;

/// Generated message types of package `emr.v1`.
pub mod v1 {
    include!(concat!(env!("OUT_DIR"), "/emr.v1.rs"));
}

pub use v1::*;
