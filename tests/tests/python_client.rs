//! The Python client (`clients/python`, package `emr_client`) against the Rust side: its codec
//! decoder bit for bit against the Rust decoder on clouds the Rust encoder wrote with every codec
//! option, its unit tests, and `python -m emr_client` on a running fleet (every key of the table
//! received and decoded; `save` writing the map `emr-station save` writes).
//!
//! Needs python3 with numpy, zstandard, protobuf and eclipse-zenoh (`pip install clients/python`
//! brings them), and protoc for the check of the generated message classes; `.ci/run` installs
//! them. The tests import the client from the working tree.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use cloud::PointCloud;
use nalgebra::Point3;
use proto::codec::{self, CodecConfig};
use tests::*;

/// Where the client's sources live.
fn client_source() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../clients/python")
}

/// A `python3` command that imports the client from the working tree (its layout is the installed
/// one: `pip install clients/python` copies the `emr_client` package as it is). Ahead of an
/// installed copy, so that the test always runs the code beside it.
fn python() -> Command {
    let mut cmd = Command::new("python3");
    cmd.env("PYTHONPATH", client_source()).env("PYTHONDONTWRITEBYTECODE", "1");
    cmd
}

/// Runs `cmd` to completion; its stdout, or a panic with its stderr.
fn run(cmd: &mut Command, what: &str) -> String {
    let out = cmd.output().unwrap_or_else(|e| panic!("cannot start {what}: {e}"));
    assert!(
        out.status.success(),
        "{what} failed ({}):\n{}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8 output")
}

/// SplitMix64: the seeded generator of every random cloud here.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// Which optional channels a cloud gets.
#[derive(Clone, Copy)]
struct Channels {
    intensity: bool,
    ring: bool,
    time: bool,
}

const ALL: Channels = Channels { intensity: true, ring: true, time: true };
const NONE: Channels = Channels { intensity: false, ring: false, time: false };

fn with_channels(mut cloud: PointCloud, channels: Channels, rng: &mut Rng) -> PointCloud {
    let n = cloud.len();
    cloud.intensity = channels.intensity.then(|| (0..n).map(|_| rng.uniform(0.0, 255.0) as f32).collect());
    cloud.ring = channels.ring.then(|| (0..n).map(|_| rng.below(128) as u16).collect());
    cloud.time = channels.time.then(|| (0..n).map(|_| rng.uniform(0.0, 0.1) as f32).collect());
    cloud
}

/// `n` points uniform in a cube of `half` metres around the origin.
fn uniform_cloud(n: usize, half: f64, rng: &mut Rng) -> PointCloud {
    PointCloud::from_points(
        (0..n).map(|_| Point3::new(0, 0, 0).map(|_: i32| rng.uniform(-half, half) as f32)).collect(),
    )
}

/// A spinning LiDAR's sweep in sensor order: `rings` beams, range varying along the azimuth
/// with centimetre noise; what the scan predictor is for. Ring and time are the sensor's.
fn ring_scan(rings: usize, columns: usize, rng: &mut Rng) -> PointCloud {
    let mut cloud = PointCloud::default();
    let (mut ring, mut time, mut intensity) = (Vec::new(), Vec::new(), Vec::new());
    for c in 0..columns {
        let azimuth = c as f64 / columns as f64 * std::f64::consts::TAU;
        for r in 0..rings {
            let elevation = (r as f64 / rings as f64 - 0.6) * 0.5;
            let range = 12.0 + 6.0 * (3.0 * azimuth).sin().abs() + rng.uniform(-0.02, 0.02);
            let (x, y) = (range * elevation.cos() * azimuth.cos(), range * elevation.cos() * azimuth.sin());
            cloud.points.push(Point3::new(x as f32, y as f32, (range * elevation.sin()) as f32));
            ring.push(r as u16);
            time.push((0.1 * c as f64 / columns as f64) as f32);
            intensity.push(rng.uniform(0.0, 1.0) as f32);
        }
    }
    cloud.intensity = Some(intensity);
    cloud.ring = Some(ring);
    cloud.time = Some(time);
    cloud
}

