//! ROS 2 with no bridge, checked at the wire by an independent peer: `tests/scripts/ros2_peer.py`
//! (Python zenoh, rosbags' CDR and RIHS01 hashes, xxhash; no code of ours) finds our topics from
//! rmw_zenoh's liveliness tokens alone, reads them as a ROS 2 node would, and publishes KITTI scans
//! as a ROS 2 LiDAR driver would.
//!
//! Needs python3 with eclipse-zenoh, rosbags and xxhash (`.ci/run` installs them).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use serde_json::Value;
use tests::*;

const FLEET: &str = "ros2-fleet";
/// The fleet's ROS 2 namespace: its name with `-` written `_`.
const NAMESPACE: &str = "/emr/ros2_fleet";
const SCENARIO: &str = "warehouse-small";
/// Scans each robot replays (robot 2 is not placed in robot 1's map by then: the topics of an
/// unplaced robot are checked too).
const FRAMES: usize = 300;
const TIMEOUT: Duration = Duration::from_secs(600);

fn peer_script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/ros2_peer.py")
}

/// The peer, started with `args`; stderr into `log`.
fn peer(args: &[String], log: &Path) -> Child {
    Command::new("python3")
        .arg(peer_script())
        .args(args)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(log.with_extension("out")).unwrap())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start python3 ({e}): install it with eclipse-zenoh, rosbags, xxhash"))
}

/// Waits for the peer and reads what it wrote to `out`; panics with its log if it failed.
fn finished(mut child: Child, out: &Path, log: &Path) -> Value {
    let status = child.wait().unwrap();
    let said = std::fs::read_to_string(log).unwrap_or_default();
    assert!(status.success(), "the ROS 2 peer failed ({status}):\n{said}");
    serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap()
}

/// `listen` arguments: the first `count` samples of `ty` on `topic`, reached through `endpoints`.
fn listen(endpoints: &[String], ty: &str, topic: &str, count: usize, out: &Path) -> Vec<String> {
    let mut args: Vec<String> = vec!["listen".into()];
    for e in endpoints {
        args.extend(["--connect".into(), e.clone()]);
    }
    args.extend(
        [
            "--type",
            ty,
            "--topic",
            topic,
            "--count",
            &count.to_string(),
            "--timeout",
            "300",
            "--out",
            &out.display().to_string(),
        ]
        .map(String::from),
    );
    args
}

/// The one sample the peer read, checked: rmw_zenoh's 33-byte attachment whose id is its token's,
/// a type hash equal to rosbags' for the type.
fn checked_samples(got: &Value) -> &Vec<Value> {
    assert_eq!(got["type_hash_ok"], true, "type hash differs from rosbags': {}", got["token"]);
    let samples = got["samples"].as_array().expect("samples");
    assert!(!samples.is_empty());
    for s in samples {
        assert_eq!(s["attachment_len"], 33, "attachment of {}", got["key"]);
        assert_eq!(s["gid_matches_token"], true, "publisher id of {}", got["key"]);
        assert!(s["sequence"].as_i64().unwrap() >= 1);
    }
    samples
}

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array().expect("an array").iter().map(|x| x.as_f64().expect("a number")).collect()
}

fn isometry(pose_or_transform: &Value, position: &str, orientation: &str) -> Isometry3<f64> {
    let (p, q) = (&pose_or_transform[position], &pose_or_transform[orientation]);
    let n = |v: &Value, k: &str| v[k].as_f64().unwrap();
    Isometry3::from_parts(
        Translation3::new(n(p, "x"), n(p, "y"), n(p, "z")),
        UnitQuaternion::from_quaternion(Quaternion::new(n(q, "w"), n(q, "x"), n(q, "y"), n(q, "z"))),
    )
}

