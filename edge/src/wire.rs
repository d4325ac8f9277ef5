//! Keyframes on the wire: odometry keyframes to `emr.v1.Keyframe` messages and back (no networking).

use cloud::PointCloud;
use nalgebra::Isometry3;
use proto::codec::{self, CodecConfig, DecodeError, DecodeLimits, EncodeError};
use proto::{CompressedCloud, Fleet, InvalidPose, Pose, Timestamp};

use crate::keyframe::Keyframe;
use crate::loops::LoopCloser;
use cloud::scan_context::ScanContext;

/// Largest keyframe cloud [`keyframe_cloud`] decodes: a voxel-downsampled scan has thousands of
/// points, so this bounds what a corrupt message can make a receiver allocate (~70 MB).
pub const MAX_KEYFRAME_POINTS: u64 = 1 << 22;

/// Why a `Keyframe` message does not hold a usable keyframe.
#[derive(Debug, thiserror::Error)]
pub enum WireError {
    /// The message has no `odom_pose`.
    #[error("keyframe {seq} of robot {robot}: no odom_pose")]
    MissingPose {
        /// Robot id in the message.
        robot: u32,
        /// Keyframe sequence number in the message.
        seq: u64,
    },
    /// The pose is not a rigid transform.
    #[error("keyframe {seq} of robot {robot}: bad odom_pose: {source}")]
    BadPose {
        /// Robot id in the message.
        robot: u32,
        /// Keyframe sequence number in the message.
        seq: u64,
        /// What is wrong with it.
        source: InvalidPose,
    },
    /// The message has no `cloud`.
    #[error("keyframe {seq} of robot {robot}: no cloud")]
    MissingCloud {
        /// Robot id in the message.
        robot: u32,
        /// Keyframe sequence number in the message.
        seq: u64,
    },
    /// The cloud's bytes do not decode.
    #[error("keyframe {seq} of robot {robot}: cloud does not decode: {source}")]
    Codec {
        /// Robot id in the message.
        robot: u32,
        /// Keyframe sequence number in the message.
        seq: u64,
        /// What the codec said.
        source: DecodeError,
    },
}

/// The wire message of an odometry keyframe; `stamp_s` is the time of the scan that made it.
pub fn keyframe_message(
    fleet: &Fleet,
    robot: u32,
    kf: &Keyframe,
    stamp_s: f64,
    context: Option<&ScanContext>,
    codec: &CodecConfig,
) -> Result<proto::Keyframe, EncodeError> {
    let data = codec::encode(&kf.cloud, codec)?;
    Ok(proto::Keyframe {
        fleet: fleet.to_string(),
        robot,
        seq: kf.seq,
        stamp: Some(Timestamp::from_secs_f64(stamp_s)),
        odom_pose: Some(Pose::from(&kf.pose)),
        scan_context: context.map(proto::ScanContext::from),
        cloud: Some(CompressedCloud { data: data.into(), points: kf.cloud.len() as u64 }),
        // The node names its session; a message made elsewhere is of no session.
        session: 0,
    })
}

/// The wire message of the loop closure's graph after an optimisation: every keyframe's pose and the
/// loops in the graph.
pub fn posegraph_message(fleet: &Fleet, robot: u32, loops: &LoopCloser) -> proto::PoseGraphUpdate {
    let places = loops.places();
    let poses = places
        .iter()
        .zip(loops.poses())
        .map(|(place, pose)| proto::KeyframePose { seq: place.seq, pose: Some(Pose::from(pose)) })
        .collect();
    let loops_in_graph = loops
        .loops()
        .map(|l| proto::LoopEdge {
            from_seq: places[l.a].seq,
            to_seq: places[l.b].seq,
            relative: Some(Pose::from(&l.fit.transform)),
            score: l.fit.score,
        })
        .collect();
    proto::PoseGraphUpdate {
        fleet: fleet.to_string(),
        robot,
        revision: loops.revision(),
        poses,
        loops: loops_in_graph,
        session: 0,
    }
}

