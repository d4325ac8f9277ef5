//! The station service: pure state and planning, then stations on loopback with fake robots
//! (hand-made keyframes of a synthetic room, a fake keyframe store), including a kill and restart.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use cloud::PointCloud;
use nalgebra::{Isometry3, Point3, Vector3};
use prost::Message;
use proto::codec::{self, CodecConfig};
use proto::{CompressedCloud, Fleet, Keyframe, KeyframePose, KeyframeRequest, Pose, PoseGraphUpdate, keyexpr};
use station::service::backfill::{Backfill, Ended, MAX_KEYFRAMES_PER_REQUEST, Want};
use station::service::fleet_state::{FleetState, Inserted, ReceivedKeyframe};
use station::service::{Station, StationConfig, StationProgress, client, ingest};
use tokio::sync::watch;
use zenoh::Session;
use zenoh::qos::CongestionControl;

// ---------------------------------------------------------------- helpers

fn fleet() -> Fleet {
    Fleet::new("testfleet").unwrap()
}

/// Walls and floor of a 6 x 4 x 2.5 m room on a 0.25 m grid: a few hundred points.
fn room() -> Vec<Point3<f32>> {
    let mut pts = Vec::new();
    let grid = |n: f32| (0..=(n / 0.25) as usize).map(|i| i as f32 * 0.25);
    for x in grid(6.0) {
        for z in grid(2.5) {
            pts.extend([Point3::new(x, 0.0, z), Point3::new(x, 4.0, z)]);
        }
        for y in grid(4.0) {
            pts.push(Point3::new(x, y, 0.0));
        }
    }
    for y in grid(4.0) {
        for z in grid(2.5) {
            pts.extend([Point3::new(0.0, y, z), Point3::new(6.0, y, z)]);
        }
    }
    pts
}

fn odom(seq: u64) -> Isometry3<f64> {
    Isometry3::translation(0.2 * seq as f64, 0.1, 0.0)
}

/// Keyframe `seq` of `robot`: the room seen from the keyframe's odometry pose.
fn keyframe_msg(fleet: &str, robot: u32, seq: u64) -> Keyframe {
    let inverse = odom(seq).inverse().cast::<f32>();
    let cloud = PointCloud::from_points(room().iter().map(|p| inverse * p).collect());
    let data = codec::encode(&cloud, &CodecConfig::default()).unwrap();
    Keyframe {
        fleet: fleet.into(),
        robot,
        seq,
        stamp: Some(proto::Timestamp::from_secs_f64(seq as f64)),
        odom_pose: Some(Pose::from(odom(seq))),
        scan_context: None,
        cloud: Some(CompressedCloud { data: data.into(), points: cloud.len() as u64 }),
        session: 0,
    }
}

fn keyframe_bytes(robot: u32, seq: u64) -> Vec<u8> {
    keyframe_msg(fleet().as_str(), robot, seq).encode_to_vec()
}

fn received(robot: u32, seq: u64) -> ReceivedKeyframe {
    let key = keyexpr::keyframe(&fleet(), robot);
    ingest::keyframe(&fleet(), robot, &key, &keyframe_bytes(robot, seq)).unwrap()
}

fn config() -> StationConfig {
    StationConfig {
        debounce: Duration::from_millis(50),
        max_delay: Duration::from_millis(500),
        status_period: Duration::from_millis(200),
        ..StationConfig::new(fleet())
    }
}

/// A station session listening on a fresh port and a robot session connected to it.
async fn sessions() -> (Session, Session, u16) {
    let port = bus::free_port().unwrap();
    let station = bus::Network::loopback_ports(&[port], &[]).open().await.unwrap();
    let robot = bus::Network::loopback_ports(&[], &[port]).open().await.unwrap();
    (station, robot, port)
}

async fn client_session(port: u16) -> Session {
    bus::Network::loopback_ports(&[], &[port]).open().await.unwrap()
}

async fn publisher(session: &Session, key: String) -> zenoh::pubsub::Publisher<'static> {
    let p = session.declare_publisher(key).congestion_control(CongestionControl::Block).await.unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    while !p.matching_status().await.unwrap().matching() {
        assert!(Instant::now() < deadline, "the station never subscribed");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    p
}

async fn wait_for(
    rx: &mut watch::Receiver<StationProgress>,
    what: &str,
    pred: impl FnMut(&StationProgress) -> bool,
) -> StationProgress {
    let waited = tokio::time::timeout(Duration::from_secs(30), rx.wait_for(pred)).await.map(|p| p.unwrap().clone());
    waited.unwrap_or_else(|_| panic!("timed out waiting for {what}: {:?}", *rx.borrow()))
}