/// Points at the edge of what an i32 count of steps holds, where every sum wraps.
fn extreme_cloud(step: f64) -> PointCloud {
    let edge = [-2_147_483_000.0, 2_147_483_000.0, 0.0, -1.0, 1.0, 1_000_000.0, -1_073_741_824.0];
    let mut points = Vec::new();
    for &x in &edge {
        for &y in &edge {
            for &z in &edge {
                points.push(Point3::new(x, y, z).map(|v: f64| (v * step) as f32));
            }
        }
    }
    PointCloud::from_points(points)
}

fn kitti_scan(name: &str) -> PointCloud {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/kitti00/velodyne").join(name);
    cloud::formats::read_cloud(&path).unwrap_or_else(|e| panic!("KITTI scan expected at {}: {e}", path.display())).cloud
}

/// A voxelised map of about 130k points, as the station publishes: four KITTI scans, 6 cm voxels.
fn map_130k() -> PointCloud {
    let scans: Vec<Point3<f32>> =
        (0..4).flat_map(|i| kitti_scan(&format!("{i:06}.bin")).points).map(|p| p + nalgebra::Vector3::x()).collect();
    let map = cloud::voxel::downsample(&PointCloud::from_points(scans), 0.06).unwrap();
    let keep: Vec<usize> = (0..map.len().min(130_000)).collect();
    map.select(&keep)
}

/// Every option of `CodecConfig`, each value at least once.
fn configs() -> Vec<CodecConfig> {
    let mut out = Vec::new();
    for (i, step) in [1e-4, 1e-3, 0.01, 0.25].into_iter().enumerate() {
        for reorder in [false, true] {
            out.push(CodecConfig {
                step,
                intensity_step: [1e-3, 1.0, 0.5, 0.01][i],
                time_step: [1e-6, 1e-5, 1e-6, 1e-3][i],
                zstd_level: [1, 3, 9, 19][i],
                reorder,
            });
        }
    }
    out
}

/// One encoded cloud and what it was made from.
struct Case {
    name: String,
    original: Option<PointCloud>,
    config: CodecConfig,
    bytes: Vec<u8>,
}

fn encoded(name: String, cloud: PointCloud, config: CodecConfig) -> Case {
    let bytes = codec::encode(&cloud, &config).unwrap_or_else(|e| panic!("{name}: {e}"));
    Case { name, original: Some(cloud), config, bytes }
}

/// The clouds: random ones with every channel combination under every configuration, scans in
/// sensor order (scan predictor), KITTI, the 130k map, the edges of the range, empty and tiny.
fn cases() -> Vec<Case> {
    let mut rng = Rng(0x05ee_d0fc_0dec);
    let mut out = Vec::new();
    let channel_sets = [ALL, NONE, Channels { intensity: true, ..NONE }, Channels { ring: true, time: true, ..NONE }];
    for (c, config) in configs().into_iter().enumerate() {
        let channels = channel_sets[c % channel_sets.len()];
        let cloud = with_channels(uniform_cloud(3000, 100.0, &mut rng), channels, &mut rng);
        out.push(encoded(format!("uniform-{c}"), cloud, config.clone()));
        out.push(encoded(format!("ring-{c}"), ring_scan(16, 400, &mut rng), config.clone()));
        out.push(encoded(format!("extreme-{c}"), extreme_cloud(config.step), config.clone()));
        out.push(encoded(
            format!("tiny-{c}"),
            with_channels(uniform_cloud(c % 3, 5.0, &mut rng), ALL, &mut rng),
            config,
        ));
    }
    let sim = sim::Simulator::new(sim::Scenario::by_name("warehouse-large").unwrap(), 0, sim::SimConfig::default());
    out.push(encoded("sim-vlp16".into(), sim.unwrap().scan(3).cloud, CodecConfig::default()));
    out.push(encoded("kitti-scan".into(), kitti_scan("000000.bin"), CodecConfig::default()));
    let reorder = CodecConfig { reorder: true, ..CodecConfig::default() };
    out.push(encoded("map-130k".into(), map_130k(), reorder));
    out
}

