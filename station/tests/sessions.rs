//! A robot that restarts: every start is a new session, with an odometry frame and sequence
//! numbers of its own. The station keeps each session as a map of its own, drops nothing as a
//! conflict and places both sessions with the merge, against the simulator's truth.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use cloud::PointCloud;
use cloud::se3::pose_error;
use nalgebra::Isometry3;
use prost::Message;
use proto::codec::{self, CodecConfig};
use proto::{CompressedCloud, Fleet, GlobalMap, Keyframe, MergeStatus, Pose, StationStatus, keyexpr};
use sim::{RobotMaps, Scenario};
use station::merge::MergeConfig;
use station::service::backfill::{Backfill, Ended, MAX_KEYFRAMES_PER_REQUEST, Want};
use station::service::fleet_state::{FleetState, Inserted, Member, ReceivedKeyframe};
use station::service::{Station, StationConfig, StationProgress, client, ingest};
use tokio::sync::watch;
use zenoh::qos::CongestionControl;

const ROBOT: u32 = 1;

fn fleet() -> Fleet {
    Fleet::new("sessions").unwrap()
}

/// Keyframe `seq` of `session` of [`ROBOT`]: `cloud` at the identity pose.
fn keyframe_bytes(session: u64, seq: u64, cloud: &PointCloud) -> Vec<u8> {
    let data = codec::encode(cloud, &CodecConfig::default()).unwrap();
    Keyframe {
        fleet: fleet().to_string(),
        robot: ROBOT,
        seq,
        stamp: Some(proto::Timestamp::from_secs_f64(seq as f64)),
        odom_pose: Some(Pose::from(Isometry3::identity())),
        scan_context: None,
        cloud: Some(CompressedCloud { data: data.into(), points: cloud.len() as u64 }),
        session,
    }
    .encode_to_vec()
}

/// A map cut into `n` keyframes (every n-th point each), all at the identity pose.
fn pieces(map: &PointCloud, n: usize) -> Vec<PointCloud> {
    (0..n).map(|k| PointCloud::from_points(map.points.iter().skip(k).step_by(n).copied().collect())).collect()
}

fn received(session: u64, seq: u64, cloud: &PointCloud) -> ReceivedKeyframe {
    let key = keyexpr::keyframe(&fleet(), ROBOT);
    ingest::keyframe(&fleet(), ROBOT, &key, &keyframe_bytes(session, seq, cloud)).unwrap()
}

/// Two different clouds, so that the same sequence number in two sessions has other bytes.
fn two_clouds() -> [PointCloud; 2] {
    let line =
        |z: f32| PointCloud::from_points((0..50).map(|i| nalgebra::Point3::new(i as f32 * 0.1, 0.0, z)).collect());
    [line(0.0), line(1.0)]
}

#[test]
fn a_restarted_robot_is_a_new_session_not_a_conflict() {
    let [a, b] = two_clouds();
    let mut s = FleetState::default();
    for seq in 0..5 {
        assert_eq!(s.insert_keyframe(&received(0, seq, &a)), Inserted::New);
    }
    // The restart: the same robot numbers its keyframes from 0 again, in a session of its own.
    for seq in 0..3 {
        assert_eq!(s.insert_keyframe(&received(7, seq, &b)), Inserted::New, "keyframe {seq} of session 7");
    }
    assert_eq!(s.total_conflicts(), 0);
    assert_eq!(s.keyframe_counts(), BTreeMap::from([(ROBOT, 8)]));
    assert_eq!(s.session_counts(), BTreeMap::from([(Member::new(ROBOT, 0), 5), (Member::new(ROBOT, 7), 3)]));
    assert_eq!(s.newest_session(ROBOT), Some(Member::new(ROBOT, 7)));
    assert_eq!(s.previous_session(Member::new(ROBOT, 7)), Some(Member::new(ROBOT, 0)));
    assert_eq!(s.previous_session(Member::new(ROBOT, 0)), None);
    // Within a session, other bytes for a held sequence number are still a conflict.
    assert_eq!(s.insert_keyframe(&received(7, 1, &a)), Inserted::Conflict);
    assert_eq!(s.robot(Member::new(ROBOT, 7)).unwrap().conflicts(), 1);
    assert_eq!(Member::new(ROBOT, 0).name(), "robot1");
    assert_eq!(Member::new(ROBOT, 7).name(), "robot1/s7");
}

#[test]
fn backfill_asks_each_session_by_name_and_a_reappeared_robot_for_its_current_one() {
    let [a, b] = two_clouds();
    let mut s = FleetState::default();
    for seq in [0, 2] {
        s.insert_keyframe(&received(0, seq, &a));
    }
    s.insert_keyframe(&received(5, 0, &b));
    let t0 = Instant::now();
    let mut backfill = Backfill::new(Duration::from_secs(2));
    let limit = Some(MAX_KEYFRAMES_PER_REQUEST);
    backfill.want(Member::new(ROBOT, 0), Want::Gaps);
    let sent = backfill.requests(&s, t0);
    assert_eq!(sent.len(), 1);
    assert_eq!((sent[0].1.seqs.clone(), sent[0].1.session, sent[0].1.limit), (vec![1], Some(0), limit));
    backfill.done(ROBOT, Ended::Complete, t0);
    // Reappeared: the rest of its newest session held, then which session it is in now (a
    // request naming none, one keyframe: a station that knows the robot only needs the name).
    backfill.appeared(ROBOT, &s);
    let first = backfill.requests(&s, t0);
    assert_eq!(first.len(), 1, "one request per robot at a time");
    assert_eq!((first[0].1.session, first[0].1.from_seq), (Some(5), Some(1)));
    backfill.done(ROBOT, Ended::Complete, t0);
    let second = backfill.requests(&s, t0);
    assert_eq!((second[0].1.session, second[0].1.from_seq, second[0].1.limit), (None, Some(0), Some(1)));
    backfill.done(ROBOT, Ended::Full, t0);
    assert!(backfill.requests(&s, t0).is_empty(), "a full answer to which session is not asked again");
}

