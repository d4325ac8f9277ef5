//! The station seen from outside: fetching the latest global map (`emr-station save`) and
//! summarising any sample of the key-expression scheme (`emr-station watch`).

use std::time::Duration;

use cloud::PointCloud;
use nalgebra::Isometry3;
use prost::Message;
use proto::codec::{self, DecodeLimits};
use proto::{Fleet, GlobalMap, Keyframe, MergeStatus, PoseGraphUpdate, StationStatus, Topic, keyexpr};
use serde_json::{Value, json};

use crate::merge::files::matrix_rows;

/// Why the global map could not be fetched.
#[derive(Debug, thiserror::Error)]
pub enum FetchError {
    /// Nobody answered on the key in time.
    #[error("no station answered on {key} within {timeout:?}")]
    NoAnswer {
        /// The queried key.
        key: String,
        /// How long we waited.
        timeout: Duration,
    },
    /// A station answered that it has no global map yet.
    #[error("the station on {key} has no global map yet")]
    NoMapYet {
        /// The queried key.
        key: String,
    },
    /// The answer is not a `GlobalMap`.
    #[error("the reply on {key} is not a GlobalMap: {source}")]
    Malformed {
        /// The queried key.
        key: String,
        /// What prost said.
        source: prost::DecodeError,
    },
    /// Zenoh refused the query.
    #[error("zenoh: {0}")]
    Zenoh(String),
}

/// Asks the fleet's station for its latest global map; returns the map and its bytes as sent.
pub async fn fetch_global_map(
    session: &zenoh::Session,
    fleet: &Fleet,
    timeout: Duration,
) -> Result<(GlobalMap, Vec<u8>), FetchError> {
    let key = keyexpr::global_map(fleet);
    let replies = session.get(&key).timeout(timeout).await.map_err(|e| FetchError::Zenoh(e.to_string()))?;
    let mut refused = false;
    while let Ok(reply) = replies.recv_async().await {
        match reply.result() {
            Ok(sample) => {
                let bytes = sample.payload().to_bytes().to_vec();
                let map = GlobalMap::decode(bytes.as_slice())
                    .map_err(|source| FetchError::Malformed { key: key.clone(), source })?;
                return Ok((map, bytes));
            }
            Err(_) => refused = true,
        }
    }
    Err(if refused { FetchError::NoMapYet { key } } else { FetchError::NoAnswer { key, timeout } })
}

/// The global map's cloud, decoded.
pub fn global_map_cloud(map: &GlobalMap) -> Result<PointCloud, codec::DecodeError> {
    match &map.cloud {
        Some(c) if !c.data.is_empty() => codec::decode_with_limits(&c.data, &DecodeLimits::default()),
        _ => Ok(PointCloud::default()),
    }
}

/// The placements as JSON, in the spirit of `emr-station merge`'s transforms.json: per robot its
/// `transform` (4x4 row-major, robot odometry frame into the global frame), `confidence`, `status`
/// and `keyframes`; per spanning-tree edge the transform mapping robot_b's frame into robot_a's.
pub fn placements_json(map: &GlobalMap) -> Value {
    let robots: Vec<Value> = map
        .robots
        .iter()
        .map(|r| {
            json!({
                "robot": r.robot,
                "session": r.session,
                "transform": matrix(r.transform.as_ref()),
                "confidence": r.confidence,
                "status": status_name(r.status),
                "keyframes": r.keyframes,
            })
        })
        .collect();
    let edges: Vec<Value> = map
        .edges
        .iter()
        .map(|e| {
            json!({
                "robot_a": e.robot_a,
                "robot_b": e.robot_b,
                "session_a": e.session_a,
                "session_b": e.session_b,
                "transform": matrix(e.transform.as_ref()),
                "confidence": e.confidence,
                "inliers": e.inliers,
            })
        })
        .collect();
    json!({
        "fleet": map.fleet,
        "revision": map.revision,
        "reference_robot": map.reference_robot,
        "reference_session": map.reference_session,
        "settled": map.settled,
        "robots": robots,
        "edges": edges,
    })
}

fn matrix(p: Option<&proto::Pose>) -> Value {
    match p.map(Isometry3::try_from) {
        Some(Ok(iso)) => json!(matrix_rows(&iso)),
        _ => Value::Null,
    }
}

fn status_name(status: i32) -> &'static str {
    match MergeStatus::try_from(status) {
        Ok(MergeStatus::Merged) => "merged",
        Ok(MergeStatus::Unmerged) => "unmerged",
        _ => "unspecified",
    }
}

