//! The commands of `emr-station`, one module per group: [`files`] work on point-cloud files,
//! [`service`] runs or talks to the networked station, [`certs`] makes a fleet's certificates.

pub mod certs;
pub mod files;
pub mod service;
