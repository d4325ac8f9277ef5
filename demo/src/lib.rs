//! `emr-demo`: the whole system in one process, with no set-up.
//!
//! Two edges ([`edge::node`]) replay the simulated two-robot warehouse and a station
//! ([`station::service`]) merges their maps, each on its own zenoh session, peers on loopback: the
//! station listens on a free 127.0.0.1 port and the edges connect to it. When both robots' scans
//! are done and the station has published a global map built from every keyframe, the demo stops
//! everything and writes its results, judged against the simulator's ground truth.
//!
//! This crate is where robot code and station code meet in one process; the `eval` crate runs it to
//! compare the paper's four systems.

mod figures;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use cloud::trajectory::{self, Ate, Trajectory};
use edge::node::state_dir::StateDir;
use edge::node::{self, NodeConfig, NodeSummary, Rate, SourceEnd};
use edge::odometry::Method;
use edge::source::SourceSpec;
use nalgebra::Isometry3;
use proto::{Fleet, GlobalMap, MergeStatus};
use serde_json::{Value, json};
use sim::SimConfig;
use station::joint::{self, JointConfig};
use station::merge::MergeConfig;
use station::merge::files::{self, FilesError};
use station::service::client::{global_map_cloud, placements_json};
use station::service::fleet_state::Member;
use station::service::joint_input::joint_input;
use station::service::merge_job::RobotSnapshot;
use station::service::{Station, StationConfig, StationError};
use tokio::sync::{mpsc, oneshot};
use tracing::{info, warn};

/// What the demo runs.
#[derive(Clone, Debug)]
pub struct DemoConfig {
    /// Simulated scenario (default `warehouse-large`: two robots, both halls).
    pub scenario: String,
    /// Robots of the scenario to run, 1-based (default 1 and 2).
    pub robots: Vec<u32>,
    /// Scans per robot (default: the whole scenario).
    pub frames: Option<usize>,
    /// Scan pacing (default as fast as the odometry goes).
    pub rate: Rate,
    /// Where the results go (default `out/demo`).
    pub out: PathBuf,
    /// Station settings (default: the outdoor merge preset, as `emr-station run`; 1 s debounce; in memory).
    pub station: StationConfig,
    /// The robots' odometry: F-LOAM (default) or A-LOAM ([`edge::odometry::aloam`]).
    pub method: Method,
    /// Robots close their own loops (default true: the paper's EMR systems; false: MR).
    pub loops: bool,
    /// Seed of the simulated sensors' range noise and dropouts (default 0).
    pub seed: u64,
    /// Stop one robot's edge mid-run and start a new session of it later (default none).
    pub restart: Option<Restart>,
}

/// A robot that restarts: its edge stops after scan `scan` (its first session, 0) and a new session
/// (1) starts [`RESTART_GAP`] scans later, in an odometry frame of its own, keeping its keyframes in
/// a state directory under the output as a robot does on disk.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Restart {
    /// The robot, 1-based.
    pub robot: u32,
    /// Scans its first session reads.
    pub scan: usize,
}

/// Scans a restarted robot moves on while its edge is down: it does not start again where it stopped.
pub const RESTART_GAP: usize = 50;

impl std::str::FromStr for Restart {
    type Err = String;

    /// `ROBOT@SCAN`, as `emr-demo run --restart 1@600` takes it.
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("{s:?}: expected ROBOT@SCAN, e.g. 1@600");
        let (robot, scan) = s.split_once('@').ok_or_else(bad)?;
        let robot: u32 = robot.trim().parse().map_err(|_| bad())?;
        let scan: usize = scan.trim().parse().map_err(|_| bad())?;
        if robot == 0 || scan == 0 {
            return Err(format!("{s:?}: the robot is 1-based and the first session reads at least one scan"));
        }
        Ok(Restart { robot, scan })
    }
}

impl DemoConfig {
    /// The defaults above.
    pub fn new() -> Self {
        let fleet = Fleet::new("demo").expect("valid fleet name");
        let station = StationConfig {
            merge: MergeConfig::outdoor(),
            debounce: Duration::from_secs(1),
            ..StationConfig::new(fleet)
        };
        DemoConfig {
            scenario: "warehouse-large".into(),
            robots: vec![1, 2],
            frames: None,
            rate: Rate::Max,
            out: PathBuf::from("out/demo"),
            station,
            method: Method::Floam,
            loops: true,
            seed: 0,
            restart: None,
        }
    }
}