/// A fake keyframe store for `robot` holding `held`; records every request it gets.
async fn fake_store(session: &Session, robot: u32, held: Vec<u64>) -> Arc<Mutex<Vec<KeyframeRequest>>> {
    let requests = Arc::new(Mutex::new(Vec::new()));
    let key = keyexpr::keyframe_store(&fleet(), robot);
    let queryable = session.declare_queryable(key.clone()).await.unwrap();
    let log = Arc::clone(&requests);
    tokio::spawn(async move {
        while let Ok(query) = queryable.recv_async().await {
            let request = KeyframeRequest::decode(query.payload().unwrap().to_bytes().as_ref()).unwrap();
            let wanted = |s: &u64| request.seqs.contains(s) || request.from_seq.is_some_and(|from| *s >= from);
            // As a robot does: the lowest `limit` of them.
            let limit = request.limit.map_or(usize::MAX, |l| l as usize);
            for seq in held.iter().copied().filter(wanted).take(limit) {
                query.reply(key.clone(), keyframe_bytes(robot, seq)).await.unwrap();
            }
            log.lock().unwrap().push(request);
        }
    });
    requests
}

// ---------------------------------------------------------------- pure state

#[test]
fn gaps_are_the_missing_seqs_below_the_newest() {
    let mut s = FleetState::default();
    for seq in [0, 1, 4, 2, 7] {
        assert_eq!(s.insert_keyframe(&received(1, seq)), Inserted::New);
    }
    assert_eq!(s.missing(1), vec![3, 5, 6]);
    assert_eq!(s.missing(9), Vec::<u64>::new());
    s.insert_keyframe(&received(2, 3));
    assert_eq!(s.missing(2), vec![0, 1, 2], "a robot first seen late misses everything before");
}

#[test]
fn an_absurd_sequence_number_lists_boundedly_many_gaps() {
    let mut s = FleetState::default();
    s.insert_keyframe(&received(1, 2));
    for seq in [1 << 40, u64::MAX] {
        // A well-formed keyframe (the cloud of keyframe 2) under an absurd sequence number.
        let bytes = Keyframe { seq, ..keyframe_msg(fleet().as_str(), 1, 2) }.encode_to_vec();
        let key = keyexpr::keyframe(&fleet(), 1);
        s.insert_keyframe(&station::service::ingest::keyframe(&fleet(), 1, &key, &bytes).unwrap());
    }
    let gaps = s.missing(1);
    assert_eq!(gaps.len(), station::service::fleet_state::MAX_LISTED_GAPS);
    assert_eq!(&gaps[..3], &[0, 1, 3], "lowest first");
    // 2^64 sequence numbers 0..=u64::MAX, 3 of them held.
    assert_eq!(s.robot(1).unwrap().missing_count(), u64::MAX - 2);
}

#[test]
fn inserts_are_idempotent_and_order_free() {
    let mut a = FleetState::default();
    let mut b = FleetState::default();
    for seq in 0..5 {
        a.insert_keyframe(&received(1, seq));
        b.insert_keyframe(&received(1, 4 - seq));
    }
    let revision = a.robot(1).unwrap().revision();
    assert_eq!(a.insert_keyframe(&received(1, 2)), Inserted::Duplicate);
    assert_eq!(a.robot(1).unwrap().revision(), revision, "a duplicate changes nothing");
    assert_eq!(a.basis(), b.basis());
    assert_eq!(a.keyframe_counts(), BTreeMap::from([(1, 5)]));
}

#[test]
fn a_conflicting_keyframe_keeps_the_first() {
    let mut s = FleetState::default();
    let first = received(1, 0);
    s.insert_keyframe(&first);
    let mut other = received(1, 1);
    other.seq = 0;
    assert_eq!(s.insert_keyframe(&other), Inserted::Conflict);
    assert_eq!(s.robot(1).unwrap().keyframes()[&0].bytes, first.bytes);
    assert_eq!(s.total_conflicts(), 1);
}

