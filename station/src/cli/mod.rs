//! The commands of `emr-station`, one module per group: [`files`] work on point-cloud files,
//! [`service`] runs or talks to the networked station, [`bench`](mod@bench) times the registration, [`certs`] makes a fleet's certificates.

pub mod bench;
pub mod certs;
pub mod files;
pub mod service;