/// Damaged copies of a few encoded clouds: truncated, bytes flipped (header, lengths, frames),
/// bytes appended, a huge point count. Rust and Python must agree on each: both refuse it, or
/// both decode the same values.
fn damaged(cases: &[Case]) -> Vec<Case> {
    let mut rng = Rng(0x0bad_b17e);
    let mut out = Vec::new();
    for source in cases.iter().filter(|c| c.name.starts_with("uniform-") || c.name.starts_with("ring-")).take(6) {
        let b = &source.bytes;
        let mut variants: Vec<(String, Vec<u8>)> = Vec::new();
        for cut in [0, 3, 39, 40, 44, b.len() / 2, b.len() - 1] {
            variants.push((format!("cut{cut}"), b[..cut].to_vec()));
        }
        for at in [0, 4, 5, 6, 7, 8, 15, 16, 23, 24, 31, 32, 39, 40, 41, 44, 45, 48] {
            let mut d = b.clone();
            d[at] ^= 1 << rng.below(8);
            variants.push((format!("flip{at}"), d));
        }
        for k in 0..8 {
            let mut d = b.clone();
            let at = 40 + rng.below((b.len() - 40) as u64) as usize;
            d[at] ^= 1 << rng.below(8);
            variants.push((format!("random{k}-flip{at}"), d));
        }
        let mut appended = b.clone();
        appended.extend_from_slice(&[0, 0, 0, 0]);
        variants.push(("appended".into(), appended));
        let mut huge = b.clone();
        huge[32..40].copy_from_slice(&u64::MAX.to_le_bytes());
        variants.push(("huge".into(), huge));
        for (what, bytes) in variants {
            let name = format!("{}-{what}", source.name);
            out.push(Case { name, original: None, config: source.config.clone(), bytes });
        }
    }
    out
}

/// The decoded values in the layout `emr_client.check` writes.
fn raw(cloud: &PointCloud) -> Vec<u8> {
    let mut out: Vec<u8> = cloud.xyz().as_flattened().iter().flat_map(|v| v.to_le_bytes()).collect();
    out.extend(cloud.intensity.iter().flatten().flat_map(|v| v.to_le_bytes()));
    out.extend(cloud.ring.iter().flatten().flat_map(|v| v.to_le_bytes()));
    out.extend(cloud.time.iter().flatten().flat_map(|v| v.to_le_bytes()));
    out
}

/// Half a step, plus the f32 rounding of the decoded value (as the codec's own tests bound it).
fn bound(x: f32, step: f64) -> f64 {
    step / 2.0 + (f64::from(x.abs()) + step) * 2f64.powi(-24)
}

/// Every value Python decoded lies within its step of the input.
fn assert_within_step(name: &str, original: &PointCloud, python: &PointCloud, config: &CodecConfig) {
    assert_eq!(original.len(), python.len(), "{name}: point count");
    for (i, (a, b)) in original.xyz().iter().zip(python.xyz()).enumerate() {
        for k in 0..3 {
            let error = (f64::from(a[k]) - f64::from(b[k])).abs();
            assert!(error <= bound(a[k], config.step), "{name}: point {i} axis {k}: {} -> {}", a[k], b[k]);
        }
    }
    let scalars = [
        (&original.intensity, &python.intensity, config.intensity_step),
        (&original.time, &python.time, config.time_step),
    ];
    for (a, b, step) in scalars {
        for (x, y) in a.iter().flatten().zip(b.iter().flatten()) {
            assert!((f64::from(*x) - f64::from(*y)).abs() <= bound(*x, step), "{name}: {x} -> {y}");
        }
    }
    assert_eq!(original.ring, python.ring, "{name}: rings");
}

/// `original` in the order of `decoded` (the encoder's Z-order when it reordered), matching each
/// decoded point to an input point with the same quantised coordinates.
fn in_decoded_order(original: &PointCloud, decoded: &PointCloud, step: f64) -> PointCloud {
    // As the encoder quantises: times the inverse step, ties to even.
    let key = |p: &[f32; 3]| p.map(|v| (f64::from(v) * (1.0 / step)).round_ties_even() as i64);
    let mut by_key: std::collections::HashMap<[i64; 3], Vec<usize>> = std::collections::HashMap::new();
    for (i, p) in original.xyz().iter().enumerate().rev() {
        by_key.entry(key(p)).or_default().push(i);
    }
    let order: Vec<usize> = decoded
        .xyz()
        .iter()
        .map(|p| {
            by_key.get_mut(&key(p)).and_then(Vec::pop).unwrap_or_else(|| panic!("decoded {p:?} is no input point"))
        })
        .collect();
    original.select(&order)
}

