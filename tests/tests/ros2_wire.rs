//! Our ROS 2 payloads and type hashes against an independent implementation: rosbags (Python),
//! its CDR deserializer and serializer and its RIHS01 hashes of the ROS 2 releases' message
//! definitions. No code of ours runs on the Python side.
//!
//! Needs python3 with rosbags (`.ci/run` installs it).

use std::process::Command;

use nalgebra::{Isometry3, Vector3};
use proto::ros2::messages::{
    Covariance, Header, Odometry, Path, PoseStamped, PoseWithCovariance, StringMessage, TfMessage, Time,
    TransformStamped, Twist, TwistWithCovariance, to_cdr, xyzi_cloud,
};
use proto::ros2::{ODOMETRY, PATH, POINT_CLOUD2, RosType, STRING, TF_MESSAGE, TYPES};

/// Runs `script` with `args`; its stdout, or a panic with its stderr.
fn python(script: &str, args: &[String]) -> String {
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("cannot start python3 ({e}): install it and rosbags (see .ci/run)"));
    assert!(out.status.success(), "python3 with rosbags failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).expect("utf-8 output")
}

/// rosbags reads each payload (TYPE HEX ...), writes it again and prints, per payload, whether the
/// bytes came back identical and the message as JSON.
const ROUND_TRIP: &str = r#"
import json, sys
import numpy as np
from rosbags.typesys import Stores, get_typestore
ts = get_typestore(Stores.ROS2_JAZZY)