/// One received sample, summarised.
#[derive(Clone, Debug, PartialEq)]
pub struct SampleSummary {
    /// The key expression.
    pub key: String,
    /// The message type the key promises (`Topic::parse`), or `unknown`.
    pub kind: &'static str,
    /// The summary fields, or `{"malformed": reason}`.
    pub fields: Value,
}

impl SampleSummary {
    /// One JSON object: `key`, `type` and the fields.
    pub fn to_json(&self) -> Value {
        let mut v = json!({ "key": self.key, "type": self.kind });
        if let (Value::Object(out), Value::Object(fields)) = (&mut v, &self.fields) {
            out.extend(fields.clone());
        }
        v
    }

    /// One line: the key, the type and `name=value` per field.
    pub fn to_line(&self) -> String {
        let fields = match &self.fields {
            Value::Object(m) => m.iter().map(|(k, v)| format!("{k}={}", compact(v))).collect::<Vec<_>>().join(" "),
            other => other.to_string(),
        };
        format!("{} {} {fields}", self.key, self.kind)
    }
}

fn compact(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        Value::Array(items) => format!("[{}]", items.iter().map(compact).collect::<Vec<_>>().join(",")),
        other => other.to_string(),
    }
}

/// Summarises a sample by the message type its key promises; a payload that does not decode is
/// summarised as malformed.
pub fn summarize(key: &str, payload: &[u8]) -> SampleSummary {
    let (kind, fields) = match Topic::parse(key) {
        Some(Topic::Keyframe { .. }) => ("Keyframe", decoded(payload, keyframe_fields)),
        Some(Topic::PoseGraph { .. }) => ("PoseGraphUpdate", decoded(payload, posegraph_fields)),
        Some(Topic::GlobalMap { .. }) => ("GlobalMap", decoded(payload, global_map_fields)),
        Some(Topic::StationStatus { .. }) => ("StationStatus", decoded(payload, status_fields)),
        Some(Topic::KeyframeStore { .. }) => ("KeyframeStore", json!({ "bytes": payload.len() })),
        Some(Topic::Alive { .. }) => ("Alive", json!({ "bytes": payload.len() })),
        None => ("unknown", json!({ "bytes": payload.len() })),
    };
    SampleSummary { key: key.to_owned(), kind, fields }
}

fn decoded<M: Message + Default>(payload: &[u8], fields: fn(&M) -> Value) -> Value {
    match M::decode(payload) {
        Ok(m) => fields(&m),
        Err(e) => json!({ "malformed": e.to_string(), "bytes": payload.len() }),
    }
}

fn keyframe_fields(k: &Keyframe) -> Value {
    let t = k.odom_pose.as_ref().map(|p| [p.tx, p.ty, p.tz].map(round3));
    json!({
        "robot": k.robot,
        "session": k.session,
        "seq": k.seq,
        "points": k.cloud.as_ref().map_or(0, |c| c.points),
        "translation": t,
    })
}

fn posegraph_fields(u: &PoseGraphUpdate) -> Value {
    json!({
        "robot": u.robot,
        "session": u.session,
        "revision": u.revision,
        "poses": u.poses.len(),
        "loops": u.loops.len(),
    })
}

fn global_map_fields(m: &GlobalMap) -> Value {
    let robots: Vec<String> =
        m.robots.iter().map(|r| format!("{}:{}:{:.3}", r.robot, status_name(r.status), r.confidence)).collect();
    json!({
        "revision": m.revision,
        "reference": m.reference_robot,
        "robots": robots,
        "edges": m.edges.len(),
        "points": m.cloud.as_ref().map_or(0, |c| c.points),
    })
}

fn status_fields(s: &StationStatus) -> Value {
    json!({
        "robots": s.robots,
        "keyframes": s.keyframes,
        "queue": s.merge_queue_depth,
        "last_merge_ms": round3(s.last_merge_ms),
        "estimating": s.estimating,
        "last_round_ms": round3(s.last_round_ms),
        "revision": s.global_map_revision,
        "malformed": s.malformed_payloads,
        "memory_mb": memory_mb(&s.memory),
    })
}

/// What a station holds per robot, MB to the kilobyte: `[{robot, keyframes, map}]`.
pub fn memory_mb(memory: &[proto::RobotMemory]) -> Value {
    let mb = |bytes: u64| round3(bytes as f64 / 1e6);
    memory
        .iter()
        .map(|m| json!({ "robot": m.robot, "keyframes": mb(m.keyframe_bytes), "map": mb(m.map_bytes) }))
        .collect()
}

fn round3(v: f64) -> f64 {
    (v * 1e3).round() / 1e3
}