/// Python's output as a cloud with `like`'s channels.
fn from_raw(bytes: &[u8], like: &PointCloud) -> PointCloud {
    let n = like.len();
    let f32s = |at: usize, count: usize| -> Vec<f32> {
        bytes[at..at + 4 * count].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
    };
    let xyz = f32s(0, 3 * n);
    let mut cloud = PointCloud::from_points(xyz.chunks_exact(3).map(|p| Point3::new(p[0], p[1], p[2])).collect());
    let mut at = 12 * n;
    if like.intensity.is_some() {
        cloud.intensity = Some(f32s(at, n));
        at += 4 * n;
    }
    if like.ring.is_some() {
        cloud.ring = Some(bytes[at..at + 2 * n].chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect());
        at += 2 * n;
    }
    if like.time.is_some() {
        cloud.time = Some(f32s(at, n));
    }
    cloud
}

#[test]
fn python_decodes_what_rust_encodes_bit_for_bit() {
    let dir = scratch();
    let clean = cases();
    let broken = damaged(&clean);
    let predictors: std::collections::BTreeSet<u8> = clean.iter().map(|c| c.bytes[6]).collect();
    assert_eq!(predictors.into_iter().collect::<Vec<_>>(), vec![0, 1], "both predictors must be exercised");
    let data = dir.path().join("clouds");
    std::fs::create_dir_all(&data).unwrap();
    for case in clean.iter().chain(&broken) {
        std::fs::write(data.join(format!("{}.emp", case.name)), &case.bytes).unwrap();
    }
    let out = run(python().args(["-m", "emr_client.check", "--repeat", "3"]).arg(&data), "emr_client.check");
    let report: Vec<serde_json::Value> = out.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(report.len(), clean.len() + broken.len());

    let (mut refused, mut damaged_decoded) = (0, 0);
    for case in clean.iter().chain(&broken) {
        let python_out = std::fs::read(data.join(format!("{}.decoded", case.name)));
        let python_err = std::fs::read_to_string(data.join(format!("{}.error", case.name)));
        match codec::decode(&case.bytes) {
            Ok(rust) => {
                let python_out = python_out.unwrap_or_else(|_| {
                    panic!("{}: Rust decodes it, Python refused: {}", case.name, python_err.unwrap_or_default())
                });
                assert!(python_out == raw(&rust), "{}: Python's values differ from Rust's", case.name);
                if let Some(original) = &case.original {
                    let python = from_raw(&python_out, &rust);
                    let original = in_decoded_order(original, &python, case.config.step);
                    assert_within_step(&case.name, &original, &python, &case.config);
                }
                damaged_decoded += usize::from(case.original.is_none());
            }
            Err(e) => {
                assert!(python_out.is_err(), "{}: Rust refuses it ({e}), Python decoded it", case.name);
                assert!(python_err.is_ok_and(|m| !m.is_empty()), "{}: no error message from Python", case.name);
                refused += 1;
            }
        }
    }
    println!(
        "{} clouds and {damaged_decoded} damaged ones decoded bit for bit like Rust; {refused} damaged ones refused by both",
        clean.len()
    );
    for name in ["map-130k.emp", "kitti-scan.emp", "sim-vlp16.emp"] {
        let line = report.iter().find(|r| r["file"] == name).expect("reported");
        let ms = line["ms"].as_f64().unwrap();
        println!("python decodes {name}: {} points, {} predictor, {ms:.1} ms", line["points"], line["predictor"]);
        if name == "map-130k.emp" {
            assert!(ms < 1000.0, "decoding the 130k-point map took {ms:.0} ms");
        }
    }
}

#[test]
fn python_unit_tests_pass() {
    let dir = scratch();
    let tests = client_source().join("tests");
    let out = python()
        .args(["-m", "unittest", "discover", "-v", "-s"])
        .arg(&tests)
        .current_dir(dir.path())
        .output()
        .expect("python3");
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "Python unit tests failed:\n{log}");
    println!("{}", log.lines().find(|l| l.starts_with("Ran ")).unwrap_or_default());
}

const FLEET: &str = "pyclient";
const SCENARIO: &str = "warehouse-small";
/// Scans each robot replays: robot 1 closes loops (so that it publishes pose graphs) within 950,
/// robot 2 adds its map in 300.
const FRAMES: [usize; 2] = [950, 300];
const TIMEOUT: Duration = Duration::from_secs(600);

/// A child process killed when dropped, with stdout in a file.
struct Watcher {
    child: std::process::Child,
    stdout: PathBuf,
}

