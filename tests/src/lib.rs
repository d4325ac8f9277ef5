//! Harness for the system tests: the real `emr-edge` and `emr-station` binaries as processes on
//! 127.0.0.1, an observer session, and the simulator's ground truth to judge the result.
//!
//! The binaries are the ones `cargo test --workspace` builds next to the test executables
//! (`target/<profile>/emr-edge`); run the whole workspace's tests, or `cargo build --bins` first.

pub mod hosts;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use nalgebra::Isometry3;
use prost::Message;
use proto::{Fleet, GlobalMap, MergeStatus, StationStatus};
use sim::{Scenario, SimConfig, Simulator};
use station::service::client::fetch_global_map;

/// Path of one of the workspace's binaries, built beside the running test executable.
pub fn binary(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test> -> target/<profile>/<name>
    let dir = exe.parent().and_then(Path::parent).expect("test executable in target/<profile>/deps");
    let path = dir.join(name);
    assert!(
        path.exists(),
        "{} is missing: run `cargo test --workspace` (or `cargo build --bins`) first",
        path.display()
    );
    path
}

/// The fleet's router, the real `zenohd` that `deploy/zenohd.sh` builds once and caches (`.ci/run`
/// runs it first); `EMR_ZENOHD` names another binary.
pub fn zenohd() -> PathBuf {
    let path = match std::env::var_os("EMR_ZENOHD") {
        Some(p) => PathBuf::from(p),
        None => {
            let out = Command::new("bash")
                .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/zenohd.sh"))
                .env("EMR_ZENOHD_NO_BUILD", "1")
                .output()
                .expect("run deploy/zenohd.sh");
            PathBuf::from(String::from_utf8_lossy(&out.stdout).trim())
        }
    };
    assert!(
        path.is_file(),
        "no zenohd at {:?}: run `bash deploy/zenohd.sh` once (it builds and caches it), or set EMR_ZENOHD",
        path
    );
    path
}

/// A child process killed when dropped, with its stderr kept in a file for the failure message.
pub struct Process {
    /// What it is, for messages.
    pub name: String,
    child: Child,
    log: PathBuf,
}

impl Process {
    /// Starts `binary args...`, its stderr into `log_dir/<name>.log` (appended: restarts share it).
    pub fn start(name: &str, binary: &Path, args: &[String], log_dir: &Path) -> Process {
        let log = log_dir.join(format!("{name}.log"));
        let file = std::fs::OpenOptions::new().create(true).append(true).open(&log).expect("log file");
        let child = Command::new(binary)
            .args(args)
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(file)
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", binary.display()));
        Process { name: name.to_owned(), child, log }
    }

    /// SIGKILL (`kill -9`): no chance to flush anything.
    pub fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// SIGTERM, then waits up to `timeout` for the exit status.
    pub fn terminate(&mut self, timeout: Duration) -> Option<std::process::ExitStatus> {
        let _ = Command::new("kill").arg("-TERM").arg(self.child.id().to_string()).status();
        self.wait(timeout)
    }

    /// Its process id (to send it a signal).
    pub fn id(&self) -> u32 {
        self.child.id()
    }

    /// Waits up to `timeout` for the exit status.
    pub fn wait(&mut self, timeout: Duration) -> Option<std::process::ExitStatus> {
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            if let Ok(Some(status)) = self.child.try_wait() {
                return Some(status);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        None
    }

    /// True while the process runs.
    pub fn running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// The last lines of its log, for assertion messages: without the frames of a backtrace, which
    /// would otherwise push the error or panic message itself out of view.
    pub fn tail(&self) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let lines: Vec<&str> = text.lines().filter(|l| !is_backtrace_frame(l)).collect();
        format!(
            "--- {} (last lines of {}, backtrace frames left out) ---\n{}",
            self.name,
            self.log.display(),
            lines[lines.len().saturating_sub(40)..].join("\n")
        )
    }
}