impl Default for DemoConfig {
    fn default() -> Self {
        Self::new()
    }
}

/// Why the demo failed.
#[derive(Debug, thiserror::Error)]
pub enum DemoError {
    /// No free loopback port or a session would not open.
    #[error("network: {0}")]
    Network(String),
    /// The station failed.
    #[error(transparent)]
    Station(#[from] StationError),
    /// `restart` names a robot that is not run, or a scan past the run's end.
    #[error("--restart {robot}@{scan}: {reason}")]
    Restart {
        /// The robot named.
        robot: u32,
        /// The scan named.
        scan: usize,
        /// What is wrong.
        reason: String,
    },
    /// An edge failed.
    #[error("robot {robot}: {source}")]
    Edge {
        /// The robot.
        robot: u32,
        /// What went wrong.
        source: node::NodeError,
    },
    /// Interrupted before the global map was complete.
    #[error("interrupted before the global map held every keyframe")]
    Interrupted,
    /// The results could not be written.
    #[error("writing {path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
}

/// One robot's results.
#[derive(Clone, Debug)]
pub struct RobotResult {
    /// Robot id.
    pub robot: u32,
    /// Scans and keyframes the edge made.
    pub frames: usize,
    /// Keyframes.
    pub keyframes: u64,
    /// Loops the robot closed (in its pose graph at the end).
    pub loops: usize,
    /// Odometry ATE in the robot's own frame, after SE(3) alignment and as estimated.
    pub odometry_ate: (Ate, Ate),
    /// The same after the robot's loop closure (equal to the odometry's without loops).
    pub corrected_ate: (Ate, Ate),
    /// ATE of the trajectory placed in the global frame against the truth in that frame (merge
    /// and odometry errors together, no alignment), when the robot was merged.
    pub global_ate: Option<Ate>,
    /// The same with the station's joint pose graph ([`station::joint`]) in place of the rigid
    /// placement: each scan follows its keyframe's jointly optimised pose. `None` when the robot
    /// was not joined (not merged, or no inter-robot edge links it to the reference).
    pub joint_ate: Option<Ate>,
    /// Placement error against the truth: metres and degrees.
    pub placement_error: Option<(f64, f64)>,
    /// The placement error a perfect rigid merge would leave, metres and degrees: this robot's and
    /// the reference robot's maps each placed by its best rigid fit onto the truth
    /// ([`trajectory::map_fit`]). What it holds is the maps' own shape error (odometry), which no
    /// rigid placement removes; `placement_error` above it is the merge's.
    pub placement_floor: Option<(f64, f64)>,
    /// The robot's odometry frame in the global frame, estimated and true, when it was merged.
    pub frame: Option<GlobalFrame>,
    /// Published confidence and status.
    pub confidence: f64,
    /// Merged or not.
    pub merged: bool,
    /// Wall time of the odometry on each scan, milliseconds.
    pub odometry_ms: Vec<f64>,
    /// Each session of the robot (one unless it restarted), oldest first.
    pub sessions: Vec<SessionResult>,
}

/// One session of a robot: what an edge did between a start and a stop.
#[derive(Clone, Debug)]
pub struct SessionResult {
    /// The session (0 the first, 1 after a restart).
    pub session: u64,
    /// Scans it read.
    pub frames: usize,
    /// Keyframes it made.
    pub keyframes: u64,
    /// Keyframes of it in the global map.
    pub in_map: u64,
    /// Its map is placed in the global map.
    pub merged: bool,
    /// Its odometry frame's placement against the truth, metres and degrees, when merged.
    pub placement_error: Option<(f64, f64)>,
    /// The placement error a perfect rigid merge would leave (see [`RobotResult::placement_floor`]).
    pub placement_floor: Option<(f64, f64)>,
}

/// Where a merged robot's odometry frame lies in the global frame.
#[derive(Clone, Copy, Debug)]
pub struct GlobalFrame {
    /// As the station placed it.
    pub placed: Isometry3<f64>,
    /// As the simulator knows it.
    pub truth: Isometry3<f64>,
}

/// What the demo did.
#[derive(Clone, Debug)]
pub struct DemoReport {
    /// Per robot.
    pub robots: Vec<RobotResult>,
    /// The final global map.
    pub global_map: GlobalMap,
    /// Wall time of the whole run, seconds.
    pub wall_s: f64,
    /// Wall time of each merge, milliseconds.
    pub merge_ms: Vec<f64>,
    /// Keyframes the station dropped as conflicts (another keyframe of the same robot session
    /// and sequence number had come first): 0 unless something is wrong.
    pub conflicts: u64,
    /// Files written.
    pub written: Vec<PathBuf>,
}

/// One run of an edge: a robot and its session.
type RobotSession = (u32, u64);

/// Runs the demo until the global map holds every keyframe or `interrupt` resolves.
pub async fn run(config: DemoConfig, interrupt: impl Future<Output = ()>) -> Result<DemoReport, DemoError> {
    let started = Instant::now();
    check_restart(&config)?;
    let (port, station_session) = open_on_a_free_port().await?;
    let station = Station::start(station_session, config.station.clone()).await?;
    info!("station listening on {}", bus::endpoint(port));
    let (done_tx, mut done_rx) = mpsc::unbounded_channel();
    let mut edges = BTreeMap::new();
    for &robot in &config.robots {
        let plan = EdgePlan::first(&config, robot);
        edges.insert((robot, plan.session), start_edge(&config, &plan, port, done_tx.clone()).await?);
    }
    let mut summaries = BTreeMap::new();
    let mut interrupt = std::pin::pin!(interrupt);
    let complete = tokio::select! {
        sent = follow_sources(&config, port, &mut edges, &mut summaries, &mut done_rx, &done_tx) => {
            wait_station(&station, &sent?).await
        }
        () = &mut interrupt => false,
    };
    for (key, edge) in std::mem::take(&mut edges) {
        summaries.insert(key, stop_edge(edge).await?);
    }
    let station = station.stop().await?;
    let global_map = match (complete, station.global_map) {
        (true, Some(map)) => map,
        _ => return Err(DemoError::Interrupted),
    };
    let joint = joint_poses(&station.fleet, &global_map);
    let robots = judge(&summaries, &global_map, &joint);
    let firsts: BTreeMap<u32, NodeSummary> =
        summaries.into_iter().filter(|((_, session), _)| *session == 0).map(|((r, _), s)| (r, s)).collect();
    let timing =
        Timing { wall_s: started.elapsed().as_secs_f64(), merge_ms: station.merge_ms, conflicts: station.conflicts };
    let written = write_results(&config, &firsts, &global_map, &robots, &timing)?;
    let conflicts = timing.conflicts;
    Ok(DemoReport { robots, global_map, wall_s: timing.wall_s, merge_ms: timing.merge_ms, conflicts, written })
}

/// Refuses a restart of a robot that is not run, or one whose second session would read no scan.
fn check_restart(config: &DemoConfig) -> Result<(), DemoError> {
    let Some(Restart { robot, scan }) = config.restart else { return Ok(()) };
    let refuse = |reason: String| Err(DemoError::Restart { robot, scan, reason });
    if !config.robots.contains(&robot) {
        return refuse(format!("robot {robot} is not among those run ({:?})", config.robots));
    }
    let available = sim::Scenario::by_name(&config.scenario)
        .ok()
        .and_then(|s| sim::Simulator::new(s, robot as usize - 1, SimConfig::default()).ok())
        .map(|s| s.frames());
    let frames = match (config.frames, available) {
        (Some(f), Some(a)) => f.min(a),
        (Some(f), None) => f,
        (None, Some(a)) => a,
        // An unknown scenario: the edge says so when it opens its source.
        (None, None) => return Ok(()),
    };
    if scan + RESTART_GAP >= frames {
        return refuse(format!(
            "the second session would start at scan {}, past the run's {frames} scans",
            scan + RESTART_GAP
        ));
    }
    Ok(())
}

/// Waits until every edge's source has ended, restarting the robot [`DemoConfig::restart`] names
/// when its first session ends; returns what each session had sent.
async fn follow_sources(
    config: &DemoConfig,
    port: u16,
    edges: &mut BTreeMap<RobotSession, EdgeTask>,
    summaries: &mut BTreeMap<RobotSession, NodeSummary>,
    done: &mut mpsc::UnboundedReceiver<(RobotSession, SourceDone)>,
    done_tx: &mpsc::UnboundedSender<(RobotSession, SourceDone)>,
) -> Result<BTreeMap<RobotSession, SourceDone>, DemoError> {
    let runs = config.robots.len() + usize::from(config.restart.is_some());
    let mut sent = BTreeMap::new();
    while sent.len() < runs {
        let Some(((robot, session), d)) = done.recv().await else { break };
        info!(
            "robot {robot} session {session}: all scans done, {} keyframes, pose graph revision {}",
            d.keyframes, d.pose_revision
        );
        sent.insert((robot, session), d);
        if let Some(restart) = config.restart.filter(|r| r.robot == robot && session == 0) {
            let edge = edges.remove(&(robot, session)).expect("a running edge ended its source");
            summaries.insert((robot, session), stop_edge(edge).await?);
            let plan = EdgePlan::restarted(config, restart);
            info!(
                "robot {robot}: stopped after scan {}, session {} starts at scan {}",
                restart.scan, plan.session, plan.start_at
            );
            edges.insert((robot, plan.session), start_edge(config, &plan, port, done_tx.clone()).await?);
        }
    }
    Ok(sent)
}

/// Where the time went.
struct Timing {
    wall_s: f64,
    merge_ms: Vec<f64>,
    /// The station's conflicting keyframes.
    conflicts: u64,
}

/// A running edge.
struct EdgeTask {
    robot: u32,
    stop: oneshot::Sender<()>,
    task: tokio::task::JoinHandle<Result<NodeSummary, node::NodeError>>,
}

/// Stops an edge and returns what it did.
async fn stop_edge(edge: EdgeTask) -> Result<NodeSummary, DemoError> {
    let _ = edge.stop.send(());
    let summary = edge.task.await.map_err(|e| DemoError::Network(e.to_string()))?;
    summary.map_err(|source| DemoError::Edge { robot: edge.robot, source })
}

async fn open(network: &bus::Network) -> Result<zenoh::Session, DemoError> {
    network.open().await.map_err(|e| DemoError::Network(e.to_string()))
}

/// Times the station's session is tried on another port; see [`open_on_a_free_port`].
const PORT_TRIES: usize = 5;

/// The station's session, listening on a loopback port that was free when asked. Another process
/// may take the port before the session binds it (an outgoing connection's ephemeral port, as
/// tests running beside the demo make): then another port is tried.
async fn open_on_a_free_port() -> Result<(u16, zenoh::Session), DemoError> {
    let mut failed = None;
    for _ in 0..PORT_TRIES {
        let port = bus::free_port().map_err(|e| DemoError::Network(e.to_string()))?;
        match open(&bus::Network::loopback_ports(&[port], &[])).await {
            Ok(session) => return Ok((port, session)),
            Err(e) => {
                warn!("station: port {port} could not be listened on ({e}); trying another");
                failed = Some(e);
            }
        }
    }
    Err(failed.unwrap_or_else(|| DemoError::Network("no port tried".into())))
}

/// What one run of an edge reads, and as which session.
struct EdgePlan {
    robot: u32,
    session: u64,
    start_at: usize,
    max_frames: Option<usize>,
    /// Where a robot that restarts keeps its keyframes.
    state: Option<PathBuf>,
}

impl EdgePlan {
    /// A robot's first session: its run from the start, up to the restart if it has one.
    fn first(config: &DemoConfig, robot: u32) -> Self {
        let restart = config.restart.filter(|r| r.robot == robot);
        EdgePlan {
            robot,
            session: 0,
            start_at: 0,
            max_frames: restart.map(|r| r.scan).or(config.frames),
            state: restart.map(|_| state_dir(config, robot)),
        }
    }

