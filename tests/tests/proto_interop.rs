//! The .proto files compile unchanged with the reference protobuf compiler (protoc), and what Rust
//! writes, Python's official protobuf runtime reads back (and the other way round).
//!
//! Needs `protoc` (Debian: protobuf-compiler) and Python's `protobuf` package; `.ci/run` installs both.

use std::path::{Path, PathBuf};
use std::process::Command;

use nalgebra::{Isometry3, Vector3};
use prost::Message;
use proto::{GlobalMap, Keyframe, MergeEdge, MergeStatus, Pose, RobotPlacement, Timestamp};

fn proto_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../proto")
}

fn run(cmd: &mut Command, what: &str) -> String {
    let out = cmd.output().unwrap_or_else(|e| panic!("cannot start {what} ({e}): install it (see .ci/run)"));
    assert!(out.status.success(), "{what} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).expect("utf-8 output")
}

/// Compiles the .proto files with protoc into a fresh directory for Python.
fn protoc_python(dir: &Path) {
    run(
        Command::new("protoc")
            .arg("-I")
            .arg(proto_root())
            .arg(format!("--python_out={}", dir.display()))
            .arg("emr/v1/messages.proto"),
        "protoc",
    );
}

fn python(dir: &Path, script: &str) -> String {
    run(Command::new("python3").arg("-c").arg(script).current_dir(dir), "python3 with the protobuf package")
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("emr-interop-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn python_reads_a_global_map_written_by_rust() {
    let dir = scratch("globalmap");
    protoc_python(&dir);
    let t = Isometry3::new(Vector3::new(12.5, -3.25, 0.5), Vector3::new(0.0, 0.0, 1.2));
    let map = GlobalMap {
        fleet: "demo".into(),
        revision: 42,
        reference_robot: 1,
        robots: vec![
            RobotPlacement {
                robot: 1,
                transform: Some(Pose::identity()),
                confidence: 0.0,
                status: MergeStatus::Merged as i32,
                keyframes: 10,
                session: 0,
            },
            RobotPlacement {
                robot: 2,
                transform: Some(Pose::from(&t)),
                confidence: 0.875,
                status: MergeStatus::Merged as i32,
                keyframes: 12,
                session: 0,
            },
        ],
        edges: vec![MergeEdge {
            robot_a: 1,
            robot_b: 2,
            transform: Some(Pose::from(&t)),
            confidence: 0.875,
            inliers: 250,
            session_a: 0,
            session_b: 0,
        }],
        cloud: Some(proto::CompressedCloud { data: vec![7u8; 300].into(), points: 99 }),
        stamp: Some(Timestamp { sec: 1_800_000_000, nanosec: 5 }),
        settled: true,
        reference_session: 0,
    };
    std::fs::write(dir.join("map.bin"), map.encode_to_vec()).unwrap();
    let out = python(
        &dir,
        r#"
import json
from emr.v1 import messages_pb2 as m
g = m.GlobalMap(); g.ParseFromString(open("map.bin", "rb").read())
r = g.robots[1]
print(json.dumps({"fleet": g.fleet, "revision": g.revision, "robots": len(g.robots),
  "status": m.MergeStatus.Name(r.status), "tx": r.transform.tx, "qz": r.transform.qz, "qw": r.transform.qw,
  "conf": r.confidence, "inliers": g.edges[0].inliers, "cloud_len": len(g.cloud.data),
  "points": g.cloud.points, "sec": g.stamp.sec, "settled": g.settled}))
"#,
    );
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let q = t.rotation.quaternion();
    assert_eq!(v["fleet"], "demo");
    assert_eq!(v["revision"], 42);
    assert_eq!(v["robots"], 2);
    assert_eq!(v["status"], "MERGE_STATUS_MERGED");
    assert_eq!(v["tx"].as_f64().unwrap(), 12.5);
    assert_eq!(v["qz"].as_f64().unwrap(), q.k);
    assert_eq!(v["qw"].as_f64().unwrap(), q.w);
    assert_eq!(v["conf"].as_f64().unwrap(), 0.875);
    assert_eq!(v["inliers"], 250);
    assert_eq!(v["cloud_len"], 300);
    assert_eq!(v["points"], 99);
    assert_eq!(v["sec"], 1_800_000_000u64);
    assert_eq!(v["settled"], true);
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn rust_reads_a_keyframe_written_by_python() {
    let dir = scratch("keyframe");
    protoc_python(&dir);
    python(
        &dir,
        r#"
from emr.v1 import messages_pb2 as m
k = m.Keyframe(fleet="f1", robot=3, seq=17)
k.stamp.sec = 100; k.stamp.nanosec = 250000000
k.odom_pose.tx = 1.5; k.odom_pose.qw = 1.0
k.scan_context.rings = 2; k.scan_context.sectors = 2; k.scan_context.max_range = 80.0
k.scan_context.cells.extend([0.5, 1.0, 1.5, 2.0])
k.cloud.data = bytes(range(10)); k.cloud.points = 3
open("kf.bin", "wb").write(k.SerializeToString())
"#,
    );
    let k = Keyframe::decode(std::fs::read(dir.join("kf.bin")).unwrap().as_slice()).unwrap();
    assert_eq!((k.fleet.as_str(), k.robot, k.seq), ("f1", 3, 17));
    assert_eq!(k.stamp.unwrap().as_secs_f64(), 100.25);
    let pose = Isometry3::try_from(&k.odom_pose.unwrap()).unwrap();
    assert_eq!(pose.translation.vector, Vector3::new(1.5, 0.0, 0.0));
    assert_eq!(k.scan_context.unwrap().cells, vec![0.5, 1.0, 1.5, 2.0]);
    assert_eq!(&k.cloud.unwrap().data[..], &(0u8..10).collect::<Vec<_>>()[..]);
    std::fs::remove_dir_all(dir).ok();
}
