//! The running system: `emr-station run` and two `emr-edge run` processes replaying the simulated
//! `warehouse-large` robots on 127.0.0.1, judged against the simulator's ground truth.
//!
//! Every process is a zenoh peer on loopback with scouting off; the station listens on a free port
//! and the edges and the observer connect to it.

use std::path::Path;
use std::time::Duration;

use prost::Message;
use proto::{CompressedCloud, GlobalMap, Keyframe, Pose, Timestamp};
use tests::*;

const SCENARIO: &str = "warehouse-large";
/// Scans each robot replays: 90 s of driving, ~140 keyframes each; by then 60 % of robot 2's path
/// runs within 3 m of robot 1's (at 600 scans, 28 %: too little for a confident merge).
const FRAMES: usize = 900;
const FLEET: &str = "systest";
const TIMEOUT: Duration = Duration::from_secs(600);

/// The bar for the system: each robot placed within 10 cm of the truth.
const MAX_PLACEMENT_ERROR_M: f64 = 0.10;

/// A station and its two edges.
struct Fleet {
    station: Process,
    edges: Vec<Process>,
    port: u16,
    dir: tempfile::TempDir,
}

impl Fleet {
    fn start(name: &str) -> Fleet {
        let dir = scratch();
        let port = bus::free_port().unwrap();
        let station = start_station(name, port, dir.path());
        let edges = (1..=2).map(|r| start_edge(name, r, port, dir.path())).collect();
        Fleet { station, edges, port, dir }
    }

    fn procs(&mut self) -> Vec<&mut Process> {
        let mut all: Vec<&mut Process> = vec![&mut self.station];
        all.extend(self.edges.iter_mut());
        all
    }

    /// Waits for both edges to finish their scans; returns (robot, keyframes) for each.
    fn wait_edges(&mut self) -> Vec<(u32, u64)> {
        let dir = self.dir.path().to_owned();
        (1..=2u32).map(|r| (r, wait_summary(&summary_path(&dir, r), TIMEOUT, &mut self.procs()).keyframes)).collect()
    }

    /// Waits for a global map holding every keyframe of both robots.
    fn wait_complete_map(&mut self, observer: &Observer, keyframes: &[(u32, u64)]) -> GlobalMap {
        observer.wait_global_map(TIMEOUT, &mut self.procs(), |m| settled_with_all(m, keyframes))
    }
}

fn start_station(name: &str, port: u16, dir: &Path) -> Process {
    let args = station_args(FLEET, port, &dir.join("station-data"));
    Process::start(&format!("{name}-station"), &binary("emr-station"), &args, dir)
}

fn start_edge(name: &str, robot: u32, port: u16, dir: &Path) -> Process {
    let args = edge_args(FLEET, SCENARIO, robot, FRAMES, port, &summary_path(dir, robot));
    Process::start(&format!("{name}-edge{robot}"), &binary("emr-edge"), &args, dir)
}

fn summary_path(dir: &Path, robot: u32) -> std::path::PathBuf {
    dir.join(format!("edge{robot}-summary.json"))
}

/// Both robots merged, the non-reference one within 10 cm and 1 degree of the truth.
fn assert_placed_like_the_truth(map: &GlobalMap) {
    assert!(all_merged(map), "not every robot merged: {}", describe(map));
    let reference = map.reference_robot;
    for r in map.robots.iter().map(|r| r.robot) {
        let (dt, dr) = difference(&placement(map, r), &true_placement(SCENARIO, reference, r));
        println!("robot {r} in robot {reference}'s frame: {:.1} cm, {dr:.3} deg from the truth", dt * 100.0);
        assert!(dt < MAX_PLACEMENT_ERROR_M && dr < 1.0, "robot {r}: {dt:.3} m / {dr:.2} deg off; {}", describe(map));
    }
}