/// A line of a Rust backtrace: `  12: function` or `      at file:line:column`.
fn is_backtrace_frame(line: &str) -> bool {
    let line = line.trim_start();
    line.starts_with("at ")
        || line.split_once(": ").is_some_and(|(n, _)| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
}

impl Drop for Process {
    fn drop(&mut self) {
        self.kill9();
    }
}

/// The command line of a station on `port` (it listens; everyone connects to it).
pub fn station_args(fleet: &str, port: u16, data_dir: &Path) -> Vec<String> {
    vec![
        "run".into(),
        "--fleet".into(),
        fleet.into(),
        "--data-dir".into(),
        data_dir.display().to_string(),
        "--debounce-ms".into(),
        "1000".into(),
        "--listen".into(),
        bus::endpoint(port),
    ]
}

/// The command line of an edge replaying a simulated robot, connecting to the station's port.
pub fn edge_args(
    fleet: &str,
    scenario: &str,
    robot: u32,
    frames: usize,
    station_port: u16,
    summary: &Path,
) -> Vec<String> {
    vec![
        "run".into(),
        "--fleet".into(),
        fleet.into(),
        "--robot".into(),
        robot.to_string(),
        "--source".into(),
        format!("sim:{scenario}:{robot}"),
        "--max-frames".into(),
        frames.to_string(),
        "--rate".into(),
        "max".into(),
        "--summary".into(),
        summary.display().to_string(),
        "--connect".into(),
        bus::endpoint(station_port),
    ]
}

/// What `emr-edge run --summary` writes once its source is exhausted.
#[derive(Clone, Debug, PartialEq)]
pub struct EdgeSummary {
    /// The session it was (0 from an edge without sessions).
    pub session: u64,
    /// Scans read.
    pub frames: u64,
    /// Keyframes produced.
    pub keyframes: u64,
}

/// Waits until `path` holds an edge summary, or panics after `timeout` with the processes' logs.
pub fn wait_summary(path: &Path, timeout: Duration, procs: &mut [&mut Process]) -> EdgeSummary {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(s) = read_summary(path) {
            return s;
        }
        assert!(Instant::now() < deadline, "no edge summary at {} in {timeout:?}\n{}", path.display(), tails(procs));
        for p in procs.iter_mut() {
            assert!(p.running(), "{} stopped early\n{}", p.name, p.tail());
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn read_summary(path: &Path) -> Option<EdgeSummary> {
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()?;
    Some(EdgeSummary {
        session: v["session"].as_u64().unwrap_or(0),
        frames: v["frames"].as_u64()?,
        keyframes: v["keyframes"].as_u64()?,
    })
}

/// The logs of all processes, for a failure message.
pub fn tails(procs: &[&mut Process]) -> String {
    procs.iter().map(|p| p.tail()).collect::<Vec<_>>().join("\n")
}

/// An observer: a loopback peer connected to the station, to read what the station publishes.
pub struct Observer {
    /// Its runtime (the tests themselves are synchronous).
    pub runtime: tokio::runtime::Runtime,
    /// Its session.
    pub session: zenoh::Session,
    fleet: Fleet,
}

impl Observer {
    /// Connects to the station's port.
    pub fn connect(fleet: &str, station_port: u16) -> Observer {
        let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        let session =
            runtime.block_on(bus::Network::loopback_ports(&[], &[station_port]).open()).expect("observer session");
        Observer { runtime, session, fleet: Fleet::new(fleet).unwrap() }
    }

    /// The station's latest global map, from its queryable, if it answers within a second.
    pub fn latest_global_map(&self) -> Option<GlobalMap> {
        let fetched = self.runtime.block_on(fetch_global_map(&self.session, &self.fleet, Duration::from_secs(1)));
        fetched.ok().map(|(map, _)| map)
    }

    /// The next `StationStatus` the station publishes, if one comes within `timeout`.
    pub fn next_status(&self, timeout: Duration) -> Option<StationStatus> {
        self.runtime.block_on(async {
            let sub = self.session.declare_subscriber(proto::keyexpr::station_status(&self.fleet)).await.ok()?;
            let sample = tokio::time::timeout(timeout, sub.recv_async()).await.ok()?.ok()?;
            StationStatus::decode(sample.payload().to_bytes().as_ref()).ok()
        })
    }

    /// Reads the station's status until `done` holds for one; panics with the logs after `timeout`.
    pub fn wait_status(
        &self,
        timeout: Duration,
        procs: &mut [&mut Process],
        done: impl Fn(&StationStatus) -> bool,
    ) -> StationStatus {
        let deadline = Instant::now() + timeout;
        let mut last = None;
        loop {
            if let Some(status) = self.next_status(Duration::from_secs(5)) {
                if done(&status) {
                    return status;
                }
                last = Some(status.sessions);
            }
            assert!(
                Instant::now() < deadline,
                "no satisfying station status in {timeout:?}; last sessions seen: {last:?}\n{}",
                tails(procs)
            );
        }
    }

    /// Polls the station until `done` holds for its global map; panics with the logs after `timeout`.
    pub fn wait_global_map(
        &self,
        timeout: Duration,
        procs: &mut [&mut Process],
        done: impl Fn(&GlobalMap) -> bool,
    ) -> GlobalMap {
        let deadline = Instant::now() + timeout;
        let mut last = None;
        loop {
            if let Some(map) = self.latest_global_map() {
                if done(&map) {
                    return map;
                }
                last = Some(describe(&map));
            }
            assert!(
                Instant::now() < deadline,
                "no satisfying global map in {timeout:?}; last seen: {last:?}\n{}",
                tails(procs)
            );
            std::thread::sleep(Duration::from_millis(500));
        }
    }
}

/// One line about a global map, for messages.
pub fn describe(map: &GlobalMap) -> String {
    let robots: Vec<String> = map
        .robots
        .iter()
        .map(|r| format!("robot {} {:?} conf {:.3} kf {}", r.robot, r.status(), r.confidence, r.keyframes))
        .collect();
    format!("revision {} reference {} [{}]", map.revision, map.reference_robot, robots.join(", "))
}

/// True when every robot in `keyframes` (robot, count) is in the map with that many keyframes.
pub fn holds_all(map: &GlobalMap, keyframes: &[(u32, u64)]) -> bool {
    keyframes.iter().all(|(robot, n)| map.robots.iter().any(|r| r.robot == *robot && r.keyframes == *n))
}

/// [`holds_all`], and the station merged it at rest: the map a from-scratch merge of those
/// keyframes gives, what runs are compared by (a map published while robots streamed may place
/// them from slightly older maps).
pub fn settled_with_all(map: &GlobalMap, keyframes: &[(u32, u64)]) -> bool {
    map.settled && holds_all(map, keyframes)
}

/// True when the map holds each robot session of `keyframes` (robot, session, count) with that
/// many keyframes, and nothing else.
pub fn holds_sessions(map: &GlobalMap, keyframes: &[(u32, u64, u64)]) -> bool {
    map.robots.len() == keyframes.len()
        && keyframes.iter().all(|(robot, session, n)| {
            map.robots.iter().any(|r| r.robot == *robot && r.session == *session && r.keyframes == *n)
        })
}

/// True when every robot of the map is merged.
pub fn all_merged(map: &GlobalMap) -> bool {
    !map.robots.is_empty() && map.robots.iter().all(|r| r.status() == MergeStatus::Merged)
}

/// A robot's transform in the map.
pub fn placement(map: &GlobalMap, robot: u32) -> Isometry3<f64> {
    let r = map.robots.iter().find(|r| r.robot == robot).unwrap_or_else(|| panic!("robot {robot} not in the map"));
    Isometry3::try_from(r.transform.as_ref().expect("placement transform")).expect("valid transform")
}

/// One robot session's transform in the map.
pub fn session_placement(map: &GlobalMap, robot: u32, session: u64) -> Isometry3<f64> {
    let r = map
        .robots
        .iter()
        .find(|r| r.robot == robot && r.session == session)
        .unwrap_or_else(|| panic!("robot {robot} session {session} not in the map"));
    Isometry3::try_from(r.transform.as_ref().expect("placement transform")).expect("valid transform")
}

/// The sensor's world pose at the end of simulated `robot`'s first sweep in `scenario`: the origin
/// of that robot's odometry frame, which the simulator knows exactly.
pub fn first_sweep_pose(scenario: &str, robot: u32) -> Isometry3<f64> {
    sweep_pose(scenario, robot, 0)
}

/// The sensor's world pose at the end of simulated `robot`'s sweep `frame`: the origin of the
/// odometry frame of a session that started there (`emr-edge run --start-at FRAME`).
pub fn sweep_pose(scenario: &str, robot: u32, frame: usize) -> Isometry3<f64> {
    let scenario = Scenario::by_name(scenario).expect("scenario");
    Simulator::new(scenario, robot as usize - 1, SimConfig::default()).expect("simulator").ground_truth(frame)
}

/// The true poses of `robot`'s sweeps `start..end`, each in the frame of sweep `start` (the frame
/// its odometry starts in when it starts there).
pub fn true_trajectory(scenario: &str, robot: u32, start: usize, end: usize) -> Vec<Isometry3<f64>> {
    let scenario = Scenario::by_name(scenario).expect("scenario");
    let sim = Simulator::new(scenario, robot as usize - 1, SimConfig::default()).expect("simulator");
    let origin = sim.ground_truth(start).inverse();
    (start..end).map(|k| origin * sim.ground_truth(k)).collect()
}

/// The simulator's sweep period, seconds: scan `k` is stamped `k` periods.
pub fn sweep_period() -> f64 {
    SimConfig::default().sensor.period
}

/// The true placement of `robot`'s odometry frame in `reference`'s (both of `scenario`).
pub fn true_placement(scenario: &str, reference: u32, robot: u32) -> Isometry3<f64> {
    first_sweep_pose(scenario, reference).inverse() * first_sweep_pose(scenario, robot)
}

/// Translation (m) and rotation (deg) between two transforms.
pub fn difference(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let d = a.inverse() * b;
    (d.translation.vector.norm(), d.rotation.angle().to_degrees())
}

/// A fresh scratch directory, removed at the end of the test.
pub fn scratch() -> tempfile::TempDir {
    // EMR_KEEP_SCRATCH=1 keeps it, with the processes' logs, to look into a failure.
    let keep = std::env::var_os("EMR_KEEP_SCRATCH").is_some();
    tempfile::Builder::new().prefix("emr-system-").disable_cleanup(keep).tempdir().expect("scratch dir")
}

/// The share of `map`'s global-map points that have a point of `other`'s within `radius` (m).
/// Two stations that assembled the same keyframes along different histories (one killed and
/// restarted) voxelise on grids that differ by the placements' millimetres and the order the maps
/// came in: their point counts differ by a percent or two, while each map still covers the other.
pub fn covered_share(map: &GlobalMap, other: &GlobalMap, radius: f32) -> f64 {
    let decode = |m: &GlobalMap| {
        let data = m.cloud.as_ref().map(|c| c.data.as_ref()).unwrap_or(&[][..]);
        proto::codec::decode(data).expect("global map cloud decodes").points
    };
    let (points, others) = (decode(map), decode(other));
    let tree = cloud::kdtree::KdTree::from_points(&others);
    let covered = points.iter().filter(|p| tree.nearest_within(&[p.x, p.y, p.z], radius).is_some()).count();
    covered as f64 / points.len().max(1) as f64
}
