//! The demo's MCAP recording opens in the reference readers (Python's `mcap` package, decoding with
//! the schemas the file carries; and the Rust `mcap` crate) with the live view's channels, and
//! holds what the run did: a map and its frames per published revision, every keyframe each robot
//! sent, each robot's trajectory, loops and status as the demo reports them.
//!
//! Runs the real `emr-demo` binary (built beside the tests: `cargo test --workspace`, or
//! `cargo build -p demo` first); needs `python3` with `mcap` and `protobuf` (`.ci/run` installs them).

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

use serde_json::Value;

/// Scans per robot of the small warehouse: enough for the station to merge both robots (5 s).
const FRAMES: usize = 100;

fn run_demo(out: &Path) -> String {
    let frames = FRAMES.to_string();
    let args = [
        "--scenario",
        "warehouse-small",
        "--frames",
        &frames,
        "--foxglove",
        "127.0.0.1:0",
        "--out",
        &out.display().to_string(),
    ];
    let run = Command::new(tests::binary("emr-demo")).args(args).output().expect("start emr-demo");
    let stdout = String::from_utf8_lossy(&run.stdout).into_owned();
    assert!(run.status.success(), "emr-demo failed:\n{stdout}\n{}", String::from_utf8_lossy(&run.stderr));
    stdout
}

/// Per topic what the Python reader found (see tests/scripts/read_mcap.py).
fn read_with_python(path: &Path) -> BTreeMap<String, Value> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/read_mcap.py");
    let run = Command::new("python3").arg(script).arg(path).output().expect("start python3 (see .ci/run)");
    assert!(run.status.success(), "the Python MCAP reader failed:\n{}", String::from_utf8_lossy(&run.stderr));
    serde_json::from_slice(&run.stdout).expect("JSON from the reader")
}

/// Messages per topic as the Rust `mcap` crate reads them.
fn count_with_rust(path: &Path) -> BTreeMap<String, u64> {
    let bytes = std::fs::read(path).unwrap();
    let mut counts = BTreeMap::new();
    for message in mcap::MessageStream::new(&bytes).expect("an MCAP file") {
        *counts.entry(message.expect("a readable message").channel.topic.clone()).or_insert(0) += 1;
    }
    counts
}

fn topic<'a>(topics: &'a BTreeMap<String, Value>, name: &str) -> &'a Value {
    topics.get(name).unwrap_or_else(|| panic!("no channel {name} in the recording: {:?}", topics.keys()))
}

/// The channel has the schema and encodings a Foxglove well-known type has.
fn assert_schema(topics: &BTreeMap<String, Value>, name: &str, schema: &str) {
    let t = topic(topics, name);
    assert_eq!(t["schema"], schema, "{name}");
    assert_eq!(t["schema_encoding"], "protobuf", "{name}");
    assert_eq!(t["message_encoding"], "protobuf", "{name}");
}

fn assert_json(topics: &BTreeMap<String, Value>, name: &str) {
    assert_eq!(topic(topics, name)["message_encoding"], "json", "{name}");
}

#[test]
fn the_demo_records_the_live_view_as_mcap() {
    let out = tests::scratch();
    let stdout = run_demo(out.path());
    assert!(stdout.contains("Foxglove: ws://127.0.0.1:"), "the server's address is printed:\n{stdout}");
    let path = out.path().join("run.mcap");
    let summary: Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("summary.json")).unwrap()).unwrap();
    let topics = read_with_python(&path);

    let merges = summary["timing"]["merges"].as_u64().unwrap();
    assert!(merges >= 1);
    assert_schema(&topics, "/map", "foxglove.PointCloud");
    assert_schema(&topics, "/tf", "foxglove.FrameTransforms");
    assert_json(&topics, "/station/status");
    assert_eq!(topic(&topics, "/map")["count"], merges, "a map message per published revision");
    assert_eq!(topic(&topics, "/tf")["count"], merges, "the frames with every revision");
    assert!(topic(&topics, "/station/status")["count"].as_u64().unwrap() >= 1);

    let map = &topic(&topics, "/map")["last"];
    assert_eq!(map["frame_id"], "map");
    assert_eq!(map["points"], summary["global_map_points"], "the last map is the final global map");
    assert_eq!(map["fields"], serde_json::json!(["robot", "x", "y", "z"]));
    let robots = summary["robots"].as_array().unwrap();
    let merged: Vec<&Value> = robots.iter().filter(|r| r["merged"] == true).collect();
    let labelled: Vec<String> = map["robots"].as_object().unwrap().keys().cloned().collect();
    let merged_ids: Vec<String> = merged.iter().map(|r| r["robot"].to_string()).collect();
    assert_eq!(labelled, merged_ids, "every merged robot's points, and only theirs, are in the map");
    let frames: Vec<Value> =
        merged.iter().map(|r| serde_json::json!(["map", format!("robot{}", r["robot"])])).collect();
    assert_eq!(map_frames(&topics), frames, "a frame per merged robot");

    for r in robots {
        let id = r["robot"].as_u64().unwrap();
        let name = |what: &str| format!("/robot{id}/{what}");
        assert_schema(&topics, &name("keyframe"), "foxglove.PointCloud");
        assert_schema(&topics, &name("trajectory"), "foxglove.PosesInFrame");
        assert_schema(&topics, &name("loops"), "foxglove.SceneUpdate");
        assert_json(&topics, &name("status"));
        let keyframes = r["keyframes"].as_u64().unwrap();
        assert_eq!(topic(&topics, &name("keyframe"))["count"], keyframes, "robot {id}: every keyframe it sent");
        assert_eq!(topic(&topics, &name("keyframe"))["last"]["frame_id"], format!("robot{id}"));
        let trajectory = &topic(&topics, &name("trajectory"))["last"];
        assert_eq!(trajectory["poses"], keyframes, "robot {id}: a pose per keyframe");
        let loops = &topic(&topics, &name("loops"))["last"]["entities"][0];
        assert_eq!(loops["points"], 2 * r["loops"].as_u64().unwrap(), "robot {id}: a line per loop");
        let status = &topic(&topics, &name("status"));
        assert_eq!(status["count"], merges, "robot {id}: a status per revision");
        assert_eq!(status["last"]["status"], if r["merged"] == true { "merged" } else { "unmerged" });
        assert_eq!(status["last"]["confidence"], r["confidence"]);
        assert_eq!(status["last"]["keyframes_in_map"], keyframes);
    }

    let rust: BTreeMap<String, u64> = count_with_rust(&path);
    let python: BTreeMap<String, u64> = topics.iter().map(|(k, v)| (k.clone(), v["count"].as_u64().unwrap())).collect();
    assert_eq!(rust, python, "both readers see the same messages");
}

fn map_frames(topics: &BTreeMap<String, Value>) -> Vec<Value> {
    topic(topics, "/tf")["last"]["frames"].as_array().unwrap().clone()
}