#[test]
fn two_edges_and_a_station_merge_the_warehouse() {
    let mut fleet = Fleet::start("plain");
    let observer = Observer::connect(FLEET, fleet.port);
    let keyframes = fleet.wait_edges();
    let map = fleet.wait_complete_map(&observer, &keyframes);
    assert_placed_like_the_truth(&map);
    assert!(
        map.cloud.as_ref().is_some_and(|c| c.points > 10_000),
        "global map cloud: {:?}",
        map.cloud.as_ref().map(|c| c.points)
    );
    let status = fleet.station.terminate(Duration::from_secs(10));
    assert!(
        status.is_some_and(|s| s.success()),
        "station did not exit cleanly on SIGTERM: {status:?}\n{}",
        fleet.station.tail()
    );
}

#[test]
fn killed_station_and_edge_lose_no_keyframe() {
    // The uninterrupted run the interrupted one must match.
    let mut calm = Fleet::start("calm");
    let calm_observer = Observer::connect(FLEET, calm.port);
    let calm_keyframes = calm.wait_edges();
    let calm_map = calm.wait_complete_map(&calm_observer, &calm_keyframes);
    drop(calm);

    let mut rough = Fleet::start("rough");
    let observer = Observer::connect(FLEET, rough.port);
    // Once the station has published a first map, kill -9 it and edge 2 mid-run.
    let before = observer.wait_global_map(TIMEOUT, &mut rough.procs(), |_| true);
    assert!(!summary_path(rough.dir.path(), 2).exists(), "edge 2 finished before it could be killed mid-run");
    rough.station.kill9();
    rough.edges[1].kill9();
    std::thread::sleep(Duration::from_secs(3));
    rough.station = start_station("rough", rough.port, rough.dir.path());
    // The restarted station serves what it had published before the kill, or newer.
    let again = observer.wait_global_map(Duration::from_secs(30), &mut rough.procs(), |_| true);
    assert!(again.revision >= before.revision, "revision went back: {} -> {}", before.revision, again.revision);
    if again.revision == before.revision {
        assert_eq!(again.encode_to_vec(), before.encode_to_vec(), "same revision, different map after restart");
    }
    rough.edges[1] = start_edge("rough", 2, rough.port, rough.dir.path());
    let keyframes = rough.wait_edges();
    assert_eq!(keyframes, calm_keyframes, "the edges made different keyframes");
    let map = rough.wait_complete_map(&observer, &keyframes);
    assert_placed_like_the_truth(&map);
    for r in 1..=2 {
        let (dt, dr) = difference(&placement(&map, r), &placement(&calm_map, r));
        assert!(dt < 0.01 && dr < 0.1, "robot {r} placed {dt:.4} m / {dr:.3} deg away from the uninterrupted run");
    }
    // Every part of the uninterrupted map is in the interrupted one and nothing else is: each
    // point has one of the other's within a voxel of the global map (the station's default).
    let voxel = station::merge::MergeConfig::default().output_voxel;
    for (a, b, name) in [(&calm_map, &map, "uninterrupted"), (&map, &calm_map, "interrupted")] {
        let share = covered_share(a, b, voxel);
        println!("{:.2} % of the {name} map's points have a point of the other's within {voxel} m", share * 100.0);
        assert!(share >= 0.99, "only {:.2} % of the {name} map is in the other", share * 100.0);
    }
}

#[test]
fn a_hostile_publisher_does_not_stop_the_station() {
    let mut fleet = Fleet::start("hostile");
    let observer = Observer::connect(FLEET, fleet.port);
    let sent = observer.runtime.block_on(attack(&observer.session));
    let keyframes = fleet.wait_edges();
    let map = fleet.wait_complete_map(&observer, &keyframes);
    assert_placed_like_the_truth(&map);
    let status = observer.next_status(Duration::from_secs(10)).expect("station status");
    assert!(
        status.malformed_payloads >= sent,
        "{} malformed payloads counted of {sent} sent",
        status.malformed_payloads
    );
    assert!(fleet.station.running(), "{}", fleet.station.tail());
}

