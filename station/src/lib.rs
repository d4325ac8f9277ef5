//! EMR-FLOAM central station library: the map-merging computations behind `emr-station`.
//!
//! [`pairwise`] aligns two robot maps without an initial guess (map_merge_3d's global registration).
//! [`merge`] fuses N maps into one global map along a maximum spanning tree of pairwise estimates.
//! [`service`] is the networked station (`emr-station run`); [`demo`] runs edges and a station in one
//! process. Only those two touch the network.

pub mod demo;
pub mod fleet_load;
pub mod merge;
pub mod pairwise;
pub mod service;