#[test]
fn optimised_poses_override_odometry_and_old_revisions_are_ignored() {
    let mut s = FleetState::default();
    s.insert_keyframe(&received(1, 0));
    s.insert_keyframe(&received(1, 1));
    let moved = Isometry3::translation(5.0, 0.0, 0.0);
    assert!(s.apply_poses(1, 3, BTreeMap::from([(1, moved)])));
    let r = s.robot(1).unwrap();
    assert_eq!(r.pose(1), Some(moved));
    assert_eq!(r.pose(0), Some(odom(0)), "keyframes without an optimised pose keep their odometry");
    let revision = r.revision();
    assert!(!s.apply_poses(1, 2, BTreeMap::new()), "older revision");
    assert!(!s.apply_poses(1, 3, BTreeMap::new()), "same revision");
    assert_eq!(s.robot(1).unwrap().revision(), revision);
    assert_eq!(s.robot(1).unwrap().pose(1), Some(moved));
    assert!(!s.apply_poses(1, 4, BTreeMap::from([(1, moved)])), "newer revision, same poses");
    assert_eq!(s.robot(1).unwrap().basis().pose_revision, Some(3), "the basis follows the poses in effect");
}

#[test]
fn malformed_keyframes_are_refused_with_their_key() {
    let f = fleet();
    let key = keyexpr::keyframe(&f, 1);
    let good = keyframe_bytes(1, 0);
    let mut wrong_fleet = keyframe_msg("other", 1, 0);
    let mut bad_cloud = keyframe_msg(f.as_str(), 1, 0);
    bad_cloud.cloud.as_mut().unwrap().data = bad_cloud.cloud.as_ref().unwrap().data.slice(..20);
    let mut bad_pose = keyframe_msg(f.as_str(), 1, 0);
    bad_pose.odom_pose = Some(Pose::default());
    let cases: Vec<(&str, Vec<u8>)> = vec![
        ("garbage", vec![0xff; 40]),
        ("truncated", good[..good.len() / 2].to_vec()),
        ("wrong fleet", wrong_fleet.encode_to_vec()),
        ("bad cloud", bad_cloud.encode_to_vec()),
        ("bad pose", bad_pose.encode_to_vec()),
    ];
    for (what, bytes) in cases {
        let err = ingest::keyframe(&f, 1, &key, &bytes).unwrap_err();
        assert!(err.to_string().contains(&key), "{what}: {err}");
    }
    assert!(ingest::keyframe(&f, 2, &key, &good).is_err(), "robot 1's keyframe on robot 2's key");
    wrong_fleet.fleet = f.to_string();
    assert!(ingest::keyframe(&f, 1, &key, &wrong_fleet.encode_to_vec()).is_ok());
}

/// What the backfill asks robot 1's session 0 for: `seqs`, and everything from `from_seq` on.
fn request(seqs: &[u64], from_seq: Option<u64>) -> KeyframeRequest {
    KeyframeRequest { seqs: seqs.to_vec(), from_seq, limit: Some(MAX_KEYFRAMES_PER_REQUEST), session: Some(0) }
}

#[test]
fn backfill_keeps_one_request_per_robot_and_does_not_repeat_itself() {
    let mut s = FleetState::default();
    for seq in [0, 3] {
        s.insert_keyframe(&received(1, seq));
    }
    let now = Instant::now();
    let mut b = Backfill::new(Duration::from_secs(2));
    b.want(1, Want::Gaps);
    let sent = b.requests(&s, now);
    assert_eq!(sent, vec![(1, request(&[1, 2], None))]);
    b.want(1, Want::Gaps);
    assert!(b.requests(&s, now).is_empty(), "one outstanding request per robot");
    b.done(1, Ended::Complete, now);
    assert!(b.requests(&s, now).is_empty(), "the same gaps again so soon");
    b.want(1, Want::Everything);
    assert_eq!(b.requests(&s, now), vec![(1, request(&[1, 2], Some(4)))]);
}

#[test]
fn a_request_that_timed_out_is_made_again_for_what_is_still_missing() {
    let mut s = FleetState::default();
    for seq in [0, 3] {
        s.insert_keyframe(&received(1, seq));
    }
    let t0 = Instant::now();
    let retry = Duration::from_secs(2);
    let mut b = Backfill::new(retry);
    b.want(1, Want::Everything);
    assert_eq!(b.requests(&s, t0), vec![(1, request(&[1, 2], Some(4)))]);
    // Part of it came before the timeout.
    s.insert_keyframe(&received(1, 1));
    s.insert_keyframe(&received(1, 4));
    b.done(1, Ended::TimedOut, t0);
    assert!(b.requests(&s, t0 + retry / 2).is_empty(), "asked again before the retry delay");
    assert_eq!(b.requests(&s, t0 + retry), vec![(1, request(&[2], Some(5)))]);
    b.done(1, Ended::Complete, t0 + retry);
    assert!(b.requests(&s, t0 + retry * 10).is_empty(), "a completed request is not repeated");
}