/// The odometry pose and the decoded cloud of a wire keyframe.
pub fn keyframe_cloud(msg: &proto::Keyframe) -> Result<(Isometry3<f64>, PointCloud), WireError> {
    let (robot, seq) = (msg.robot, msg.seq);
    let pose = msg.odom_pose.as_ref().ok_or(WireError::MissingPose { robot, seq })?;
    let pose = Isometry3::try_from(pose).map_err(|source| WireError::BadPose { robot, seq, source })?;
    let compressed = msg.cloud.as_ref().ok_or(WireError::MissingCloud { robot, seq })?;
    let limits = DecodeLimits { max_points: MAX_KEYFRAME_POINTS };
    let cloud = codec::decode_with_limits(&compressed.data, &limits).map_err(|source| WireError::Codec {
        robot,
        seq,
        source,
    })?;
    Ok((pose, cloud))
}

#[cfg(test)]
mod tests {
    use nalgebra::{Point3, Translation3, UnitQuaternion};

    use super::*;

    fn keyframe() -> Keyframe {
        let points: Vec<Point3<f32>> =
            (0..500).map(|i| Point3::new(i as f32 * 0.01, (i as f32 * 0.3).sin() * 5.0, 1.5)).collect();
        let pose = Isometry3::from_parts(
            Translation3::new(1.25, -3.5, 0.125),
            UnitQuaternion::from_euler_angles(0.01, -0.02, 1.3),
        );
        Keyframe { seq: 7, frame: 42, pose, cloud: PointCloud::from_points(points) }
    }

    #[test]
    fn keyframes_round_trip_within_the_codec_step() {
        let kf = keyframe();
        let fleet = Fleet::new("f1").unwrap();
        let msg = keyframe_message(&fleet, 3, &kf, 12.5, None, &CodecConfig::default()).unwrap();
        assert_eq!((msg.fleet.as_str(), msg.robot, msg.seq), ("f1", 3, 7));
        assert_eq!(msg.stamp, Some(Timestamp { sec: 12, nanosec: 500_000_000 }));
        assert_eq!(msg.cloud.as_ref().unwrap().points, 500);
        let (pose, cloud) = keyframe_cloud(&msg).unwrap();
        assert_eq!(pose, kf.pose);
        assert_eq!(cloud.len(), kf.cloud.len());
        for (a, b) in cloud.points.iter().zip(&kf.cloud.points) {
            assert!((a - b).abs().max() <= 0.0005 + 1e-6, "{a} vs {b}");
        }
    }

    #[test]
    fn broken_messages_say_what_is_wrong() {
        let fleet = Fleet::new("f1").unwrap();
        let good = keyframe_message(&fleet, 3, &keyframe(), 0.0, None, &CodecConfig::default()).unwrap();
        let no_pose = proto::Keyframe { odom_pose: None, ..good.clone() };
        assert!(matches!(keyframe_cloud(&no_pose), Err(WireError::MissingPose { robot: 3, seq: 7 })));
        let bad_pose = proto::Keyframe { odom_pose: Some(Pose { qw: 2.0, ..Pose::identity() }), ..good.clone() };
        let err = keyframe_cloud(&bad_pose).unwrap_err();
        assert!(matches!(err, WireError::BadPose { .. }) && err.to_string().contains("keyframe 7 of robot 3"), "{err}");
        let no_cloud = proto::Keyframe { cloud: None, ..good.clone() };
        assert!(matches!(keyframe_cloud(&no_cloud), Err(WireError::MissingCloud { .. })));
        let garbage = CompressedCloud { data: vec![1, 2, 3].into(), points: 1 };
        let bad_cloud = proto::Keyframe { cloud: Some(garbage), ..good };
        assert!(matches!(keyframe_cloud(&bad_cloud), Err(WireError::Codec { .. })));
    }
}
