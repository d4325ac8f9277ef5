//! Every message survives protobuf encoding with every field set, and poses convert losslessly.

use nalgebra::{Isometry3, Vector3};
use prost::Message;
use proto::*;

fn pose(i: f64) -> Pose {
    Pose::from(&Isometry3::new(Vector3::new(i, -2.0 * i, 0.5 + i), Vector3::new(0.1 * i, -0.2, 0.3)))
}

fn cloud() -> CompressedCloud {
    CompressedCloud { data: vec![1u8, 2, 3, 255].into(), points: 4 }
}

fn round_trip<M: Message + Default + PartialEq + std::fmt::Debug>(m: &M) {
    let bytes = m.encode_to_vec();
    assert_eq!(&M::decode(bytes.as_slice()).unwrap(), m);
}

#[test]
fn keyframe_round_trips() {
    round_trip(&Keyframe {
        fleet: "alpha".into(),
        robot: 2,
        seq: 123_456_789_012,
        stamp: Some(Timestamp { sec: 1_700_000_000, nanosec: 999_999_999 }),
        odom_pose: Some(pose(1.0)),
        scan_context: Some(ScanContext {
            rings: 2,
            sectors: 3,
            max_range: 80.0,
            cells: vec![0.0, 1.5, 2.0, 0.0, 3.25, 9.0],
        }),
        cloud: Some(cloud()),
        session: 1_700_000_123,
    });
    // The descriptor is optional: absent must stay absent, not become an empty one.
    round_trip(&Keyframe { scan_context: None, ..Default::default() });
}

#[test]
fn pose_graph_update_round_trips() {
    round_trip(&PoseGraphUpdate {
        fleet: "alpha".into(),
        robot: 1,
        revision: 9,
        poses: (0..5).map(|s| KeyframePose { seq: s, pose: Some(pose(s as f64)) }).collect(),
        loops: vec![LoopEdge { from_seq: 4, to_seq: 0, relative: Some(pose(0.5)), score: 0.93 }],
        session: 3,
    });
}

#[test]
fn global_map_round_trips() {
    round_trip(&GlobalMap {
        fleet: "alpha".into(),
        revision: 3,
        reference_robot: 1,
        robots: vec![
            RobotPlacement {
                robot: 1,
                transform: Some(Pose::identity()),
                confidence: 12.5,
                status: MergeStatus::Merged as i32,
                keyframes: 40,
                session: 0,
            },
            RobotPlacement {
                robot: 2,
                transform: Some(pose(3.0)),
                confidence: 0.0,
                status: MergeStatus::Unmerged as i32,
                keyframes: 17,
                session: 4,
            },
        ],
        edges: vec![MergeEdge {
            robot_a: 1,
            robot_b: 2,
            transform: Some(pose(2.0)),
            confidence: 12.5,
            inliers: 311,
            session_a: 0,
            session_b: 4,
        }],
        cloud: Some(cloud()),
        stamp: Some(Timestamp::from_secs_f64(42.25)),
        settled: true,
        reference_session: 0,
    });
}

#[test]
fn station_status_and_request_round_trip() {
    round_trip(&StationStatus {
        fleet: "alpha".into(),
        robots: vec![1, 2, 8],
        keyframes: 1234,
        merge_queue_depth: 1,
        last_merge_ms: 183.5,
        global_map_revision: 7,
        malformed_payloads: 3,
        stamp: Some(Timestamp::now()),
        memory: vec![
            RobotMemory { robot: 1, keyframe_bytes: 16_400_000, map_bytes: 81_000_000 },
            RobotMemory { robot: 8, keyframe_bytes: 0, map_bytes: 0 },
        ],
        estimating: true,
        last_round_ms: 3014.5,
        sessions: vec![SessionKeyframes { robot: 1, session: 2, keyframes: 40, conflicts: 0 }],
    });
    round_trip(&KeyframeRequest { seqs: vec![0, 5, 6, 7, u64::MAX], from_seq: None, limit: None, session: None });
    round_trip(&KeyframeRequest { seqs: vec![], from_seq: Some(42), limit: None, session: Some(0) });
}

/// A sender without sessions (these messages as they were before the field) is session 0, and a
/// session survives a receiver that does not know the field (an older station keeps the bytes).
#[test]
fn an_absent_session_is_session_0() {
    let old = Keyframe { fleet: "alpha".into(), robot: 2, seq: 7, ..Default::default() };
    let bytes = old.encode_to_vec();
    assert!(!bytes.windows(1).any(|b| b[0] == (8 << 3)), "session 0 must not be written at all");
    assert_eq!(Keyframe::decode(bytes.as_slice()).unwrap().session, 0);
    let update = PoseGraphUpdate { robot: 2, revision: 1, session: 9, ..Default::default() };
    assert_eq!(PoseGraphUpdate::decode(update.encode_to_vec().as_slice()).unwrap().session, 9);
    // The current session is asked for by leaving the field out; session 0 is asked for explicitly.
    let request = KeyframeRequest { session: Some(0), ..Default::default() };
    assert_eq!(KeyframeRequest::decode(request.encode_to_vec().as_slice()).unwrap().session, Some(0));
    assert_eq!(KeyframeRequest::decode(&[][..]).unwrap().session, None);
}

#[test]
fn poses_convert_losslessly_through_the_wire() {
    for i in 0..50 {
        let f = i as f64;
        let iso = Isometry3::new(
            Vector3::new(f * 13.7 - 300.0, (f * 0.37).sin() * 1e4, -f),
            Vector3::new((f * 0.9).sin() * 3.0, (f * 1.3).cos(), (f * 0.21).sin() * 0.5),
        );
        let wire = Pose::decode(Pose::from(&iso).encode_to_vec().as_slice()).unwrap();
        assert_eq!(Isometry3::try_from(&wire).unwrap(), iso);
    }
}

#[test]
fn garbage_does_not_decode_as_a_keyframe() {
    // A length prefix far beyond the buffer must be an error, not a panic or a huge allocation.
    let hostile = [0x3a, 0xff, 0xff, 0xff, 0xff, 0x0f, 0x01];
    assert!(Keyframe::decode(&hostile[..]).is_err());
    assert!(GlobalMap::decode(&[0xff; 16][..]).is_err());
}
