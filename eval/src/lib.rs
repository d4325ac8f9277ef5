//! Everything that measures rather than serves: the odometry's robustness matrix ([`robustness`],
//! beside KISS-ICP), the station under a simulated fleet's load ([`load`], with the joint pose
//! graph's figures in [`joint`]), the paper's four systems through the demo ([`report`]), and the
//! micro-benchmarks of the shared kit: registration ([`registration`]), global registration
//! ([`global`]), the station's pairwise merge ([`merge`]) and the simulator ([`simulator`]).
//! The settings page is rendered and checked by [`settings`]. Percentiles come from [`cloud::stats`], as the product's own figures do.

pub mod global;
pub mod joint;
pub mod load;
pub mod merge;
pub mod registration;
pub mod report;
pub mod robustness;
pub mod settings;
pub mod simulator;