    /// The session after a restart: [`RESTART_GAP`] scans after the first stopped, to the run's end.
    fn restarted(config: &DemoConfig, restart: Restart) -> Self {
        let start_at = restart.scan + RESTART_GAP;
        EdgePlan {
            robot: restart.robot,
            session: 1,
            start_at,
            max_frames: config.frames.map(|f| f.saturating_sub(start_at)),
            state: Some(state_dir(config, restart.robot)),
        }
    }
}

/// A restarting robot's state directory, under the demo's output.
fn state_dir(config: &DemoConfig, robot: u32) -> PathBuf {
    config.out.join("state").join(format!("robot{robot}"))
}

/// Starts one robot's edge on its own session, connected to the station.
async fn start_edge(
    config: &DemoConfig,
    plan: &EdgePlan,
    port: u16,
    done: mpsc::UnboundedSender<(RobotSession, SourceDone)>,
) -> Result<EdgeTask, DemoError> {
    let (robot, session) = (plan.robot, plan.session);
    let network = open(&bus::Network::loopback_ports(&[], &[port])).await?;
    let source = SourceSpec::Sim { scenario: config.scenario.clone(), robot };
    let state = plan.state.as_deref().and_then(|dir| StateDir::open(dir, robot));
    let mut node_config = NodeConfig {
        session,
        start_at: plan.start_at,
        max_frames: plan.max_frames,
        state: state.map(|s| Arc::new(std::sync::Mutex::new(s))),
        rate: config.rate,
        on_source_end: Some(SourceEnd(Arc::new(move |s: &NodeSummary| {
            let d = SourceDone { keyframes: s.keyframes, pose_revision: s.posegraph_revision };
            let _ = done.send(((robot, session), d));
        }))),
        loops: config.loops,
        sim: SimConfig { seed: config.seed, ..SimConfig::default() },
        ..NodeConfig::new(config.station.fleet.clone(), robot, source)
    };
    node_config.odometry.method = config.method;
    let (stop, stopped) = oneshot::channel();
    let task = tokio::spawn(async move {
        let summary = node::run(&network, node_config, async {
            let _ = stopped.await;
        })
        .await;
        let _ = network.close().await;
        summary
    });
    Ok(EdgeTask { robot, stop, task })
}

/// What a robot had sent when its source ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct SourceDone {
    keyframes: u64,
    /// Its newest pose-graph revision (0: it closed no loop).
    pose_revision: u64,
}

