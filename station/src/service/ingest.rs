//! Turning received payloads into checked state updates. Anything a robot (or anyone else) sends may
//! be garbage: every check here returns an error naming the key expression, never panics.

use std::collections::BTreeMap;
use std::sync::Arc;

use cloud::PointCloud;
use cloud::scan_context::ScanContext;
use nalgebra::Isometry3;
use prost::Message;
use proto::codec::{self, DecodeLimits};
use proto::{Fleet, Keyframe, PoseGraphUpdate};

use super::fleet_state::{Member, ReceivedKeyframe};

/// A loop edge of a robot's pose graph: keyframe sequence numbers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LoopEdge {
    /// The older keyframe.
    pub from: u64,
    /// The newer keyframe.
    pub to: u64,
}

/// Largest keyframe payload accepted, bytes (a keyframe is a downsampled scan: a few MB at most).
pub const MAX_KEYFRAME_BYTES: usize = 64 << 20;

/// Largest pose-graph payload accepted, bytes (about 800 000 poses).
pub const MAX_POSEGRAPH_BYTES: usize = 64 << 20;

/// Largest keyframe cloud accepted, points.
pub const MAX_KEYFRAME_POINTS: u64 = 4 << 20;

/// A payload that is not what its key expression promises.
#[derive(Debug, thiserror::Error)]
#[error("malformed {kind} on {key}: {reason}")]
pub struct Malformed {
    /// The key expression it arrived on.
    pub key: String,
    /// The message type expected.
    pub kind: &'static str,
    /// What is wrong with it.
    pub reason: String,
}

/// A checked pose-graph update.
#[derive(Clone, Debug, PartialEq)]
pub struct ReceivedPoses {
    /// Robot id.
    pub robot: u32,
    /// The robot's session the poses are of.
    pub session: u64,
    /// The update's revision.
    pub revision: u64,
    /// Optimised poses by sequence number.
    pub poses: BTreeMap<u64, Isometry3<f64>>,
    /// The graph's loop edges.
    pub loops: Vec<LoopEdge>,
}

/// Checks and decodes a keyframe that arrived on `key` for `robot` of `fleet`.
pub fn keyframe(fleet: &Fleet, robot: u32, key: &str, bytes: &[u8]) -> Result<ReceivedKeyframe, Malformed> {
    let bad = malformed(key, "Keyframe");
    let kf: Keyframe = decode(bytes, MAX_KEYFRAME_BYTES).map_err(&bad)?;
    check_sender(fleet, robot, &kf.fleet, kf.robot).map_err(&bad)?;
    let odom_pose = pose(kf.odom_pose.as_ref()).map_err(|e| bad(format!("odom_pose: {e}")))?;
    let cloud = keyframe_cloud(&kf).map_err(&bad)?;
    let (seq, session) = (kf.seq, kf.session);
    Ok(ReceivedKeyframe { robot, session, seq, bytes: Arc::from(bytes), odom_pose, cloud: Arc::new(cloud) })
}

impl ReceivedPoses {
    /// The robot session whose poses these are.
    pub fn member(&self) -> Member {
        Member::new(self.robot, self.session)
    }
}

/// Checks and decodes a pose-graph update that arrived on `key` for `robot` of `fleet`.
pub fn poses(fleet: &Fleet, robot: u32, key: &str, bytes: &[u8]) -> Result<ReceivedPoses, Malformed> {
    let bad = malformed(key, "PoseGraphUpdate");
    let update: PoseGraphUpdate = decode(bytes, MAX_POSEGRAPH_BYTES).map_err(&bad)?;
    check_sender(fleet, robot, &update.fleet, update.robot).map_err(&bad)?;
    let mut poses = BTreeMap::new();
    for p in &update.poses {
        let iso = pose(p.pose.as_ref()).map_err(|e| bad(format!("pose of keyframe {}: {e}", p.seq)))?;
        poses.insert(p.seq, iso);
    }
    let loops = update.loops.iter().map(|l| LoopEdge { from: l.from_seq, to: l.to_seq }).collect();
    Ok(ReceivedPoses { robot, session: update.session, revision: update.revision, poses, loops })
}

/// Builds the error for a payload of `kind` on `key` from a reason.
fn malformed(key: &str, kind: &'static str) -> impl Fn(String) -> Malformed {
    move |reason| Malformed { key: key.to_owned(), kind, reason }
}

/// Decodes `bytes` as `M`, refusing payloads above `limit` before decoding them.
fn decode<M: Message + Default>(bytes: &[u8], limit: usize) -> Result<M, String> {
    if bytes.len() > limit {
        return Err(format!("{} bytes, limit {limit}", bytes.len()));
    }
    M::decode(bytes).map_err(|e| e.to_string())
}

/// A message's fleet and robot must be those of its key expression: otherwise one robot could
/// write into another's map.
fn check_sender(fleet: &Fleet, robot: u32, msg_fleet: &str, msg_robot: u32) -> Result<(), String> {
    if msg_fleet != fleet.as_str() || msg_robot != robot {
        return Err(format!("says fleet {msg_fleet:?} robot {msg_robot}, key says fleet {fleet:?} robot {robot}"));
    }
    Ok(())
}

fn pose(p: Option<&proto::Pose>) -> Result<Isometry3<f64>, String> {
    let p = p.ok_or("missing")?;
    Isometry3::try_from(p).map_err(|e| e.to_string())
}

/// A keyframe held as its bytes (checked by [`keyframe`] when it arrived), decoded again: what the
/// merge does when it needs the points.
pub fn held_keyframe(bytes: &[u8]) -> Result<HeldKeyframe, String> {
    let kf: Keyframe = decode(bytes, MAX_KEYFRAME_BYTES)?;
    let context = kf.scan_context.as_ref().map(|m| ScanContext::try_from(m).map_err(|e| e.to_string()));
    Ok(HeldKeyframe { cloud: keyframe_cloud(&kf)?, context })
}

/// A held keyframe as the merge uses it.
pub struct HeldKeyframe {
    /// Its points, in the sensor frame.
    pub cloud: PointCloud,
    /// Its place descriptor, when it came with one (an unusable one says why).
    pub context: Option<Result<ScanContext, String>>,
}

/// The keyframe's cloud, positions only (the merge uses nothing else; channels would only cost
/// memory), with every point finite.
fn keyframe_cloud(kf: &Keyframe) -> Result<PointCloud, String> {
    let compressed = kf.cloud.as_ref().ok_or("no cloud")?;
    let limits = DecodeLimits { max_points: MAX_KEYFRAME_POINTS };
    let cloud = codec::decode_with_limits(&compressed.data, &limits).map_err(|e| format!("cloud: {e}"))?;
    if cloud.len() as u64 != compressed.points {
        return Err(format!("cloud holds {} points, message says {}", cloud.len(), compressed.points));
    }
    let mut cloud = PointCloud::from_points(cloud.points);
    cloud.retain_finite();
    Ok(cloud)
}