// ---------------------------------------------------------------- a station on loopback

fn station_config() -> StationConfig {
    StationConfig {
        merge: MergeConfig::indoor(),
        debounce: Duration::from_millis(50),
        max_delay: Duration::from_millis(500),
        status_period: Duration::from_millis(200),
        ..StationConfig::new(fleet())
    }
}

async fn wait_for(
    rx: &mut watch::Receiver<StationProgress>,
    what: &str,
    pred: impl FnMut(&StationProgress) -> bool,
) -> StationProgress {
    let waited = tokio::time::timeout(Duration::from_secs(120), rx.wait_for(pred)).await.map(|p| p.unwrap().clone());
    waited.unwrap_or_else(|_| panic!("timed out waiting for {what}: {:?}", *rx.borrow()))
}

/// The placement of `session` of [`ROBOT`] in `map`.
fn placement(map: &GlobalMap, session: u64) -> Isometry3<f64> {
    let p = map.robots.iter().find(|p| p.robot == ROBOT && p.session == session).expect("the session is placed");
    assert_eq!(p.status(), MergeStatus::Merged, "session {session}: {map:?}");
    Isometry3::try_from(p.transform.as_ref().unwrap()).unwrap()
}

/// The warehouse's two robots' exact maps, sent as two sessions of one robot: the second session
/// starts where the scenario's second robot does, in an odometry frame of its own, its keyframes
/// numbered from 0 again. Both are held in full and placed within 5 cm / 0.5 deg of the truth.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn both_sessions_of_a_restarted_robot_are_held_and_merged_against_the_truth() {
    let truth = RobotMaps::build(&Scenario::by_name("warehouse-large").unwrap(), 10, 0.1).unwrap();
    let sessions = [(0u64, pieces(&truth.maps[0], 4)), (1, pieces(&truth.maps[1], 4))];
    let port = bus::free_port().unwrap();
    let station_session = bus::Network::loopback_ports(&[port], &[]).open().await.unwrap();
    let robot = bus::Network::loopback_ports(&[], &[port]).open().await.unwrap();
    let station = Station::start(station_session, station_config()).await.unwrap();
    let mut progress = station.progress();
    let publisher = robot
        .declare_publisher(keyexpr::keyframe(&fleet(), ROBOT))
        .congestion_control(CongestionControl::Block)
        .await
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    while !publisher.matching_status().await.unwrap().matching() {
        assert!(Instant::now() < deadline, "the station never subscribed");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    for (session, keyframes) in &sessions {
        for (seq, cloud) in keyframes.iter().enumerate() {
            publisher.put(keyframe_bytes(*session, seq as u64, cloud)).await.unwrap();
        }
    }
    let both_merged = |p: &StationProgress| p.total_keyframes() == 8 && p.up_to_date();
    let p = wait_for(&mut progress, "both sessions merged", both_merged).await;
    assert_eq!(p.conflicts, 0, "nothing is dropped as a conflict");
    assert_eq!(p.sessions, BTreeMap::from([(Member::new(ROBOT, 0), 4), (Member::new(ROBOT, 1), 4)]));
    let client_session = bus::Network::loopback_ports(&[], &[port]).open().await.unwrap();
    let (map, _) = client::fetch_global_map(&client_session, &fleet(), Duration::from_secs(5)).await.unwrap();
    assert_eq!(map.robots.len(), 2, "one placement per session: {map:?}");
    assert!(map.robots.iter().all(|p| p.keyframes == 4));
    let estimate = placement(&map, 0).inverse() * placement(&map, 1);
    let error = pose_error(&estimate, &truth.truth(0, 1));
    println!("session 1 in session 0's frame: {:.4} m, {:.4} deg off", error.translation_m, error.rotation_deg);
    assert!(error.translation_m < 0.05 && error.rotation_deg < 0.5, "{error:?}");
    // The status says what is held of each session.
    let status = status(&client_session).await;
    let held: Vec<(u32, u64, u64, u64)> =
        status.sessions.iter().map(|s| (s.robot, s.session, s.keyframes, s.conflicts)).collect();
    assert_eq!(held, vec![(ROBOT, 0, 4, 0), (ROBOT, 1, 4, 0)]);
    assert_eq!(status.robots, vec![ROBOT]);
    let summary = station.stop().await.unwrap();
    assert_eq!(summary.keyframes, BTreeMap::from([(ROBOT, 8)]));
    assert_eq!(summary.conflicts, 0);
}

/// The next station status.
async fn status(session: &zenoh::Session) -> StationStatus {
    let sub = session.declare_subscriber(keyexpr::station_status(&fleet())).await.unwrap();
    let sample = tokio::time::timeout(Duration::from_secs(10), sub.recv_async()).await.unwrap().unwrap();
    StationStatus::decode(sample.payload().to_bytes().as_ref()).unwrap()
}