/// Waits until the station holds every keyframe and every session's newest pose graph, and has
/// published a map built from them all.
async fn wait_station(station: &Station, sent: &BTreeMap<RobotSession, SourceDone>) -> bool {
    let mut progress = station.progress();
    loop {
        let ready = {
            let p = progress.borrow_and_update();
            p.up_to_date()
                && sent.iter().all(|(&(robot, session), d)| {
                    let member = Member::new(robot, session);
                    p.sessions.get(&member).is_some_and(|&k| k as u64 == d.keyframes)
                        && (d.pose_revision == 0
                            || p.session_pose_revisions.get(&member).is_some_and(|&v| v >= d.pose_revision))
                })
        };
        if ready {
            return true;
        }
        if progress.changed().await.is_err() {
            return false;
        }
    }
}

/// Scores each robot (its first session) and each of its sessions against the simulator's truth.
fn judge(summaries: &BTreeMap<RobotSession, NodeSummary>, map: &GlobalMap, joint: &JointPoses) -> Vec<RobotResult> {
    let reference = summaries.get(&(map.reference_robot, map.reference_session));
    let reference_start = reference.and_then(|s| s.ground_truth.first().copied().flatten());
    let reference_fit = reference.and_then(map_fit);
    // Where a session's odometry frame is, as placed and as the truth has it, when merged.
    let frame_of = |(robot, session): RobotSession, s: &NodeSummary| {
        let placement = map.robots.iter().find(|p| p.robot == robot && p.session == session);
        let merged = placement.is_some_and(|p| p.status() == MergeStatus::Merged);
        let placed = placement.and_then(|p| p.transform.as_ref()).and_then(|t| Isometry3::try_from(t).ok());
        let frame = match (merged, placed, reference_start, s.ground_truth.first()) {
            (true, Some(placed), Some(g_ref), Some(Some(g0))) => {
                Some(GlobalFrame { placed, truth: g_ref.inverse() * g0 })
            }
            _ => None,
        };
        (placement, merged, frame)
    };
    let floor = |frame: Option<GlobalFrame>, s: &NodeSummary| {
        frame.zip(reference_fit).zip(map_fit(s)).map(|((f, reference), own)| {
            metres_and_degrees(&(rigid_floor(&f.truth, &reference, &own).inverse() * f.truth))
        })
    };
    summaries
        .iter()
        .filter(|((_, session), _)| *session == 0)
        .map(|(&(robot, session), s)| {
            let (placement, merged, frame) = frame_of((robot, session), s);
            let truth = truth_in_own_frame(s);
            let odometry_ate = (ate(&truth, &s.poses, true), ate(&truth, &s.poses, false));
            let corrected = s.corrected_poses();
            let corrected_ate = (ate(&truth, &corrected, true), ate(&truth, &corrected, false));
            // The station places the keyframes at their optimised poses: the trajectory it places
            // is the corrected one.
            let global_ate = frame.map(|f| ate(&moved(&truth, &f.truth), &moved(&corrected, &f.placed), false));
            let joint_ate = frame.zip(joint.get(&(robot, session))).and_then(|(f, keyframes)| {
                let placed = joint_trajectory(s, &corrected, keyframes)?;
                Some(ate(&moved(&truth, &f.truth), &placed, false))
            });
            let placement_error = frame.map(|f| metres_and_degrees(&(f.placed.inverse() * f.truth)));
            let placement_floor = floor(frame, s);
            let sessions = summaries
                .range((robot, 0)..=(robot, u64::MAX))
                .map(|(&key, s)| {
                    let (placement, merged, frame) = frame_of(key, s);
                    SessionResult {
                        session: key.1,
                        frames: s.frames,
                        keyframes: s.keyframes,
                        in_map: placement.map_or(0, |p| p.keyframes),
                        merged,
                        placement_error: frame.map(|f| metres_and_degrees(&(f.placed.inverse() * f.truth))),
                        placement_floor: floor(frame, s),
                    }
                })
                .collect();
            RobotResult {
                robot,
                frames: s.frames,
                keyframes: s.keyframes,
                loops: s.loops,
                odometry_ate,
                corrected_ate,
                global_ate,
                joint_ate,
                placement_error,
                placement_floor,
                frame,
                confidence: placement.map_or(0.0, |p| p.confidence),
                merged,
                odometry_ms: s.odometry_ms.clone(),
                sessions,
            }
        })
        .collect()
}