#[test]
fn a_full_request_is_followed_by_the_next_piece_at_once() {
    let mut s = FleetState::default();
    s.insert_keyframe(&received(1, 0));
    let t0 = Instant::now();
    let mut b = Backfill::new(Duration::from_secs(2));
    b.want(1, Want::Everything);
    assert_eq!(b.requests(&s, t0).len(), 1);
    for seq in 1..=u64::from(MAX_KEYFRAMES_PER_REQUEST) {
        s.insert_keyframe(&received(1, seq));
    }
    b.done(1, Ended::Full, t0);
    let next = KeyframeRequest {
        seqs: vec![],
        from_seq: Some(u64::from(MAX_KEYFRAMES_PER_REQUEST) + 1),
        limit: Some(MAX_KEYFRAMES_PER_REQUEST),
        session: Some(0),
    };
    assert_eq!(b.requests(&s, t0), vec![(1, next)]);
    b.done(1, Ended::Complete, t0);
    assert!(b.requests(&s, t0).is_empty(), "the robot had no more");
}

#[test]
fn gaps_that_nothing_new_reveals_are_asked_for_again() {
    let mut s = FleetState::default();
    for seq in [0, 2] {
        s.insert_keyframe(&received(1, seq));
    }
    s.insert_keyframe(&received(2, 0));
    let t0 = Instant::now();
    let retry = Duration::from_secs(2);
    let mut b = Backfill::new(retry);
    b.want(1, Want::Gaps);
    assert_eq!(b.requests(&s, t0).len(), 1);
    b.done(1, Ended::Complete, t0);
    b.recheck(&s);
    assert!(b.requests(&s, t0 + retry / 2).is_empty(), "the same gaps before the retry delay");
    b.recheck(&s);
    let again = b.requests(&s, t0 + retry);
    assert_eq!(
        again,
        vec![(
            1,
            KeyframeRequest { seqs: vec![1], from_seq: None, limit: Some(MAX_KEYFRAMES_PER_REQUEST), session: Some(0) }
        )],
        "robot 2 has no gap"
    );
}

