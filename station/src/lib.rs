//! EMR-FLOAM central station library: the map-merging computations behind `emr-station`.
//!
//! [`pairwise`] aligns two robot maps without an initial guess (`cloud::global`, map_merge_3d's global
//! registration) and judges whether the alignment is reliable enough to merge.
//! [`merge`] fuses N maps into one global map along a maximum spanning tree of pairwise estimates.
//! [`joint`] optimises the merged robots' keyframes in one pose graph, so robots correct each other's drift.
//! [`service`] is the networked station (`emr-station run`), the only part that touches the network.
//! [`access`] makes a fleet's certificates and the zenoh configurations that let only its members in.
//! The station knows nothing of the robots' code: it sees them only through their messages.

pub mod access;
pub mod joint;
pub mod merge;
pub mod pairwise;
pub mod service;