/// Per joined robot session, per keyframe (by sequence number): the pose the station held it at
/// (its session's frame) and its jointly optimised pose (global frame).
type JointPoses = BTreeMap<RobotSession, BTreeMap<u64, (Isometry3<f64>, Isometry3<f64>)>>;

/// Runs the station's joint pose graph on what it held at the end (empty when it cannot run).
fn joint_poses(fleet: &[RobotSnapshot], map: &GlobalMap) -> JointPoses {
    let started = Instant::now();
    let Some(input) = joint_input(fleet, map) else { return JointPoses::new() };
    let solution = match joint::solve(&input.paths, input.reference, &JointConfig::default()) {
        Ok(s) => s,
        Err(e) => {
            tracing::warn!("joint pose graph: {e}");
            return JointPoses::new();
        }
    };
    info!(
        "joint pose graph: {} inter-robot edges registered, {} consistent, {} of {} robots joined, {:.1} s",
        solution.registered,
        solution.constraints.len(),
        solution.joined.iter().filter(|&&j| j).count(),
        input.robots.len(),
        started.elapsed().as_secs_f64()
    );
    let mut out = JointPoses::new();
    for (r, (&robot, &session)) in
        input.robots.iter().zip(&input.sessions).enumerate().filter(|(r, _)| solution.joined[*r])
    {
        let held = input.seqs[r].iter().zip(&input.paths[r].poses).zip(&solution.poses[r]);
        out.insert((robot, session), held.map(|((&seq, held), joint)| (seq, (*held, *joint))).collect());
    }
    out
}