impl Drop for Watcher {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `python -m emr_client watch --json` connected to `endpoints`, its lines into `dir/watch.jsonl`.
fn start_watcher(dir: &Path, endpoints: &[String]) -> Watcher {
    let stdout = dir.join("watch.jsonl");
    let mut cmd = python();
    cmd.args(["-m", "emr_client", "watch", "--json", "--fleet", FLEET]);
    for e in endpoints {
        cmd.args(["--connect", e]);
    }
    let child = cmd
        .stdout(std::fs::File::create(&stdout).unwrap())
        .stderr(std::fs::File::create(dir.join("watch.log")).unwrap())
        .stdin(Stdio::null())
        .spawn()
        .expect("python3");
    Watcher { child, stdout }
}

/// An edge that also listens on `listen`: peers do not forward each other's samples, so a
/// subscriber sees a robot's topics only over a link of its own to the robot (or a router).
fn start_listening_edge(dir: &Path, robot: u32, station: u16, listen: u16) -> Process {
    let mut args = edge_args(
        FLEET,
        SCENARIO,
        robot,
        FRAMES[robot as usize - 1],
        station,
        &dir.join(format!("edge{robot}-summary.json")),
    );
    args.extend(["--listen".into(), bus::endpoint(listen)]);
    Process::start(&format!("edge{robot}"), &binary("emr-edge"), &args, dir)
}

#[test]
fn python_follows_a_fleet_and_saves_the_map_emr_station_saves() {
    let dir = scratch();
    let ports: Vec<u16> = (0..3).map(|_| bus::free_port().unwrap()).collect();
    let endpoints: Vec<String> = ports.iter().map(|&p| bus::endpoint(p)).collect();
    let station_args = station_args(FLEET, ports[0], &dir.path().join("station-data"));
    let mut station = Process::start("station", &binary("emr-station"), &station_args, dir.path());
    // Subscribed before the robots start (it keeps trying their endpoints until they listen).
    let mut watcher = start_watcher(dir.path(), &endpoints);
    std::thread::sleep(Duration::from_secs(3));
    let mut edges: Vec<Process> =
        (1..=2u32).map(|r| start_listening_edge(dir.path(), r, ports[0], ports[r as usize])).collect();
    let observer = Observer::connect(FLEET, ports[0]);
    let mut keyframes = Vec::new();
    for r in 1..=2u32 {
        let mut procs: Vec<&mut Process> = vec![&mut station];
        procs.extend(edges.iter_mut());
        let summary = dir.path().join(format!("edge{r}-summary.json"));
        keyframes.push((r, wait_summary(&summary, TIMEOUT, &mut procs).keyframes));
    }
    let mut procs: Vec<&mut Process> = vec![&mut station];
    procs.extend(edges.iter_mut());
    let map = observer.wait_global_map(TIMEOUT, &mut procs, |m| settled_with_all(m, &keyframes));
    println!("{}", describe(&map));

    let out = |name: &str| dir.path().join(name);
    let started = Instant::now();
    let save = ["save", "--connect", &endpoints[0], "--fleet", FLEET, "--out"];
    let said = run(
        python()
            .args(["-m", "emr_client"])
            .args(save)
            .arg(out("python.ply"))
            .arg("--transforms")
            .arg(out("python.json")),
        "python -m emr_client save",
    );
    println!("python save ({:.1} s with start-up): {}", started.elapsed().as_secs_f64(), said.trim());
    let rust_said = run(
        Command::new(binary("emr-station")).args(save).arg(out("rust.ply")).arg("--transforms").arg(out("rust.json")),
        "emr-station save",
    );
    assert_eq!(said.split(':').next(), rust_said.split(':').next(), "the two saves fetched different revisions");
    assert_same_map(&out("python.ply"), &out("rust.ply"), codec::CodecConfig::default().step);
    assert_same_placements(&out("python.json"), &out("rust.json"));

    assert_backfill_answers(&endpoints[1]);
    let _ = watcher.child.kill();
    let _ = watcher.child.wait();
    assert_watched_everything(&std::fs::read_to_string(&watcher.stdout).unwrap(), &keyframes);
}

/// Robot 1's keyframe queryable answers the Python client with keyframes 0, 1, 2, clouds decoded.
fn assert_backfill_answers(robot1: &str) {
    let script = format!(
        "from emr_client import Client\n\
         with Client({FLEET:?}, connect=[{robot1:?}]) as c:\n\
         \x20   print(*[f'{{m.message.seq}}:{{len(m.cloud)}}' for m in c.keyframes(1, from_seq=0, limit=3)])"
    );
    let answered = run(python().arg("-c").arg(script), "Client.keyframes");
    let got: Vec<&str> = answered.split_whitespace().collect();
    assert_eq!(got.len(), 3, "keyframes 0..3 of robot 1: {answered}");
    for (i, g) in got.iter().enumerate() {
        assert!(g.starts_with(&format!("{i}:")) && !g.ends_with(":0"), "keyframes 0..3 of robot 1: {answered}");
    }
}

/// The two PLY files hold the same points in the same order, each within a codec step.
fn assert_same_map(python: &Path, rust: &Path, step: f64) {
    let read = |p: &Path| cloud::formats::read_cloud(p).unwrap_or_else(|e| panic!("{}: {e}", p.display())).cloud;
    let (a, b) = (read(python), read(rust));
    assert_eq!(a.len(), b.len(), "point counts differ");
    assert!(a.len() > 1000, "a global map of {} points", a.len());
    let worst =
        a.xyz().iter().zip(b.xyz()).flat_map(|(p, q)| (0..3).map(move |k| (p[k] - q[k]).abs())).fold(0f32, f32::max);
    assert!(f64::from(worst) <= step, "points differ by up to {worst} m");
    let identical = records(python) == records(rust);
    println!("{} points, largest difference {worst} m, records byte-identical: {identical}", a.len());
}

/// The two placement files agree: the same fields, matrices to 1e-9.
fn assert_same_placements(python: &Path, rust: &Path) {
    let read = |p: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap() };
    let (a, b) = (read(python), read(rust));
    same_json(&a, &b, "placements");
    println!(
        "placements agree: {} robots, {} edges",
        a["robots"].as_array().unwrap().len(),
        a["edges"].as_array().unwrap().len()
    );
}

