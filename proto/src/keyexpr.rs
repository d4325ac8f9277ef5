//! The Zenoh key-expression scheme. Every topic of a fleet lives under `emr/{fleet}/`.
//!
//! | key expression                         | payload            | who publishes            |
//! |----------------------------------------|--------------------|--------------------------|
//! | `emr/{fleet}/robot/{id}/keyframe`      | `Keyframe`         | edge, one per keyframe   |
//! | `emr/{fleet}/robot/{id}/posegraph`     | `PoseGraphUpdate`  | edge, after optimisation |
//! | `emr/{fleet}/robot/{id}/keyframes`     | queryable: `KeyframeRequest` -> `Keyframe` replies | edge |
//! | `emr/{fleet}/robot/{id}/alive`         | liveliness token   | edge                     |
//! | `emr/{fleet}/station/globalmap`        | `GlobalMap`; also a queryable for the latest | station |
//! | `emr/{fleet}/station/status`           | `StationStatus`    | station, periodically    |

use std::fmt;

/// A fleet name, validated to be one plain key-expression chunk.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Fleet(String);

/// A fleet name that cannot be one chunk of a key expression.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("invalid fleet name {name:?}: {reason}")]
pub struct InvalidFleet {
    /// The rejected name.
    pub name: String,
    /// Why it was rejected.
    pub reason: &'static str,
}

impl Fleet {
    /// Validates a fleet name: non-empty ASCII letters, digits, `-` and `_` only, so that it can never
    /// contain a separator or a wildcard (`/`, `*`, `$`, `?`, `#`).
    pub fn new(name: &str) -> Result<Self, InvalidFleet> {
        let reject = |reason| Err(InvalidFleet { name: name.to_owned(), reason });
        if name.is_empty() {
            return reject("empty");
        }
        if name.len() > 64 {
            return reject("longer than 64 characters");
        }
        if !name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_') {
            return reject("only ASCII letters, digits, '-' and '_' are allowed");
        }
        Ok(Fleet(name.to_owned()))
    }

    /// The name.
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl fmt::Display for Fleet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

/// Keyframes of one robot.
pub fn keyframe(fleet: &Fleet, robot: u32) -> String {
    format!("emr/{fleet}/robot/{robot}/keyframe")
}

/// Pose-graph updates of one robot.
pub fn posegraph(fleet: &Fleet, robot: u32) -> String {
    format!("emr/{fleet}/robot/{robot}/posegraph")
}

/// One robot's keyframe store (queryable) for backfilling missed keyframes.
pub fn keyframe_store(fleet: &Fleet, robot: u32) -> String {
    format!("emr/{fleet}/robot/{robot}/keyframes")
}

/// One robot's liveliness token.
pub fn alive(fleet: &Fleet, robot: u32) -> String {
    format!("emr/{fleet}/robot/{robot}/alive")
}

/// The fleet's global map (publication and queryable for the latest).
pub fn global_map(fleet: &Fleet) -> String {
    format!("emr/{fleet}/station/globalmap")
}

/// The station's status.
pub fn station_status(fleet: &Fleet) -> String {
    format!("emr/{fleet}/station/status")
}

/// Every robot topic of the fleet (keyframes and pose graphs of all robots): what a station subscribes to.
pub fn all_robots(fleet: &Fleet) -> String {
    format!("emr/{fleet}/robot/*/*")
}

/// Every robot's liveliness token.
pub fn all_alive(fleet: &Fleet) -> String {
    format!("emr/{fleet}/robot/*/alive")
}

/// A parsed key expression of the scheme.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Topic {
    /// `emr/{fleet}/robot/{id}/keyframe`
    Keyframe { fleet: Fleet, robot: u32 },
    /// `emr/{fleet}/robot/{id}/posegraph`
    PoseGraph { fleet: Fleet, robot: u32 },
    /// `emr/{fleet}/robot/{id}/keyframes`
    KeyframeStore { fleet: Fleet, robot: u32 },
    /// `emr/{fleet}/robot/{id}/alive`
    Alive { fleet: Fleet, robot: u32 },
    /// `emr/{fleet}/station/globalmap`
    GlobalMap { fleet: Fleet },
    /// `emr/{fleet}/station/status`
    StationStatus { fleet: Fleet },
}

