//! Who may join a fleet and what each member may say: zenoh's mutual TLS with a fleet CA, and the
//! router's access control that ties every certificate to its own key expressions.
//!
//! [`certs`] issues the fleet's certificates: a CA, the router's server certificate, the station's
//! and one per robot. A certificate's common name says who it is ([`Member::common_name`]), and
//! that name is all the router's access control looks at.
//!
//! [`zenoh_config`] writes the zenoh configurations that use them: the router's (TLS with client
//! certificates required, plain TCP only for read-only tools, the access-control rules) and one per
//! member (client mode, its own certificate). Everything here is pure: the `certs` command writes
//! the files.

pub mod certs;
pub mod zenoh_config;

use std::fmt;

use proto::Fleet;

/// One member of a fleet, as its certificate names it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Member {
    /// The zenoh router every other member connects to.
    Router,
    /// The station.
    Station,
    /// Robot `id`.
    Robot(u32),
}

impl Member {
    /// The certificate's common name: `emr-{fleet}-router`, `emr-{fleet}-station`,
    /// `emr-{fleet}-robot-{id}`. The fleet is part of it, so a certificate of one fleet grants
    /// nothing in another even under a shared CA.
    pub fn common_name(self, fleet: &Fleet) -> String {
        format!("emr-{}-{self}", fleet.as_str())
    }

    /// The file stem of its certificate, key and zenoh configuration: `router`, `station`, `robot-3`.
    pub fn file_stem(self) -> String {
        self.to_string()
    }
}

impl fmt::Display for Member {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Member::Router => f.write_str("router"),
            Member::Station => f.write_str("station"),
            Member::Robot(id) => write!(f, "robot-{id}"),
        }
    }
}