def plain(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    if hasattr(v, '__dataclass_fields__'):
        return {k: plain(getattr(v, k)) for k in v.__dataclass_fields__ if k != '__msgtype__'}
    return v

args = sys.argv[1:]
for typename, hexed in zip(args[::2], args[1::2]):
    raw = bytes.fromhex(hexed)
    msg = ts.deserialize_cdr(raw, typename)
    again = bytes(ts.serialize_cdr(msg, typename))
    print(json.dumps({'type': typename, 'identical': again == raw, 'message': plain(msg)}))
"#;

fn header(frame: &str, secs: f64) -> Header {
    Header { stamp: Time::from_secs_f64(secs), frame_id: frame.into() }
}

/// One message of each type, with values that tell fields apart.
fn payloads() -> Vec<(RosType, Vec<u8>)> {
    let pose = Isometry3::new(Vector3::new(1.5, -2.25, 0.125), Vector3::new(0.1, -0.2, 0.3));
    let points = (0..5).map(|i| {
        let f = i as f32;
        ([f * 1.5, -f, 0.25 * f, 10.0 + f], vec![i + 1, 1_764_633_600 + i])
    });
    let cloud = xyzi_cloud(header("map", 1_764_633_600.5), &["robot", "session"], points);
    let path = Path {
        header: header("map", 12.0),
        poses: (0..3)
            .map(|k| PoseStamped {
                header: header("map", 10.0 + k as f64),
                pose: (&(pose * Isometry3::translation(k as f64, 0.0, 0.0))).into(),
            })
            .collect(),
    };
    let tf = TfMessage {
        transforms: vec![TransformStamped {
            header: header("map", 3.0),
            child_frame_id: "robot2/odom".into(),
            transform: (&pose).into(),
        }],
    };
    let mut covariance = [0.0; 36];
    for (i, c) in covariance.iter_mut().enumerate() {
        *c = i as f64 * 0.5;
    }
    let odometry = Odometry {
        header: header("robot1/odom", 7.25),
        child_frame_id: "robot1/base".into(),
        pose: PoseWithCovariance { pose: (&pose).into(), covariance: Covariance(covariance) },
        twist: TwistWithCovariance {
            twist: Twist { linear: proto::ros2::messages::Vector3 { x: 1.0, y: 0.0, z: -0.5 }, ..Twist::default() },
            covariance: Covariance::default(),
        },
    };
    let status = StringMessage { data: "{\"revision\": 3}".into() };
    vec![
        (POINT_CLOUD2, to_cdr(&cloud).unwrap()),
        (PATH, to_cdr(&path).unwrap()),
        (TF_MESSAGE, to_cdr(&tf).unwrap()),
        (ODOMETRY, to_cdr(&odometry).unwrap()),
        (STRING, to_cdr(&status).unwrap()),
    ]
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[test]
fn rosbags_reads_our_payloads_and_writes_them_byte_for_byte() {
    let payloads = payloads();
    let args: Vec<String> = payloads.iter().flat_map(|(ty, bytes)| [ty.name.to_string(), hex(bytes)]).collect();
    let out = python(ROUND_TRIP, &args);
    let read: Vec<serde_json::Value> = out.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(read.len(), payloads.len());
    for r in &read {
        assert_eq!(r["identical"], true, "rosbags wrote {} back other than we did: {}", r["type"], r["message"]);
    }
    // The values, as rosbags reads them.
    let cloud = &read[0]["message"];
    assert_eq!(cloud["header"]["frame_id"], "map");
    assert_eq!(cloud["header"]["stamp"]["sec"], 1_764_633_600);
    assert_eq!(cloud["header"]["stamp"]["nanosec"], 500_000_000);
    assert_eq!((cloud["width"].as_u64(), cloud["point_step"].as_u64()), (Some(5), Some(24)));
    let names: Vec<&str> = cloud["fields"].as_array().unwrap().iter().map(|f| f["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["x", "y", "z", "intensity", "robot", "session"]);
    let data: Vec<u8> = cloud["data"].as_array().unwrap().iter().map(|b| b.as_u64().unwrap() as u8).collect();
    let point = |k: usize, at: usize| f32::from_le_bytes(data[k * 24 + at..k * 24 + at + 4].try_into().unwrap());
    assert_eq!((point(3, 0), point(3, 4), point(3, 8), point(3, 12)), (4.5, -3.0, 0.75, 13.0));
    assert_eq!(u32::from_le_bytes(data[3 * 24 + 16..3 * 24 + 20].try_into().unwrap()), 4);
    let path = &read[1]["message"];
    assert_eq!(path["poses"].as_array().unwrap().len(), 3);
    assert_eq!(path["poses"][0]["pose"]["position"]["x"], 1.5);
    let tf = &read[2]["message"];
    assert_eq!(tf["transforms"][0]["child_frame_id"], "robot2/odom");
    assert_eq!(tf["transforms"][0]["transform"]["translation"]["y"], -2.25);
    let odometry = &read[3]["message"];
    assert_eq!(odometry["child_frame_id"], "robot1/base");
    assert_eq!(odometry["pose"]["covariance"][35], 17.5);
    assert_eq!(odometry["twist"]["twist"]["linear"]["z"], -0.5);
    assert_eq!(read[4]["message"]["data"], "{\"revision\": 3}");
}

#[test]
fn our_type_hashes_are_those_of_the_ros2_releases() {
    let script = r#"
import sys
from rosbags.typesys import Stores, get_typestore
for store in (Stores.ROS2_HUMBLE, Stores.ROS2_JAZZY, Stores.ROS2_KILTED):
    ts = get_typestore(store)
    for name in sys.argv[1:]:
        print(store.name, name, ts.hash_rihs01(name))
"#;
    let names: Vec<String> = TYPES.iter().map(|t| t.name.to_string()).collect();
    let out = python(script, &names);
    assert_eq!(out.lines().count(), 3 * TYPES.len());
    for line in out.lines() {
        let [store, name, hash] = line.split(' ').collect::<Vec<_>>()[..] else { panic!("{line}") };
        let ours = TYPES.iter().find(|t| t.name == name).unwrap();
        assert_eq!(ours.hash, hash, "{name} in {store}");
        // The DDS name is the type's, as rmw_zenoh spells it.
        let (package, message) = name.split_once("/msg/").unwrap();
        assert_eq!(ours.dds, format!("{package}::msg::dds_::{message}_"));
    }
}