impl Topic {
    /// Parses a concrete key expression; `None` for anything outside the scheme.
    pub fn parse(key: &str) -> Option<Topic> {
        let parts: Vec<&str> = key.split('/').collect();
        let fleet = match parts.as_slice() {
            ["emr", fleet, ..] => Fleet::new(fleet).ok()?,
            _ => return None,
        };
        match parts[2..] {
            ["robot", id, leaf] => {
                // Reject "+1", "01" and the like: ids must be canonical so one robot has one key.
                let robot: u32 = id.parse().ok().filter(|r: &u32| r.to_string() == id)?;
                match leaf {
                    "keyframe" => Some(Topic::Keyframe { fleet, robot }),
                    "posegraph" => Some(Topic::PoseGraph { fleet, robot }),
                    "keyframes" => Some(Topic::KeyframeStore { fleet, robot }),
                    "alive" => Some(Topic::Alive { fleet, robot }),
                    _ => None,
                }
            }
            ["station", "globalmap"] => Some(Topic::GlobalMap { fleet }),
            ["station", "status"] => Some(Topic::StationStatus { fleet }),
            _ => None,
        }
    }

    /// The key expression of this topic.
    pub fn key(&self) -> String {
        match self {
            Topic::Keyframe { fleet, robot } => keyframe(fleet, *robot),
            Topic::PoseGraph { fleet, robot } => posegraph(fleet, *robot),
            Topic::KeyframeStore { fleet, robot } => keyframe_store(fleet, *robot),
            Topic::Alive { fleet, robot } => alive(fleet, *robot),
            Topic::GlobalMap { fleet } => global_map(fleet),
            Topic::StationStatus { fleet } => station_status(fleet),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fleet() -> Fleet {
        Fleet::new("warehouse-1").unwrap()
    }

    #[test]
    fn keys_follow_the_table() {
        let f = fleet();
        assert_eq!(keyframe(&f, 3), "emr/warehouse-1/robot/3/keyframe");
        assert_eq!(posegraph(&f, 3), "emr/warehouse-1/robot/3/posegraph");
        assert_eq!(keyframe_store(&f, 3), "emr/warehouse-1/robot/3/keyframes");
        assert_eq!(alive(&f, 3), "emr/warehouse-1/robot/3/alive");
        assert_eq!(global_map(&f), "emr/warehouse-1/station/globalmap");
        assert_eq!(station_status(&f), "emr/warehouse-1/station/status");
        assert_eq!(all_robots(&f), "emr/warehouse-1/robot/*/*");
    }

    #[test]
    fn every_topic_parses_back() {
        let f = fleet();
        let topics = [
            Topic::Keyframe { fleet: f.clone(), robot: 0 },
            Topic::PoseGraph { fleet: f.clone(), robot: 7 },
            Topic::KeyframeStore { fleet: f.clone(), robot: 4_000_000_000 },
            Topic::Alive { fleet: f.clone(), robot: 1 },
            Topic::GlobalMap { fleet: f.clone() },
            Topic::StationStatus { fleet: f },
        ];
        for t in topics {
            assert_eq!(Topic::parse(&t.key()), Some(t.clone()), "{}", t.key());
        }
    }

    #[test]
    fn foreign_keys_do_not_parse() {
        for k in [
            "",
            "emr",
            "emr/f/robot/1",
            "emr/f/robot/x/keyframe",
            "emr/f/robot/01/keyframe",
            "emr/f/robot/-1/keyframe",
            "emr/f/robot/1/keyframe/extra",
            "emr/f/robot/1/other",
            "emr/f/station/other",
            "emr/*/station/status",
            "other/f/station/status",
            "emr/f/robot/99999999999/keyframe",
        ] {
            assert_eq!(Topic::parse(k), None, "{k}");
        }
    }

    #[test]
    fn fleet_names_cannot_smuggle_wildcards() {
        for bad in ["", "a/b", "*", "**", "a$b", "a?", "a#", "é", &"x".repeat(65)] {
            assert!(Fleet::new(bad).is_err(), "{bad}");
        }
        assert!(Fleet::new("Fleet_2-b").is_ok());
    }
}