/// `a` and `b` hold the same keys and values, numbers within 1e-9.
fn same_json(a: &serde_json::Value, b: &serde_json::Value, at: &str) {
    use serde_json::Value;
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            assert!((x - y).abs() <= 1e-9, "{at}: {x} against {y}");
        }
        (Value::Array(x), Value::Array(y)) => {
            assert_eq!(x.len(), y.len(), "{at}: lengths");
            for (i, (x, y)) in x.iter().zip(y).enumerate() {
                same_json(x, y, &format!("{at}[{i}]"));
            }
        }
        (Value::Object(x), Value::Object(y)) => {
            assert_eq!(x.keys().collect::<Vec<_>>(), y.keys().collect::<Vec<_>>(), "{at}: keys");
            for (k, v) in x {
                same_json(v, &y[k], &format!("{at}.{k}"));
            }
        }
        _ => assert_eq!(a, b, "{at}"),
    }
}

/// A PLY file's bytes after its header.
fn records(path: &Path) -> Vec<u8> {
    let bytes = std::fs::read(path).unwrap();
    let end = bytes.windows(11).position(|w| w == b"end_header\n").expect("a PLY header") + 11;
    bytes[end..].to_vec()
}

/// The watcher's lines hold every kind of message the fleet publishes, decoded, and nothing malformed.
fn assert_watched_everything(lines: &str, keyframes: &[(u32, u64)]) {
    let seen: Vec<serde_json::Value> = lines.lines().map(|l| serde_json::from_str(l).expect("JSON line")).collect();
    assert!(seen.iter().all(|v| v.get("malformed").is_none()), "malformed samples: {lines}");
    let of = |kind: &'static str| seen.iter().filter(move |v| v["type"] == kind);
    for kind in ["keyframe", "posegraph", "globalmap", "status", "alive"] {
        assert!(of(kind).count() > 0, "the watcher saw no {kind}: {} lines", seen.len());
    }
    let total: u64 = keyframes.iter().map(|(_, n)| n).sum();
    let points_ok = of("keyframe").all(|v| v["points"].as_u64().is_some_and(|p| p > 0));
    assert!(points_ok, "a keyframe without decoded points");
    assert!(of("globalmap").any(|v| v["points"].as_u64().is_some_and(|p| p > 0)), "no global map with points");
    assert!(of("alive").any(|v| v["alive"] == true), "no robot seen alive");
    println!("watched {} samples: {} keyframes of {total}", seen.len(), of("keyframe").count());
}