#[test]
fn an_independent_ros2_node_sees_the_map_paths_tf_status_and_odometry() {
    let dir = scratch();
    let out = |name: &str| dir.path().join(name);
    let ports: Vec<u16> = (0..3).map(|_| bus::free_port().unwrap()).collect();
    let endpoints: Vec<String> = ports.iter().map(|&p| bus::endpoint(p)).collect();
    let mut station_args = station_args(FLEET, ports[0], &out("station-data"));
    station_args.push("--ros2".into());
    let mut station = Process::start("station", &binary("emr-station"), &station_args, dir.path());
    // Robot 2's odometry and keyframes are volatile: subscribed before it starts (the peer waits
    // for the topic's token). Peers do not forward each other's samples: it connects to robot 2.
    let robot2 = &endpoints[2..];
    let odometry_topic = format!("{NAMESPACE}/robot2/odometry");
    let odometry =
        peer(&listen(robot2, "nav_msgs/msg/Odometry", &odometry_topic, 5, &out("odometry.json")), &out("odometry.log"));
    let keyframe_topic = format!("{NAMESPACE}/robot2/keyframe");
    let keyframe = peer(
        &listen(robot2, "sensor_msgs/msg/PointCloud2", &keyframe_topic, 1, &out("keyframe.json")),
        &out("keyframe.log"),
    );
    let mut edges: Vec<Process> = (1..=2u32)
        .map(|robot| {
            let mut args = edge_args(FLEET, SCENARIO, robot, FRAMES, ports[0], &out(&format!("edge{robot}.json")));
            args.extend(["--listen".into(), endpoints[robot as usize].clone(), "--ros2".into()]);
            Process::start(&format!("edge{robot}"), &binary("emr-edge"), &args, dir.path())
        })
        .collect();
    let observer = Observer::connect(FLEET, ports[0]);
    let mut keyframes = Vec::new();
    for robot in 1..=2u32 {
        let mut procs: Vec<&mut Process> = vec![&mut station];
        procs.extend(edges.iter_mut());
        keyframes.push((robot, wait_summary(&out(&format!("edge{robot}.json")), TIMEOUT, &mut procs).keyframes));
    }
    let mut procs: Vec<&mut Process> = vec![&mut station];
    procs.extend(edges.iter_mut());
    let map = observer.wait_global_map(TIMEOUT, &mut procs, |m| settled_with_all(m, &keyframes));
    println!("{}", describe(&map));

    // The map, as a late joiner gets it from the transient-local publisher's cache.
    let station_only = &endpoints[..1];
    let late = peer(&listen(station_only, "sensor_msgs/msg/PointCloud2", "map", 1, &out("map.json")), &out("map.log"));
    let got = finished(late, &out("map.json"), &out("map.log"));
    assert_eq!(
        got["key"],
        format!("0/emr/ros2_fleet/map/sensor_msgs::msg::dds_::PointCloud2_/{}", proto::ros2::POINT_CLOUD2.hash)
    );
    assert_eq!(got["transient_local"], true);
    let message = &checked_samples(&got)[0]["message"];
    assert_eq!(message["header"]["frame_id"], "map");
    assert_same_points(message, &map);

    // Robot 1's path: its keyframes, in its odometry frame.
    let path_topic = format!("{NAMESPACE}/robot1/path");
    let got = finished(
        peer(&listen(station_only, "nav_msgs/msg/Path", &path_topic, 1, &out("path.json")), &out("path.log")),
        &out("path.json"),
        &out("path.log"),
    );
    let path = &checked_samples(&got)[0]["message"];
    assert_eq!(path["header"]["frame_id"], "robot1/odom");
    assert_eq!(path["poses"].as_array().unwrap().len() as u64, keyframes[0].1, "robot 1's path");

    // /tf: map -> robotN/odom at the placements of the map.
    let got = finished(
        peer(&listen(station_only, "tf2_msgs/msg/TFMessage", "/tf", 1, &out("tf.json")), &out("tf.log")),
        &out("tf.json"),
        &out("tf.log"),
    );
    let transforms = checked_samples(&got)[0]["message"]["transforms"].as_array().unwrap().clone();
    // Each placed robot's, and only those.
    let merged: Vec<u32> =
        map.robots.iter().filter(|r| r.status == proto::MergeStatus::Merged as i32).map(|r| r.robot).collect();
    assert_eq!(transforms.len(), merged.len(), "{transforms:?}");
    for &robot in &merged {
        let t = transforms
            .iter()
            .find(|t| t["child_frame_id"] == format!("robot{robot}/odom"))
            .unwrap_or_else(|| panic!("no transform of robot {robot} in {transforms:?}"));
        assert_eq!(t["header"]["frame_id"], "map");
        let (metres, degrees) =
            difference(&isometry(&t["transform"], "translation", "rotation"), &placement(&map, robot));
        assert!(metres < 1e-9 && degrees < 1e-6, "robot {robot}'s transform differs by {metres} m, {degrees} deg");
    }

    // The status, as JSON in a std_msgs/String.
    let got = finished(
        peer(&listen(station_only, "std_msgs/msg/String", "status", 1, &out("status.json")), &out("status.log")),
        &out("status.json"),
        &out("status.log"),
    );
    let status: Value = serde_json::from_str(checked_samples(&got)[0]["message"]["data"].as_str().unwrap()).unwrap();
    assert_eq!(status["fleet"], FLEET);

    // Robot 2's odometry and a keyframe, as its own ROS 2 stack would see them.
    let got = finished(odometry, &out("odometry.json"), &out("odometry.log"));
    let samples = checked_samples(&got);
    assert_eq!(samples.len(), 5);
    let first_stamp = &samples[0]["message"]["header"]["stamp"];
    assert_eq!(samples[0]["message"]["header"]["frame_id"], "robot2/odom");
    assert_eq!(samples[0]["message"]["child_frame_id"], "robot2/lidar");
    let sequences: Vec<i64> = samples.iter().map(|s| s["sequence"].as_i64().unwrap()).collect();
    assert!(sequences.windows(2).all(|w| w[1] == w[0] + 1), "sequence numbers {sequences:?}");
    println!("robot 2's odometry from stamp {first_stamp}, sequence numbers {sequences:?}");
    let got = finished(keyframe, &out("keyframe.json"), &out("keyframe.log"));
    let cloud = &checked_samples(&got)[0]["message"];
    assert_eq!(cloud["header"]["frame_id"], "robot2/odom");
    let xs = f64s(&cloud["columns"]["x"]);
    assert!(xs.len() > 100 && xs.iter().all(|x| x.is_finite()), "a keyframe of {} points", xs.len());
}