/// Publishes garbage, truncated, inconsistent and oversized payloads on the fleet's robot topics;
/// returns how many it sent.
async fn attack(session: &zenoh::Session) -> u64 {
    let fleet = proto::Fleet::new(FLEET).unwrap();
    let valid = Keyframe {
        fleet: FLEET.into(),
        robot: 1,
        seq: 3,
        stamp: Some(Timestamp { sec: 1, nanosec: 0 }),
        odom_pose: Some(Pose::identity()),
        scan_context: None,
        cloud: Some(CompressedCloud { data: vec![0xEE; 64].into(), points: 1000 }),
    }
    .encode_to_vec();
    let wrong_fleet = Keyframe { fleet: "other".into(), ..Keyframe::decode(valid.as_slice()).unwrap() }.encode_to_vec();
    let far_future = Keyframe { seq: 1 << 40, ..Keyframe::decode(valid.as_slice()).unwrap() }.encode_to_vec();
    let mut lcg = 0x2545_f491_4f6c_dd1du64;
    let garbage: Vec<u8> = (0..4096)
        .map(|_| {
            lcg = lcg.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (lcg >> 56) as u8
        })
        .collect();
    let payloads: Vec<(String, Vec<u8>)> = vec![
        (proto::keyexpr::keyframe(&fleet, 1), garbage.clone()),
        (proto::keyexpr::keyframe(&fleet, 2), valid[..valid.len() / 2].to_vec()),
        (proto::keyexpr::keyframe(&fleet, 1), valid.clone()),
        (proto::keyexpr::keyframe(&fleet, 1), wrong_fleet),
        (proto::keyexpr::keyframe(&fleet, 2), far_future),
        (proto::keyexpr::posegraph(&fleet, 1), garbage.clone()),
        (proto::keyexpr::keyframe(&fleet, 7), vec![0xFF; 80 << 20]),
    ];
    let sent = payloads.len() as u64;
    for (key, bytes) in payloads {
        let publisher =
            session.declare_publisher(key).congestion_control(zenoh::qos::CongestionControl::Block).await.unwrap();
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        while !publisher.matching_status().await.unwrap().matching() && std::time::Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        publisher.put(bytes).await.unwrap();
    }
    sent
}

/// A robot that boots before its router is up: a zenoh client gives up at its first failed
/// connection, so the edge keeps trying to join, and once the station listens every keyframe
/// arrives.
#[test]
fn a_robot_started_before_its_router_joins_once_the_router_is_up() {
    let dir = scratch();
    let port = bus::free_port().unwrap();
    let client =
        tests::hosts::write_file(dir.path(), "client.json5", &tests::hosts::client_config(&bus::endpoint(port)));
    let summary = summary_path(dir.path(), 1);
    let mut args = edge_args(FLEET, SCENARIO, 1, 100, port, &summary);
    args.truncate(args.len() - 2);
    args.extend(["--zenoh".into(), client.display().to_string()]);
    let mut edge = Process::start("early-edge1", &binary("emr-edge"), &args, dir.path());

    // Nothing listens yet: the edge says it will try again, and keeps running.
    let log = dir.path().join("early-edge1.log");
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    while !std::fs::read_to_string(&log).unwrap_or_default().contains("trying again") {
        assert!(edge.running(), "the edge gave up without a router\n{}", edge.tail());
        assert!(std::time::Instant::now() < deadline, "the edge did not say it tries again\n{}", edge.tail());
        std::thread::sleep(Duration::from_millis(100));
    }
    std::thread::sleep(Duration::from_secs(2));
    assert!(edge.running(), "the edge gave up without a router\n{}", edge.tail());
    assert!(!summary.exists(), "the edge mapped before it joined");

    let mut station = start_station("late", port, dir.path());
    let observer = Observer::connect(FLEET, port);
    let keyframes = wait_summary(&summary, TIMEOUT, &mut [&mut edge, &mut station]).keyframes;
    assert!(keyframes > 0);
    let map = observer.wait_global_map(TIMEOUT, &mut [&mut edge, &mut station], |m| holds_all(m, &[(1, keyframes)]));
    println!("joined late: {keyframes} keyframes, {}", describe(&map));
}