// ---------------------------------------------------------------- stations on loopback

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_station_backfills_exactly_the_hole() {
    let (station_session, robot, port) = sessions().await;
    let station = Station::start(station_session, config()).await.unwrap();
    let mut progress = station.progress();
    let requests = fake_store(&robot, 1, (0..7).collect()).await;
    let keyframes = publisher(&robot, keyexpr::keyframe(&fleet(), 1)).await;
    for seq in [0, 1, 2, 5, 6] {
        keyframes.put(keyframe_bytes(1, seq)).await.unwrap();
    }
    let p = wait_for(&mut progress, "7 keyframes merged", |p| p.total_keyframes() == 7 && p.up_to_date()).await;
    assert_eq!(p.backfilled, 2);
    assert_eq!(p.missing, 0);
    assert_eq!(
        *requests.lock().unwrap(),
        vec![KeyframeRequest {
            seqs: vec![3, 4],
            from_seq: None,
            limit: Some(MAX_KEYFRAMES_PER_REQUEST),
            session: Some(0)
        }]
    );
    let (map, _) =
        client::fetch_global_map(&client_session(port).await, &fleet(), Duration::from_secs(5)).await.unwrap();
    assert_eq!(map.revision, p.revision);
    assert_eq!(map.robots.len(), 1);
    assert_eq!(map.robots[0].keyframes, 7);
    // It says what it holds for the robot: every keyframe as received, and for the merge at least
    // its copy of the robot's map, which has as many points as the global map of one robot.
    let sent: u64 = (0..7).map(|seq| keyframe_bytes(1, seq).len() as u64).sum();
    assert_eq!(p.memory[&1].keyframes, sent);
    let points = map.cloud.as_ref().unwrap().points;
    assert!(p.memory[&1].map >= points * 12, "{:?} for a map of {points} points", p.memory[&1]);
    let summary = station.stop().await.unwrap();
    assert_eq!(summary.keyframes, BTreeMap::from([(1, 7)]));
    assert_eq!(summary.global_map.unwrap().revision, map.revision);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_station_started_late_fetches_everything_from_a_live_robot() {
    let (station_session, robot, _) = sessions().await;
    let _token = robot.liveliness().declare_token(keyexpr::alive(&fleet(), 4)).await.unwrap();
    let requests = fake_store(&robot, 4, (0..20).collect()).await;
    let station = Station::start(station_session, config()).await.unwrap();
    let mut progress = station.progress();
    wait_for(&mut progress, "the robot's 20 keyframes", |p| p.total_keyframes() == 20 && p.up_to_date()).await;
    // In pieces of the request limit, each asking on from the newest held.
    let asked: Vec<Option<u64>> = requests.lock().unwrap().iter().map(|r| r.from_seq).collect();
    assert_eq!(asked[..3], [Some(0), Some(8), Some(16)], "{asked:?}");
    assert_eq!(requests.lock().unwrap()[0].limit, Some(MAX_KEYFRAMES_PER_REQUEST));
    station.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_payloads_are_counted_and_the_station_goes_on() {
    let (station_session, robot, _) = sessions().await;
    let station = Station::start(station_session, config()).await.unwrap();
    let mut progress = station.progress();
    let f = fleet();
    let keyframes = publisher(&robot, keyexpr::keyframe(&f, 2)).await;
    let poses = publisher(&robot, keyexpr::posegraph(&f, 2)).await;
    let good = keyframe_bytes(2, 0);
    keyframes.put(vec![0xffu8; 64]).await.unwrap();
    keyframes.put(good[..good.len() - 7].to_vec()).await.unwrap();
    keyframes.put(keyframe_msg("otherfleet", 2, 0).encode_to_vec()).await.unwrap();
    keyframes.put(keyframe_bytes(3, 0)).await.unwrap();
    poses.put(vec![0x0a, 0xff, 0xff]).await.unwrap();
    keyframes.put(good).await.unwrap();
    let update = PoseGraphUpdate {
        fleet: f.to_string(),
        robot: 2,
        revision: 1,
        poses: vec![KeyframePose { seq: 0, pose: Some(Pose::from(Isometry3::new(Vector3::x(), Vector3::zeros()))) }],
        loops: vec![],
        session: 0,
    };
    poses.put(update.encode_to_vec()).await.unwrap();
    let p = wait_for(&mut progress, "the good keyframe", |p| p.total_keyframes() == 1 && p.up_to_date()).await;
    assert_eq!(p.malformed, 5);
    let summary = station.stop().await.unwrap();
    assert_eq!(summary.malformed, 5);
    assert_eq!(summary.keyframes, BTreeMap::from([(2, 1)]));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_a_kill_the_station_reloads_and_serves_the_same_map() {
    let dir = tempfile::tempdir().unwrap();
    let config = StationConfig { data_dir: Some(dir.path().to_owned()), ..config() };
    let (station_session, robot, port) = sessions().await;
    let station = Station::start(station_session, config.clone()).await.unwrap();
    let mut progress = station.progress();
    for r in [1, 2] {
        let keyframes = publisher(&robot, keyexpr::keyframe(&fleet(), r)).await;
        for seq in 0..3 {
            keyframes.put(keyframe_bytes(r, seq)).await.unwrap();
        }
    }
    let before = wait_for(&mut progress, "6 keyframes merged and committed", |p| {
        p.total_keyframes() == 6
            && p.up_to_date()
            && p.committed.keyframes == 6
            && p.committed.map_revision == p.revision
    })
    .await;
    let (map, bytes) =
        client::fetch_global_map(&client_session(port).await, &fleet(), Duration::from_secs(5)).await.unwrap();
    assert_eq!(map.revision, before.revision);
    station.kill().await;
    drop(robot);

    let port = bus::free_port().unwrap();
    let session = bus::Network::loopback_ports(&[port], &[]).open().await.unwrap();
    let restarted = Station::start(session, config).await.unwrap();
    let after = restarted.progress().borrow().clone();
    assert_eq!(after.keyframes, BTreeMap::from([(1, 3), (2, 3)]));
    assert_eq!(after.revision, before.revision);
    assert!(after.up_to_date(), "nothing changed: no re-merge");
    let (again, again_bytes) =
        client::fetch_global_map(&client_session(port).await, &fleet(), Duration::from_secs(5)).await.unwrap();
    assert_eq!(again.revision, map.revision);
    assert_eq!(again_bytes, bytes);
    let summary = restarted.stop().await.unwrap();
    assert_eq!(summary.merges, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_database_that_cannot_be_opened_is_named() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("station.redb"), b"not a database at all").unwrap();
    let session = bus::Network::loopback_ports(&[bus::free_port().unwrap()], &[]).open().await.unwrap();
    let config = StationConfig { data_dir: Some(dir.path().to_owned()), ..config() };
    let err = Station::start(session, config).await.err().expect("a corrupt file must not open");
    assert!(err.to_string().contains("station.redb"), "{err}");
}

#[test]
fn watch_summaries_name_the_type_and_survive_garbage() {
    let f = fleet();
    let s = client::summarize(&keyexpr::keyframe(&f, 1), &keyframe_bytes(1, 3));
    assert_eq!(s.kind, "Keyframe");
    assert!(s.to_line().contains("seq=3"), "{}", s.to_line());
    let bad = client::summarize(&keyexpr::global_map(&f), &[0xff, 0xff]);
    assert_eq!(bad.kind, "GlobalMap");
    assert!(bad.to_json()["malformed"].is_string());
    assert_eq!(client::summarize("some/other/key", b"x").kind, "unknown");
}

/// The robot's pose graph: keyframes `moved` raised by 1 m, the others at their odometry poses.
fn raised(robot: u32, seqs: std::ops::Range<u64>, moved: &[u64], revision: u64) -> PoseGraphUpdate {
    let pose = |seq: u64| {
        let lift = if moved.contains(&seq) { 1.0 } else { 0.0 };
        Pose::from(Isometry3::translation(0.0, 0.0, lift) * odom(seq))
    };
    PoseGraphUpdate {
        fleet: fleet().to_string(),
        robot,
        revision,
        poses: seqs.map(|seq| KeyframePose { seq, pose: Some(pose(seq)) }).collect(),
        loops: vec![],
        session: 0,
    }
}

/// Points of the published global map above the room's 2.5 m ceiling.
async fn points_above_the_ceiling(port: u16) -> usize {
    let (map, _) =
        client::fetch_global_map(&client_session(port).await, &fleet(), Duration::from_secs(5)).await.unwrap();
    let cloud = codec::decode(&map.cloud.unwrap().data).unwrap();
    cloud.points.iter().filter(|p| p.z > 2.6).count()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_pose_graph_update_re_places_the_keyframes_in_the_global_map() {
    let (station_session, robot, port) = sessions().await;
    let station = Station::start(station_session, config()).await.unwrap();
    let mut progress = station.progress();
    let keyframes = publisher(&robot, keyexpr::keyframe(&fleet(), 1)).await;
    for seq in 0..3 {
        keyframes.put(keyframe_bytes(1, seq)).await.unwrap();
    }
    let before = wait_for(&mut progress, "3 keyframes merged", |p| p.total_keyframes() == 3 && p.up_to_date()).await;
    assert_eq!(points_above_the_ceiling(port).await, 0, "the keyframes at their odometry poses");
    // The robot closed a loop: its optimiser raised keyframe 2 by a metre. No cloud is sent again.
    let poses = publisher(&robot, keyexpr::posegraph(&fleet(), 1)).await;
    poses.put(raised(1, 0..3, &[2], 1).encode_to_vec()).await.unwrap();
    let after = wait_for(&mut progress, "the re-merge", |p| {
        p.pose_revisions.get(&1) == Some(&1) && p.up_to_date() && p.revision > before.revision
    })
    .await;
    assert_eq!(after.total_keyframes(), 3);
    assert!(points_above_the_ceiling(port).await > 50, "keyframe 2's ceiling is a metre higher");
    // An older revision arriving late changes nothing.
    poses.put(raised(1, 0..3, &[], 0).encode_to_vec()).await.unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(station.progress().borrow().revision, after.revision);
    station.stop().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_station_started_late_asks_a_live_robot_for_its_newest_pose_graph() {
    let (station_session, robot, port) = sessions().await;
    let _token = robot.liveliness().declare_token(keyexpr::alive(&fleet(), 4)).await.unwrap();
    fake_store(&robot, 4, (0..3).collect()).await;
    let key = keyexpr::posegraph(&fleet(), 4);
    let queryable = robot.declare_queryable(key.clone()).await.unwrap();
    tokio::spawn(async move {
        while let Ok(query) = queryable.recv_async().await {
            query.reply(key.clone(), raised(4, 0..3, &[1, 2], 7).encode_to_vec()).await.unwrap();
        }
    });
    let station = Station::start(station_session, config()).await.unwrap();
    let mut progress = station.progress();
    wait_for(&mut progress, "the keyframes and the pose graph", |p| {
        p.total_keyframes() == 3 && p.pose_revisions.get(&4) == Some(&7) && p.up_to_date()
    })
    .await;
    assert!(points_above_the_ceiling(port).await > 50);
    station.stop().await.unwrap();
}