/// Each scan at its keyframe's joint pose and the motion since that keyframe (global frame);
/// `None` when a scan's keyframe is not among those the station held.
fn joint_trajectory(
    s: &NodeSummary,
    corrected: &[Isometry3<f64>],
    keyframes: &BTreeMap<u64, (Isometry3<f64>, Isometry3<f64>)>,
) -> Option<Vec<Isometry3<f64>>> {
    corrected
        .iter()
        .zip(&s.keyframe_of_scan)
        .map(|(pose, &k)| keyframes.get(&(k as u64)).map(|(held, joint)| joint * (held.inverse() * pose)))
        .collect()
}

/// Translation (m) and rotation (deg) of a pose error.
fn metres_and_degrees(d: &Isometry3<f64>) -> (f64, f64) {
    (d.translation.vector.norm(), d.rotation.angle().to_degrees())
}

/// The robot's best rigid fit of its loop-closed trajectory onto the truth in its own frame.
fn map_fit(s: &NodeSummary) -> Option<Isometry3<f64>> {
    trajectory::map_fit(&truth_in_own_frame(s), &s.corrected_poses()).ok()
}

/// The placement of a robot's odometry frame in the reference robot's that a perfect rigid merge
/// would find: the one that puts the robot's map where the reference robot's map has its
/// surfaces, each map being off the truth by its best rigid fit (`own`, `reference`, estimated to
/// true). With `truth` the true placement, true points of the robot are `truth * own * p` in the
/// reference's true frame, `reference⁻¹ * truth * own * p` in its estimated one.
fn rigid_floor(truth: &Isometry3<f64>, reference: &Isometry3<f64>, own: &Isometry3<f64>) -> Isometry3<f64> {
    reference.inverse() * truth * own
}

