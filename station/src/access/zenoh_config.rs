//! The zenoh configurations of a fleet that lets only its members in.
//!
//! The router listens for members on TLS and requires a client certificate signed by the fleet CA
//! (`enable_mtls`); plain TCP endpoints, if any, are for tools on the router's host and may only
//! listen. Its access control denies by default and allows, per certificate common name:
//!
//! | who | may send (ingress) | on |
//! |---|---|---|
//! | robot N | put, delete, queryable, reply, liveliness token | `emr/{fleet}/robot/N/**` |
//! | station | put, delete, queryable, reply, liveliness token | `emr/{fleet}/station/**` |
//! | station, tools (plain TCP) | subscribe, query, liveliness subscribe and query | `emr/{fleet}/**` |
//!
//! and lets the router deliver anything of the fleet to whoever asked for it (egress). So robot 3's
//! certificate cannot publish as robot 4, a robot cannot publish a global map, and a tool cannot
//! publish at all.
//!
//! The configurations are JSON, which zenoh reads as JSON5.

use std::path::{Path, PathBuf};

use serde_json::{Value, json};

use super::Member;
use proto::Fleet;

/// Where a member finds its certificate files, as the process that reads them sees them.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CertFiles {
    /// The directory holding `ca.pem` and each member's `<stem>.pem` and `<stem>.key`.
    pub dir: PathBuf,
}

impl CertFiles {
    /// The fleet CA's certificate.
    pub fn ca(&self) -> PathBuf {
        self.dir.join("ca.pem")
    }

    /// A member's certificate.
    pub fn certificate(&self, member: Member) -> PathBuf {
        self.dir.join(format!("{}.pem", member.file_stem()))
    }

    /// A member's private key.
    pub fn key(&self, member: Member) -> PathBuf {
        self.dir.join(format!("{}.key", member.file_stem()))
    }
}

/// The router's configuration: `tls` endpoints for members (client certificate required), `tcp`
/// endpoints for read-only tools (keep them on a loopback address).
pub fn router(fleet: &Fleet, robots: &[u32], tls: &[String], tcp: &[String], files: &CertFiles) -> Value {
    let listen: Vec<&String> = tls.iter().chain(tcp).collect();
    json!({
        "mode": "router",
        "listen": { "endpoints": listen },
        "scouting": { "multicast": { "enabled": false }, "gossip": { "enabled": false } },
        "transport": { "link": { "tls": {
            "root_ca_certificate": path(&files.ca()),
            "listen_certificate": path(&files.certificate(Member::Router)),
            "listen_private_key": path(&files.key(Member::Router)),
            "enable_mtls": true,
            // A certificate that expires while connected loses its link, not only the next one.
            "close_link_on_expiration": true,
        } } },
        "access_control": access_control(fleet, robots),
    })
}

/// A member's configuration: client mode, connecting to the router's `tls` endpoints with its own
/// certificate.
pub fn member(member: Member, router: &[String], files: &CertFiles) -> Value {
    json!({
        "mode": "client",
        "connect": { "endpoints": router },
        "scouting": { "multicast": { "enabled": false }, "gossip": { "enabled": false } },
        "transport": { "link": { "tls": {
            "root_ca_certificate": path(&files.ca()),
            "connect_certificate": path(&files.certificate(member)),
            "connect_private_key": path(&files.key(member)),
            "enable_mtls": true,
        } } },
    })
}

const SPEAK: [&str; 5] = ["put", "delete", "declare_queryable", "reply", "liveliness_token"];
const LISTEN: [&str; 4] = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"];
const ALL: [&str; 9] = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
];

/// The router's `access_control` block (see the module's table).
pub fn access_control(fleet: &Fleet, robots: &[u32]) -> Value {
    let f = fleet.as_str();
    let everything = format!("emr/{f}/**");
    let rule = |id: &str, flow: &str, messages: &[&str], key: &str| json!({ "id": id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": [key] });
    let by_name = |m: Member| json!({ "id": m.to_string(), "cert_common_names": [m.common_name(fleet)] });

    let mut rules = vec![
        rule("deliver", "egress", &ALL, &everything),
        rule("listen", "ingress", &LISTEN, &everything),
        rule("station-speaks", "ingress", &SPEAK, &format!("emr/{f}/station/**")),
    ];
    let mut subjects = vec![by_name(Member::Station), json!({ "id": "tools", "link_protocols": ["tcp"] })];
    let mut policies = vec![
        json!({ "rules": ["deliver", "listen", "station-speaks"], "subjects": ["station"] }),
        json!({ "rules": ["deliver", "listen"], "subjects": ["tools"] }),
    ];
    for &id in robots {
        let robot = Member::Robot(id);
        let speaks = format!("{robot}-speaks");
        rules.push(rule(&speaks, "ingress", &SPEAK, &format!("emr/{f}/robot/{id}/**")));
        subjects.push(by_name(robot));
        policies.push(json!({ "rules": ["deliver", speaks], "subjects": [robot.to_string()] }));
    }
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    })
}

fn path(p: &Path) -> String {
    p.display().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn files() -> CertFiles {
        CertFiles { dir: PathBuf::from("/etc/emr/fleet") }
    }

    /// Zenoh itself must accept what we write: its parser denies unknown fields.
    #[test]
    fn zenoh_reads_the_router_and_member_configurations() {
        let fleet = Fleet::new("demo").unwrap();
        let router = router(&fleet, &[1, 2, 3], &["tls/0.0.0.0:7448".into()], &["tcp/127.0.0.1:7447".into()], &files());
        let config = zenoh::Config::from_json5(&router.to_string()).expect("router config");
        let acl = config.get_json("access_control").unwrap();
        assert!(acl.contains("emr-demo-robot-3"), "{acl}");
        let member = member(Member::Robot(2), &["tls/router:7448".into()], &files());
        let config = zenoh::Config::from_json5(&member.to_string()).expect("member config");
        let tls = config.get_json("transport/link/tls/connect_certificate").unwrap();
        assert_eq!(tls, "\"/etc/emr/fleet/robot-2.pem\"");
    }

    #[test]
    fn each_robot_speaks_only_under_its_own_key() {
        let fleet = Fleet::new("demo").unwrap();
        let acl = access_control(&fleet, &[3, 4]);
        let rules = acl["rules"].as_array().unwrap();
        let rule = |id: &str| rules.iter().find(|r| r["id"] == id).unwrap_or_else(|| panic!("rule {id}"));
        assert_eq!(rule("robot-3-speaks")["key_exprs"], json!(["emr/demo/robot/3/**"]));
        assert_eq!(rule("robot-4-speaks")["key_exprs"], json!(["emr/demo/robot/4/**"]));
        let policies = acl["policies"].as_array().unwrap();
        let of = |s: &str| policies.iter().find(|p| p["subjects"] == json!([s])).unwrap()["rules"].clone();
        assert_eq!(of("robot-3"), json!(["deliver", "robot-3-speaks"]));
        assert_eq!(of("tools"), json!(["deliver", "listen"]));
    }
}