/// The peer's PointCloud2 holds the global map's points, each within 1 mm of one of them (the
/// map's cloud is quantised to 1 mm and may be reordered), as many, labelled with merged robots.
fn assert_same_points(message: &Value, map: &proto::GlobalMap) {
    let columns = &message["columns"];
    let (x, y, z) = (f64s(&columns["x"]), f64s(&columns["y"]), f64s(&columns["z"]));
    let data = map.cloud.as_ref().map(|c| c.data.as_ref()).unwrap_or(&[][..]);
    let reference = proto::codec::decode(data).expect("the global map decodes").points;
    assert_eq!(x.len(), reference.len(), "points in the ROS 2 map and the GlobalMap");
    assert!(x.len() > 1000, "a map of {} points", x.len());
    let tree = cloud::kdtree::KdTree::from_points(&reference);
    let far =
        (0..x.len()).filter(|&i| tree.nearest_within(&[x[i] as f32, y[i] as f32, z[i] as f32], 1e-3).is_none()).count();
    assert_eq!(far, 0, "{far} of {} points are more than 1 mm from the GlobalMap's", x.len());
    let merged: BTreeSet<u64> = map
        .robots
        .iter()
        .filter(|r| r.status == proto::MergeStatus::Merged as i32)
        .map(|r| u64::from(r.robot))
        .collect();
    let robots: BTreeSet<u64> = f64s(&columns["robot"]).iter().map(|&r| r as u64).collect();
    assert_eq!(robots, merged, "robots labelling the points");
    let sessions: BTreeSet<u64> = f64s(&columns["session"]).iter().map(|&s| s as u64).collect();
    let placed: BTreeSet<u64> = map.robots.iter().map(|r| r.session).collect();
    assert!(sessions.is_subset(&placed), "sessions {sessions:?} of the points, {placed:?} in the map");
    println!("{} points within 1 mm of the GlobalMap's, robots {robots:?}, sessions {sessions:?}", x.len());
}