/// Poses moved into another frame.
fn moved(poses: &[Isometry3<f64>], frame: &Isometry3<f64>) -> Vec<Isometry3<f64>> {
    poses.iter().map(|p| frame * p).collect()
}

/// Ground truth relative to the first pose: the robot's odometry frame.
fn truth_in_own_frame(s: &NodeSummary) -> Vec<Isometry3<f64>> {
    let first = s.ground_truth.first().copied().flatten().unwrap_or_else(Isometry3::identity);
    s.ground_truth.iter().map(|g| first.inverse() * g.unwrap_or(first)).collect()
}

fn ate(truth: &[Isometry3<f64>], est: &[Isometry3<f64>], align: bool) -> Ate {
    trajectory::ate(truth, est, align).unwrap_or(Ate { rmse: f64::NAN, mean: f64::NAN, max: f64::NAN, pairs: 0 })
}

/// Writes `out/`: global_map.ply, placements.json, per robot the estimated and true trajectories
/// (TUM, in the global frame when merged, else the robot's own), summary.json, and the figures
/// top_down.png and error_over_distance.png.
fn write_results(
    config: &DemoConfig,
    summaries: &BTreeMap<u32, NodeSummary>,
    map: &GlobalMap,
    robots: &[RobotResult],
    timing: &Timing,
) -> Result<Vec<PathBuf>, DemoError> {
    let out = &config.out;
    std::fs::create_dir_all(out).map_err(|e| write_error(out, e))?;
    let mut written = Vec::new();
    let cloud = global_map_cloud(map).map_err(|e| write_error(out, e))?;
    let ply = out.join("global_map.ply");
    files::write_by_extension(&ply, &cloud).map_err(|e: FilesError| write_error(&ply, e))?;
    written.push(ply);
    for r in robots {
        let (robot, s) = (r.robot, &summaries[&r.robot]);
        let frame = r.frame.unwrap_or(GlobalFrame { placed: Isometry3::identity(), truth: Isometry3::identity() });
        let stamps = Some(s.stamps.clone());
        let est = Trajectory { poses: moved(&s.corrected_poses(), &frame.placed), stamps: stamps.clone() };
        let gt = Trajectory { poses: moved(&truth_in_own_frame(s), &frame.truth), stamps };
        for (name, t) in [("estimated", est), ("ground_truth", gt)] {
            let path = out.join(format!("robot{robot}_{name}_tum.txt"));
            std::fs::write(&path, t.to_tum()).map_err(|e| write_error(&path, e))?;
            written.push(path);
        }
    }
    for figure in figures::figures(&config.scenario, summaries, &cloud, robots).map_err(|e| write_error(out, e))? {
        let path = out.join(figure.file);
        std::fs::write(&path, figure.png).map_err(|e| write_error(&path, e))?;
        written.push(path);
    }
    let path = out.join("placements.json");
    write_json(&path, &placements_json(map))?;
    written.push(path);
    let path = out.join("summary.json");
    write_json(&path, &summary_json(config, map, robots, timing))?;
    written.push(path);
    Ok(written)
}

fn summary_json(config: &DemoConfig, map: &GlobalMap, robots: &[RobotResult], timing: &Timing) -> Value {
    let ate_json = |a: &Ate| json!({"rmse_m": a.rmse, "mean_m": a.mean, "max_m": a.max});
    let error_json = |e: Option<(f64, f64)>| e.map(|(m, d)| json!({"m": m, "deg": d}));
    let robots: Vec<Value> = robots
        .iter()
        .map(|r| {
            json!({
                "robot": r.robot,
                "scans": r.frames,
                "keyframes": r.keyframes,
                "merged": r.merged,
                "confidence": r.confidence,
                "placement_error": error_json(r.placement_error),
                "placement_floor": error_json(r.placement_floor),
                "loops": r.loops,
                "odometry_ate": {"aligned": ate_json(&r.odometry_ate.0), "unaligned": ate_json(&r.odometry_ate.1)},
                "loop_closed_ate": {"aligned": ate_json(&r.corrected_ate.0), "unaligned": ate_json(&r.corrected_ate.1)},
                "global_ate_unaligned": r.global_ate.as_ref().map(ate_json),
                "joint_ate_unaligned": r.joint_ate.as_ref().map(ate_json),
                "sessions": r.sessions.iter().map(|s| json!({
                    "session": s.session,
                    "scans": s.frames,
                    "keyframes": s.keyframes,
                    "keyframes_in_map": s.in_map,
                    "merged": s.merged,
                    "placement_error": error_json(s.placement_error),
                    "placement_floor": error_json(s.placement_floor),
                })).collect::<Vec<_>>(),
            })
        })
        .collect();
    json!({
        "scenario": config.scenario,
        "seed": config.seed,
        "fleet": config.station.fleet.as_str(),
        "revision": map.revision,
        "reference_robot": map.reference_robot,
        "reference_session": map.reference_session,
        "global_map_points": map.cloud.as_ref().map_or(0, |c| c.points),
        "robots": robots,
        "station": {"conflicts": timing.conflicts},
        "timing": {"wall_s": timing.wall_s, "merges": timing.merge_ms.len(), "merge_ms": timing.merge_ms},
    })
}

fn write_json(path: &Path, value: &Value) -> Result<(), DemoError> {
    let text = serde_json::to_string_pretty(value).expect("JSON values serialise");
    std::fs::write(path, text).map_err(|e| write_error(path, e))
}

fn write_error(path: &Path, e: impl std::fmt::Display) -> DemoError {
    DemoError::Write { path: path.to_owned(), message: e.to_string() }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    /// A robot's true path in its own frame: a turning run 40 m long.
    fn path(turn: f64) -> Vec<Isometry3<f64>> {
        let mut pose = Isometry3::identity();
        (0..80)
            .map(|_| {
                let now = pose;
                pose *= Isometry3::new(Vector3::new(0.5, 0.0, 0.0), Vector3::new(0.0, 0.0, turn));
                now
            })
            .collect()
    }

    #[test]
    fn the_rigid_floor_is_what_the_maps_own_errors_leave_of_the_true_placement() {
        // Each robot's map is off the truth by a rigid error of its own (a tilt and a shift about
        // its start), the second robot starts 36 m away and turned a quarter.
        let truth = Isometry3::new(Vector3::new(35.9, 0.4, 0.0), Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2));
        let reference_error =
            Isometry3::new(Vector3::new(0.01, 0.0, -0.02), Vector3::new(0.0, 0.2f64.to_radians(), 0.0));
        let own_error = Isometry3::new(Vector3::new(0.0, 0.02, 0.03), Vector3::new(0.3f64.to_radians(), 0.0, 0.0));
        let (truth_1, truth_2) = (path(0.01), path(-0.02));
        let est_1: Vec<_> = truth_1.iter().map(|p| reference_error * p).collect();
        let est_2: Vec<_> = truth_2.iter().map(|p| own_error * p).collect();
        let reference = trajectory::map_fit(&truth_1, &est_1).unwrap();
        let own = trajectory::map_fit(&truth_2, &est_2).unwrap();
        let floor = rigid_floor(&truth, &reference, &own);
        // Where the maps' surfaces coincide: the second map's points, as estimated, land on the
        // first's as estimated.
        for (t2, e2) in truth_2.iter().zip(&est_2) {
            let surface = t2 * nalgebra::Point3::new(5.0, 2.0, 1.0);
            let estimated_in_reference = reference_error * truth * surface;
            let merged = floor * e2 * (t2.inverse() * surface);
            assert!((merged - estimated_in_reference).norm() < 1e-9);
        }
        let (m, deg) = metres_and_degrees(&(floor.inverse() * truth));
        let expected = own_error * truth.inverse() * reference_error.inverse() * truth;
        let (m_expected, deg_expected) = metres_and_degrees(&expected);
        assert!((m - m_expected).abs() < 1e-9 && (deg - deg_expected).abs() < 1e-9, "{m} {deg}");
        // The tilts (0.3 deg about the second robot's heading, 0.2 about the reference's
        // sideways axis: the same axis here) partly cancel, and 36 m from the reference start
        // what is left moves the placement by decimetres, far above either map's shift (2-4 cm).
        assert!((deg - 0.1).abs() < 1e-6 && m > 0.1, "{m} {deg}");
        // Maps without error leave nothing.
        let exact = rigid_floor(&truth, &Isometry3::identity(), &Isometry3::identity());
        assert!(metres_and_degrees(&(exact.inverse() * truth)).0 < 1e-12);
    }
}