#[test]
fn kitti_scans_from_a_ros2_driver_give_the_poses_the_files_give() {
    let dir = scratch();
    let out = |name: &str| dir.path().join(name);
    let kitti = testkit::shared_data("kitti00");
    let frames = 16;
    let odometry = |input: &str, to: &Path, extra: &[String]| {
        let mut cmd = Command::new(binary("emr-edge"));
        cmd.args(["odometry", input, "--no-loops", "--max-frames", &frames.to_string()])
            .arg("--out")
            .arg(to)
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(to.with_extension("log")).unwrap());
        cmd
    };
    let files = odometry(&kitti.display().to_string(), &out("files"), &[]).output().unwrap();
    assert!(files.status.success(), "odometry on the files failed");

    // The driver: the scans at 2 Hz, once a subscription to its topic is announced.
    let publish = |endpoint: &str, log: &str| {
        let args = [
            "publish",
            "--connect",
            endpoint,
            "--topic",
            "/points",
            "--kitti",
            &kitti.display().to_string(),
            "--frames",
            &frames.to_string(),
            "--rate",
            "2",
        ]
        .map(String::from);
        let published = peer(&args, &out(log)).wait_with_output().unwrap();
        let said = std::fs::read_to_string(out(log)).unwrap_or_default();
        assert!(published.status.success(), "the publishing peer failed:\n{said}");
    };
    let endpoint = bus::endpoint(bus::free_port().unwrap());
    let mut topic = odometry("ros2:/points", &out("topic"), &["--listen".into(), endpoint.clone()]).spawn().unwrap();
    publish(&endpoint, "publisher.log");
    let status = topic.wait().unwrap();
    let log = std::fs::read_to_string(out("topic.log")).unwrap_or_default();
    assert!(status.success(), "odometry on ros2:/points failed:\n{log}");
    let read = |d: &str| std::fs::read_to_string(out(d).join("poses_kitti.txt")).unwrap();
    let (from_files, from_topic) = (read("files"), read("topic"));
    assert_eq!(from_topic.lines().count(), frames, "poses from the topic");
    let poses = |text: &str| -> Vec<Vec<f64>> {
        text.lines().map(|l| l.split_whitespace().map(|v| v.parse().unwrap()).collect()).collect()
    };
    let worst = poses(&from_files)
        .iter()
        .zip(poses(&from_topic))
        .flat_map(|(a, b)| a.iter().zip(b).map(|(x, y)| (x - y).abs()).collect::<Vec<_>>())
        .fold(0.0, f64::max);
    println!("{frames} KITTI scans over ROS 2: poses differ from the files' by at most {worst:e}");
    // The same scans, stamps and channels: only the order of parallel sums may differ.
    assert!(worst < 1e-6, "poses from the topic differ from the files' by up to {worst}");
    let stats: Value =
        serde_json::from_str(&std::fs::read_to_string(out("topic").join("stats.json")).unwrap()).unwrap();
    assert_eq!(stats["source_losses"]["dropped_scans"], 0, "{}", stats["source_losses"]);

    // The robot's service reads the topic as the odometry command does.
    let endpoint = bus::endpoint(bus::free_port().unwrap());
    let summary = out("run.json");
    let run = [
        "run",
        "--fleet",
        "ros2-kitti",
        "--robot",
        "1",
        "--source",
        "ros2:/points",
        "--max-frames",
        &frames.to_string(),
        "--rate",
        "max",
        "--no-loops",
        "--exit-when-done",
        "--summary",
        &summary.display().to_string(),
        "--listen",
        &endpoint,
    ]
    .map(String::from);
    let mut edge = Process::start("edge", &binary("emr-edge"), &run, dir.path());
    publish(&endpoint, "publisher-run.log");
    let ran = wait_summary(&summary, Duration::from_secs(120), &mut [&mut edge]);
    assert_eq!(ran.frames, frames as u64, "scans the robot read from the topic");
    assert!(ran.keyframes >= 2, "{} keyframes from {frames} scans", ran.keyframes);
    println!("emr-edge run on ros2:/points: {} scans, {} keyframes", ran.frames, ran.keyframes);

    // Without --max-frames the topic has no end: Ctrl-C ends the run, and what was read is
    // written (as many poses as scans read, the files' poses).
    let endpoint = bus::endpoint(bus::free_port().unwrap());
    let args: Vec<String> = ["odometry", "ros2:/points", "--no-loops", "--listen", &endpoint, "--out"]
        .map(String::from)
        .into_iter()
        .chain([out("interrupted").display().to_string()])
        .collect();
    let mut interrupted = Process::start("interrupted", &binary("emr-edge"), &args, dir.path());
    publish(&endpoint, "publisher-interrupted.log");
    std::thread::sleep(Duration::from_secs(2));
    let _ = Command::new("kill").arg("-INT").arg(interrupted.id().to_string()).status();
    let ended = interrupted.wait(Duration::from_secs(60));
    assert!(
        ended.is_some_and(|s| s.success()),
        "odometry on ros2:/points after Ctrl-C: {ended:?}\n{}",
        interrupted.tail()
    );
    let written = read("interrupted");
    let read_scans = written.lines().count();
    assert!((1..=frames).contains(&read_scans), "{read_scans} poses written after Ctrl-C");
    for (a, b) in poses(&written).iter().zip(poses(&from_files)) {
        assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-6), "poses after Ctrl-C differ from the files'");
    }
    println!("Ctrl-C after {frames} scans published: {read_scans} poses written, the files' poses");
}
