//! `emr-eval load`: a station under a simulated fleet's load.
//!
//! N robots publish one keyframe per scan at the sensor rate (10 Hz: ten times what a robot driving
//! 1.5 m/s with 1 m keyframe spacing sends, the worst case) to an in-process station, each robot on
//! its own zenoh session, peers on loopback. The keyframes are simulated scans at their true poses,
//! made before the clock starts so that only the station is measured. Robots beyond the scenario's
//! own replay its robots from later in their runs.
//!
//! An observer on a session of its own watches the station throughout: when each keyframe arrived
//! (the station's progress: a robot's count of keyframes held first reaching k) and when each
//! published global map was received (its placements count the keyframes it was built from), which
//! gives each keyframe's latency from arrival to the first published map holding it.

use std::collections::BTreeMap;
use std::fmt;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use crate::joint::{self, JointLoad};
use cloud::memory::{peak_rss_mb, rss_mb};
use cloud::scan_context::{ScanContext, ScanContextConfig};
use cloud::se3::{PoseError, pose_error};
use cloud::stats::Spread;
use edge::odometry::Keyframe;
use edge::wire::keyframe_message;
use nalgebra::Isometry3;
use prost::Message;
use proto::codec::CodecConfig;
use proto::{Fleet, GlobalMap, keyexpr};
use rayon::prelude::*;
use serde::Serialize;
use sim::{Scenario, SimConfig, Simulator};
use station::joint::JointConfig;
use station::service::{RobotMemory, Station, StationConfig, StationError, StationProgress};
use tokio::sync::{oneshot, watch};
use tracing::{debug, info, warn};
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;

/// How long the observer waits for the last global map once the station has published it.
const GRACE: Duration = Duration::from_secs(10);

/// What the benchmark does.
#[derive(Clone, Debug)]
pub struct LoadConfig {
    /// Scenario the robots come from (default `campus`, 4 robots).
    pub scenario: String,
    /// Robots publishing (default 8).
    pub robots: usize,
    /// Keyframes per second per robot (default 10).
    pub rate_hz: f64,
    /// How long they publish (default 20 s).
    pub seconds: f64,
    /// Keyframe voxel, metres (default 0.2, the outdoor odometry preset's).
    pub voxel: f32,
    /// The station's settings.
    pub station: StationConfig,
    /// Run the station's joint pose graph on the final maps ([`crate::joint`]), when set
    /// (default none: it runs after the station stops and adds nothing to the other figures).
    pub joint: Option<JointConfig>,
}

impl LoadConfig {
    /// The defaults above, with the station's defaults and a 1 s debounce.
    pub fn new() -> Self {
        let fleet = Fleet::new("load").expect("valid fleet name");
        LoadConfig {
            scenario: "campus".into(),
            robots: 8,
            rate_hz: 10.0,
            seconds: 20.0,
            voxel: 0.2,
            station: StationConfig { debounce: Duration::from_secs(1), ..StationConfig::new(fleet) },
            joint: None,
        }
    }

    /// Keyframes each robot publishes (`seconds × rate_hz`, rounded), or why the load is invalid.
    pub fn keyframes_per_robot(&self) -> Result<usize, LoadError> {
        let invalid = |what: String| Err(LoadError::Invalid(what));
        if self.robots == 0 {
            return invalid("robots must be at least 1, got 0".into());
        }
        // Zero for a rate that is not positive (no period), not a number or too high (none between ticks).
        let period = Duration::try_from_secs_f64(1.0 / self.rate_hz).unwrap_or_default();
        if period.is_zero() {
            return invalid(format!("rate_hz must be a positive number of keyframes per second, got {}", self.rate_hz));
        }
        let per_robot = (self.seconds * self.rate_hz).round();
        if !per_robot.is_finite() || per_robot < 1.0 {
            return invalid(format!(
                "seconds × rate_hz must make at least one keyframe per robot, got {} s × {} Hz",
                self.seconds, self.rate_hz
            ));
        }
        Ok(per_robot as usize)
    }
}

impl Default for LoadConfig {
    fn default() -> Self {
        Self::new()
    }
}

/// What was measured.
#[derive(Clone, Debug, Serialize)]
pub struct LoadReport {
    /// Robots.
    pub robots: usize,
    /// Keyframes published over all robots.
    pub sent: u64,
    /// Keyframes the station held at the end.
    pub received: u64,
    /// Mean keyframe payload, bytes.
    pub mean_payload_bytes: f64,
    /// Keyframes the station received per second while the robots published.
    pub received_per_s: f64,
    /// Most keyframes published but not yet taken in by the station at any sample (every 50 ms).
    pub max_backlog: u64,
    /// Merge jobs waiting at most (coalesced: never above 1).
    pub queue_max: u32,
    /// Merges run while publishing and until caught up.
    pub merges: usize,
    /// Merge wall time (composing and publishing a global map), milliseconds (`None` without merges).
    pub merge_ms: Option<Spread>,
    /// Rounds of estimation (preparing maps, tracking and searching pairs) run beside the merges.
    pub rounds: usize,
    /// Their wall time, milliseconds (`None` without rounds).
    pub round_ms: Option<Spread>,
    /// Per keyframe, from its arrival at the station to the first published global map holding it,
    /// milliseconds (`None` when no keyframe was in a map).
    pub latency_ms: Option<Spread>,
    /// Keyframes the station received that no published global map held.
    pub unmapped: u64,
    /// From the last keyframe published to a published global map holding every keyframe, seconds.
    pub catch_up_s: f64,
    /// Robots merged in the final map.
    pub merged_robots: usize,
    /// From the first keyframe published to the first published global map that merges every
    /// robot, seconds (`None` when none did): how soon the fleet shares one map.
    pub all_merged_s: Option<f64>,
    /// How far the final map places each merged robot from the truth, metres and degrees (over
    /// the merged robots but its reference; `None` when it merged no other).
    pub placement_error: Option<PlacementError>,
    /// The worst placement error of any published map, streaming ones included: a wrong link
    /// that was published shows here even when a later merge dropped it.
    pub worst_published_error: Option<PlacementError>,
    /// Resident memory of the process.
    pub rss_mb: Rss,
    /// What the station says it holds per robot once caught up, MB.
    pub station_mb: StationMemory,
    /// The joint pose graph on the final maps, when asked for and the final map merged its
    /// reference.
    pub joint: Option<JointLoad>,
}

/// The station's own count of what it holds ([`station::service::RobotMemory`]), MB.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct StationMemory {
    /// Keyframes as received, over all robots.
    pub keyframes: f64,
    /// Local maps, range images and merge preparations, over all robots.
    pub maps: f64,
    /// The most any one robot costs (both parts).
    pub robot_max: f64,
    /// What a robot costs on average (both parts).
    pub robot_mean: f64,
}

impl StationMemory {
    fn of(memory: &BTreeMap<u32, RobotMemory>) -> Self {
        let mb = |b: u64| b as f64 / 1e6;
        let keyframes = mb(memory.values().map(|m| m.keyframes).sum());
        let maps = mb(memory.values().map(|m| m.map).sum());
        let robot_max = mb(memory.values().map(RobotMemory::total).max().unwrap_or(0));
        let robot_mean = (keyframes + maps) / memory.len().max(1) as f64;
        StationMemory { keyframes, maps, robot_max, robot_mean }
    }
}

/// Placement errors against the simulator's truth.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PlacementError {
    /// Translation error, metres.
    pub metres: Spread,
    /// Rotation error, degrees.
    pub degrees: Spread,
}

impl PlacementError {
    /// Those of `map`'s merged robots against `frames`, each robot's frame in the world; `None`
    /// when the map merged no robot besides its reference.
    fn of(map: &GlobalMap, frames: &BTreeMap<u32, Isometry3<f64>>) -> Option<Self> {
        let reference = frames.get(&map.reference_robot)?;
        let (metres, degrees): (Vec<f64>, Vec<f64>) = map
            .robots
            .iter()
            .filter(|r| r.status() == proto::MergeStatus::Merged && r.robot != map.reference_robot)
            .filter_map(|r| {
                let placed = Isometry3::try_from(r.transform.as_ref()?).ok()?;
                let truth = reference.inverse() * frames.get(&r.robot)?;
                let PoseError { translation_m, rotation_deg } = pose_error(&placed, &truth);
                tracing::debug!(
                    "map {}: robot {} placed {translation_m:.3} m / {rotation_deg:.2} deg from the truth",
                    map.revision,
                    r.robot
                );
                Some((translation_m, rotation_deg))
            })
            .unzip();
        Some(PlacementError { metres: Spread::of_some(&metres)?, degrees: Spread::of_some(&degrees)? })
    }

    /// The larger of two, by their worst translation.
    fn worse(a: Option<Self>, b: Option<Self>) -> Option<Self> {
        match (a, b) {
            (Some(a), Some(b)) => Some(if b.metres.max > a.metres.max { b } else { a }),
            (a, b) => a.or(b),
        }
    }
}

/// Resident memory of the process (Linux `/proc/self/status`), MB; `None` where it cannot be read.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Rss {
    /// `VmRSS` with the payloads prepared and the station started, before publishing.
    pub start: Option<f64>,
    /// `VmRSS` once the station has caught up, before it stops.
    pub end: Option<f64>,
    /// `VmHWM`, the peak, at the end.
    pub peak: Option<f64>,
}

/// Why the benchmark failed.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// A setting out of range.
    #[error("invalid load: {0}")]
    Invalid(String),
    /// Simulation or encoding.
    #[error("preparing keyframes: {0}")]
    Prepare(String),
    /// Zenoh.
    #[error("network: {0}")]
    Network(String),
    /// The station.
    #[error(transparent)]
    Station(#[from] StationError),
    /// The joint pose graph on the final maps.
    #[error("joint pose graph: {0}")]
    Joint(String),
}

/// Runs the benchmark.
pub async fn run(config: LoadConfig) -> Result<LoadReport, LoadError> {
    let per_robot = config.keyframes_per_robot()?;
    info!("preparing {per_robot} keyframes for each of {} robots", config.robots);
    let Prepared { payloads, frames } = tokio::task::spawn_blocking({
        let config = config.clone();
        move || prepare(&config, per_robot)
    })
    .await
    .map_err(|e| LoadError::Prepare(e.to_string()))??;
    for (a, fa) in &frames {
        for (b, fb) in frames.range(a + 1..) {
            // What the station's "best placement" of a refused pair is to be read against.
            let t = fa.inverse() * fb;
            let (v, yaw) = (t.translation.vector, t.rotation.euler_angles().2.to_degrees());
            debug!("robots {a} and {b}: truth ({:.2}, {:.2}, {:.2}) m, yaw {yaw:.1} deg", v.x, v.y, v.z);
        }
    }
    let frames = Arc::new(frames);
    let bytes: usize = payloads.iter().flatten().map(Vec::len).sum();
    let rig = Rig::start(&config).await?;
    let published = Arc::new(AtomicU64::new(0));
    let (stop, stopped) = oneshot::channel();
    let observer =
        tokio::spawn(observe(rig.station.progress(), rig.maps, Arc::clone(&published), Arc::clone(&frames), stopped));
    let rss_start = rss_mb();
    info!("publishing for {} s", config.seconds);
    let publishing_from = Instant::now();
    let publishing = publish_all(rig.robots, payloads, &config, &published).await?;
    let sent = published.load(Ordering::Relaxed);
    let mut progress = rig.station.progress();
    let received_during = progress.borrow().total_keyframes() as f64;
    info!("published {sent} keyframes; waiting for the station to catch up");
    let caught_up = Instant::now();
    let _ = progress.wait_for(|p| p.total_keyframes() as u64 == sent && p.up_to_date()).await;
    let catch_up_s = caught_up.elapsed().as_secs_f64();
    let rss_mb = Rss { start: rss_start, end: rss_mb(), peak: peak_rss_mb() };
    let station_mb = StationMemory::of(&progress.borrow().memory);
    let _ = stop.send(progress.borrow().revision);
    let observed = observer.await.map_err(|e| LoadError::Network(e.to_string()))?;
    let summary = rig.station.stop().await?;
    let merged_robots = summary.global_map.as_ref().map_or(0, merged_count);
    let placement_error = summary.global_map.as_ref().and_then(|m| PlacementError::of(m, &frames));
    let joint = match (&config.joint, &summary.global_map) {
        (Some(joint), Some(map)) => {
            info!("running the joint pose graph on the final maps");
            let (fleet, map, frames, joint) = (summary.fleet.clone(), map.clone(), Arc::clone(&frames), joint.clone());
            tokio::task::spawn_blocking(move || joint::measure(&fleet, &map, &frames, &joint))
                .await
                .map_err(|e| LoadError::Joint(e.to_string()))?
                .map_err(|e| LoadError::Joint(e.to_string()))?
        }
        _ => None,
    };
    Ok(LoadReport {
        robots: config.robots,
        sent,
        received: summary.keyframes.values().sum::<usize>() as u64,
        mean_payload_bytes: bytes as f64 / sent.max(1) as f64,
        received_per_s: received_during / publishing.as_secs_f64(),
        max_backlog: observed.max_backlog,
        queue_max: observed.queue_max,
        merges: summary.merge_ms.len(),
        merge_ms: Spread::of_some(&summary.merge_ms),
        rounds: summary.round_ms.len(),
        round_ms: Spread::of_some(&summary.round_ms),
        latency_ms: Spread::of_some(&observed.latencies.ms),
        unmapped: observed.latencies.unmapped(),
        catch_up_s,
        merged_robots,
        all_merged_s: observed.all_merged.map(|at| at.saturating_duration_since(publishing_from).as_secs_f64()),
        placement_error,
        worst_published_error: observed.worst_error,
        rss_mb,
        station_mb,
        joint,
    })
}

/// The station, the robots' sessions and the observer's subscription to the global maps, each
/// robot and the observer on a session of its own connected to the station's port.
struct Rig {
    /// The station, listening on the port.
    station: Station,
    /// One session per robot.
    robots: Vec<zenoh::Session>,
    /// Kept open for `maps`.
    _observer: zenoh::Session,
    /// The observer's subscription to the fleet's global maps.
    maps: Subscriber<FifoChannelHandler<Sample>>,
}

impl Rig {
    /// Starts the station on a free loopback port and connects the robots and the observer to it.
    async fn start(config: &LoadConfig) -> Result<Rig, LoadError> {
        let port = bus::free_port().map_err(|e| LoadError::Network(e.to_string()))?;
        let station_session = open(&bus::Network::loopback_ports(&[port], &[])).await?;
        let station = Station::start(station_session, config.station.clone()).await?;
        let mut robots = Vec::new();
        for _ in 0..config.robots {
            robots.push(open(&bus::Network::loopback_ports(&[], &[port])).await?);
        }
        let observer = open(&bus::Network::loopback_ports(&[], &[port])).await?;
        let maps = observer
            .declare_subscriber(keyexpr::global_map(&config.station.fleet))
            .await
            .map_err(|e| LoadError::Network(e.to_string()))?;
        Ok(Rig { station, robots, _observer: observer, maps })
    }
}

async fn open(network: &bus::Network) -> Result<zenoh::Session, LoadError> {
    network.open().await.map_err(|e| LoadError::Network(e.to_string()))
}

/// Every robot publishes its payloads on its session at the configured rate; returns how long
/// that took.
async fn publish_all(
    sessions: Vec<zenoh::Session>,
    payloads: Vec<Vec<Vec<u8>>>,
    config: &LoadConfig,
    published: &Arc<AtomicU64>,
) -> Result<Duration, LoadError> {
    let started = Instant::now();
    let mut robots = Vec::new();
    for (i, (session, robot_payloads)) in sessions.into_iter().zip(payloads).enumerate() {
        let key = keyexpr::keyframe(&config.station.fleet, i as u32 + 1);
        robots.push(tokio::spawn(publish(session, key, robot_payloads, config.rate_hz, Arc::clone(published))));
    }
    for r in robots {
        r.await.map_err(|e| LoadError::Network(e.to_string()))??;
    }
    Ok(started.elapsed())
}

/// What the robots will publish, and the truth to judge the merge by.
struct Prepared {
    /// Per robot, its keyframe payloads in order.
    payloads: Vec<Vec<Vec<u8>>>,
    /// Per robot id, its odometry frame in the world.
    frames: BTreeMap<u32, Isometry3<f64>>,
}

/// Every robot's keyframe payloads, in order: simulated scans, deskewed, at their true poses
/// (relative to the robot's first), voxelised and encoded. Robot `i` beyond the scenario's own replays robot
/// `i mod n` from later in its run: the replays of a robot start evenly spread over the time it
/// moves, so that none is parked (a parked replay sends one scan over and over, which no robot
/// does, and two parked at one place are trivially linked).
fn prepare(config: &LoadConfig, per_robot: usize) -> Result<Prepared, LoadError> {
    let scenario = Scenario::by_name(&config.scenario).map_err(|e| LoadError::Prepare(e.to_string()))?;
    let own = scenario.robots().len();
    let fleet = &config.station.fleet;
    let robots: Vec<(Vec<Vec<u8>>, Isometry3<f64>)> = (0..config.robots)
        .into_par_iter()
        .map(|i| {
            let sim = Simulator::new(scenario.clone(), i % own, SimConfig::default())
                .map_err(|e| LoadError::Prepare(e.to_string()))?;
            let replays = config.robots.div_ceil(own);
            let moving = (sim.trajectory().duration() / sim.config().sensor.period) as usize;
            let offset = (i / own) * moving / replays;
            let frame = sim.ground_truth(offset);
            let origin = frame.inverse();
            let payloads = (0..per_robot)
                .map(|k| {
                    let scan = sim.scan(offset + k);
                    // Deskewed as the robot's odometry would: the raw sweep at 2 m/s is smeared by
                    // up to 20 cm, which no edge sends.
                    let cloud = cloud::voxel::downsample(&sim.deskewed(&scan), config.voxel)
                        .map_err(|e| LoadError::Prepare(e.to_string()))?;
                    // With its place descriptor, as every robot sends it (the outdoor one: the
                    // station's preset here is outdoor).
                    let context = ScanContext::new(&cloud, &ScanContextConfig::default());
                    let kf = Keyframe { seq: k as u64, frame: k, pose: origin * scan.ground_truth, cloud };
                    keyframe_message(fleet, i as u32 + 1, &kf, scan.stamp, Some(&context), &CodecConfig::default())
                        .map(|m| m.encode_to_vec())
                        .map_err(|e| LoadError::Prepare(e.to_string()))
                })
                .collect::<Result<_, _>>()?;
            Ok((payloads, frame))
        })
        .collect::<Result<_, LoadError>>()?;
    let frames = robots.iter().enumerate().map(|(i, (_, frame))| (i as u32 + 1, *frame)).collect();
    Ok(Prepared { payloads: robots.into_iter().map(|(p, _)| p).collect(), frames })
}

/// Publishes one robot's keyframes at `rate_hz`, blocking under congestion as the edges do.
async fn publish(
    session: zenoh::Session,
    key: String,
    payloads: Vec<Vec<u8>>,
    rate_hz: f64,
    published: Arc<AtomicU64>,
) -> Result<(), LoadError> {
    let publisher = session
        .declare_publisher(key)
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .map_err(|e| LoadError::Network(e.to_string()))?;
    let deadline = Instant::now() + Duration::from_secs(5);
    while !publisher.matching_status().await.is_ok_and(|s| s.matching()) && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / rate_hz));
    for p in payloads {
        tick.tick().await;
        publisher.put(p).await.map_err(|e| LoadError::Network(e.to_string()))?;
        published.fetch_add(1, Ordering::Relaxed);
    }
    Ok(())
}

/// What the observer saw.
#[derive(Debug, Default)]
struct Observed {
    /// Arrivals, maps and the latencies they give.
    latencies: Latencies,
    /// Most keyframes published but not yet held at a sample.
    max_backlog: u64,
    /// Merge jobs waiting at most.
    queue_max: u32,
    /// The worst placement error of a published map.
    worst_error: Option<PlacementError>,
    /// When the first map merging every robot was received.
    all_merged: Option<Instant>,
}

impl Observed {
    /// A change of the station's progress, seen at `at`.
    fn progress(&mut self, p: &StationProgress, at: Instant) {
        self.queue_max = self.queue_max.max(u32::from(p.merge_pending));
        self.latencies.arrived(&p.keyframes, at);
    }

    /// A backlog sample: keyframes published but not yet held.
    fn backlog(&mut self, sent: u64, p: &StationProgress) {
        self.max_backlog = self.max_backlog.max(sent.saturating_sub(p.total_keyframes() as u64));
    }
}

/// Watches the station until it has received the global map whose revision comes through `stop`
/// (sent once the station has caught up), or [`GRACE`] after that: keyframe arrivals and the merge
/// queue on every change of progress, published maps for the latencies, the backlog every 50 ms.
async fn observe(
    mut progress: watch::Receiver<StationProgress>,
    maps: Subscriber<FifoChannelHandler<Sample>>,
    published: Arc<AtomicU64>,
    frames: Arc<BTreeMap<u32, Isometry3<f64>>>,
    mut stop: oneshot::Receiver<u64>,
) -> Observed {
    let mut seen = Observed::default();
    let mut tick = tokio::time::interval(Duration::from_millis(50));
    let mut last: Option<(u64, tokio::time::Instant)> = None;
    loop {
        if last.is_some_and(|(revision, _)| seen.latencies.revision >= revision) {
            break;
        }
        let deadline = last.map_or_else(tokio::time::Instant::now, |(_, d)| d);
        tokio::select! {
            Ok(()) = progress.changed() => seen.progress(&progress.borrow_and_update(), Instant::now()),
            Ok(sample) = maps.recv_async() => {
                let at = Instant::now();
                seen.progress(&progress.borrow_and_update(), at);
                match GlobalMap::decode(&*sample.payload().to_bytes()) {
                    Ok(map) => {
                        seen.latencies.mapped(&map, at);
                        if seen.all_merged.is_none() && merges_all(&map, frames.len()) {
                            seen.all_merged = Some(at);
                        }
                        seen.worst_error = PlacementError::worse(seen.worst_error, PlacementError::of(&map, &frames));
                    }
                    Err(e) => warn!("cannot decode a global map: {e}"),
                }
            }
            _ = tick.tick() => seen.backlog(published.load(Ordering::Relaxed), &progress.borrow()),
            // A dropped sender (the run failed) stops at once.
            revision = &mut stop, if last.is_none() => {
                last = Some((revision.unwrap_or(0), tokio::time::Instant::now() + GRACE));
            }
            () = tokio::time::sleep_until(deadline), if last.is_some() => {
                warn!("the last global map did not arrive within {GRACE:?}");
                break;
            }
        }
    }
    seen
}

/// The robots `map` merges.
fn merged_count(map: &GlobalMap) -> usize {
    map.robots.iter().filter(|r| r.status() == proto::MergeStatus::Merged).count()
}

/// Whether `map` merges all `robots` robots.
fn merges_all(map: &GlobalMap, robots: usize) -> bool {
    merged_count(map) == robots
}

/// Each keyframe's latency from its arrival at the station to the first published map holding it.
///
/// Counts only grow, so the k-th keyframe of a robot arrived when its count first reached k, and a
/// map whose placement of the robot counts n keyframes holds its first n.
#[derive(Debug, Default)]
struct Latencies {
    /// Per robot, when its count of keyframes held first reached 1, 2, ...
    arrived: BTreeMap<u32, Vec<Instant>>,
    /// Per robot, how many of its first keyframes a received map has held.
    mapped: BTreeMap<u32, usize>,
    /// The latencies credited so far, milliseconds.
    ms: Vec<f64>,
    /// Newest revision received.
    revision: u64,
}

impl Latencies {
    /// Counts of keyframes held per robot, seen at `at`.
    fn arrived(&mut self, held: &BTreeMap<u32, usize>, at: Instant) {
        for (&robot, &count) in held {
            let times = self.arrived.entry(robot).or_default();
            if count > times.len() {
                times.resize(count, at);
            }
        }
    }

    /// A published map, received at `at`: credits the keyframes it is the first to hold.
    fn mapped(&mut self, map: &GlobalMap, at: Instant) {
        for placement in &map.robots {
            let times = self.arrived.get(&placement.robot).map_or(&[][..], Vec::as_slice);
            let held = (placement.keyframes as usize).min(times.len());
            let done = self.mapped.entry(placement.robot).or_default();
            for &t in times.get(*done..held).unwrap_or_default() {
                self.ms.push(cloud::stopwatch::millis(at - t));
            }
            *done = held.max(*done);
        }
        self.revision = self.revision.max(map.revision);
    }

    /// Keyframes that arrived but no received map held.
    fn unmapped(&self) -> u64 {
        let arrived: usize = self.arrived.values().map(Vec::len).sum();
        (arrived - self.mapped.values().sum::<usize>()) as u64
    }
}

impl fmt::Display for LoadReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "{} robots sent {} keyframes ({:.1} kB mean); the station holds {} ({:.1} per s while \
             publishing, backlog at most {})",
            self.robots,
            self.sent,
            self.mean_payload_bytes / 1e3,
            self.received,
            self.received_per_s,
            self.max_backlog
        )?;
        writeln!(
            f,
            "{} merges, {}; merge queue at most {}; {} robots merged ({})",
            self.merges,
            spread(self.merge_ms),
            self.queue_max,
            self.merged_robots,
            self.all_merged_s
                .map_or("never all in one map".into(), |s| format!("all of them {s:.1} s after the first keyframe"))
        )?;
        writeln!(f, "{} rounds of estimation beside them, {}", self.rounds, spread(self.round_ms))?;
        writeln!(
            f,
            "latency from arrival to the first published map holding it: {}; {} keyframes in no map; \
             caught up {:.2} s after the last keyframe",
            spread(self.latency_ms),
            self.unmapped,
            self.catch_up_s
        )?;
        writeln!(
            f,
            "placement against the truth: {} in the final map, {} at worst in a published one",
            placement(self.placement_error),
            placement(self.worst_published_error)
        )?;
        let mb = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.0} MB"));
        write!(
            f,
            "resident memory: {} at start, {} at end, {} peak; the station holds {:.0} MB of keyframes and \
             {:.0} MB of maps, {:.1} MB per robot on average, {:.1} MB at most",
            mb(self.rss_mb.start),
            mb(self.rss_mb.end),
            mb(self.rss_mb.peak),
            self.station_mb.keyframes,
            self.station_mb.maps,
            self.station_mb.robot_mean,
            self.station_mb.robot_max
        )?;
        if let Some(j) = &self.joint {
            let cm = |v: Option<f64>| v.map_or("-".into(), |v| format!("{:.1} cm", v * 100.0));
            write!(
                f,
                "\njoint pose graph: {} keyframes of {} robots, {} inter-robot edges registered, {} consistent, \
                 {} robots joined, {:.1} s (edges {:.1} s, consistency {:.0} ms, optimising {:.0} ms); keyframes against the truth: rigid {}, joint {}; \
                 edges against the truth: {}",
                j.keyframes,
                j.robots,
                j.registered,
                j.kept,
                j.joined,
                j.ms / 1e3,
                j.edges_ms / 1e3,
                j.consistency_ms,
                j.optimise_ms,
                cm(j.rigid_rmse_m),
                cm(j.joint_rmse_m),
                j.edge_error_m.zip(j.edge_error_deg).map_or("none".into(), |(m, d)| format!(
                    "median {:.1} cm / {:.2} deg, p95 {:.1} cm / {:.2} deg, max {:.1} cm / {:.2} deg",
                    m.median * 100.0,
                    d.median,
                    m.p95 * 100.0,
                    d.p95,
                    m.max * 100.0,
                    d.max
                ))
            )?;
        }
        Ok(())
    }
}

/// `max … m / … deg (median … m)`, or `none`.
fn placement(e: Option<PlacementError>) -> String {
    e.map_or("none".into(), |e| {
        format!("max {:.3} m / {:.2} deg (median {:.3} m)", e.metres.max, e.degrees.max, e.metres.median)
    })
}

/// `median … / p95 … / max … ms`, or `none`.
fn spread(p: Option<Spread>) -> String {
    p.map_or("none".into(), |p| format!("median {:.0} / p95 {:.0} / max {:.0} ms", p.median, p.p95, p.max))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::RobotPlacement;

    fn map(revision: u64, placements: &[(u32, u64)]) -> GlobalMap {
        let robots =
            placements.iter().map(|&(robot, keyframes)| RobotPlacement { robot, keyframes, ..Default::default() });
        GlobalMap { revision, robots: robots.collect(), ..Default::default() }
    }

    #[test]
    fn placement_errors_are_measured_against_the_reference_robots_truth() {
        use nalgebra::{Translation3, UnitQuaternion, Vector3};
        let frames = BTreeMap::from([
            (1, Isometry3::new(Vector3::new(10.0, 0.0, 0.0), Vector3::z() * 0.5)),
            (2, Isometry3::new(Vector3::new(0.0, 5.0, 1.0), Vector3::z() * -1.0)),
            (3, Isometry3::new(Vector3::new(3.0, 3.0, 0.0), Vector3::z() * 2.0)),
        ]);
        let truth = |r: u32| frames[&1].inverse() * frames[&r];
        let off =
            Isometry3::from_parts(Translation3::new(0.3, 0.0, 0.4), UnitQuaternion::from_euler_angles(0.0, 0.0, 0.02));
        let placed = |robot: u32, transform: Isometry3<f64>, merged: bool| RobotPlacement {
            robot,
            transform: Some(transform.into()),
            status: if merged { proto::MergeStatus::Merged } else { proto::MergeStatus::Unmerged } as i32,
            ..Default::default()
        };
        let map = GlobalMap {
            reference_robot: 1,
            robots: vec![
                placed(1, Isometry3::identity(), true),
                placed(2, truth(2) * off, true),
                placed(3, Isometry3::identity(), false),
            ],
            ..Default::default()
        };
        let e = PlacementError::of(&map, &frames).expect("robot 2 is merged");
        assert!((e.metres.max - 0.5).abs() < 1e-9, "{e:?}");
        assert!((e.degrees.max - 0.02f64.to_degrees()).abs() < 1e-9, "{e:?}");
        let alone = GlobalMap { robots: vec![placed(1, Isometry3::identity(), true)], ..map.clone() };
        assert_eq!(PlacementError::of(&alone, &frames), None);
        assert_eq!(PlacementError::worse(Some(e), None), Some(e));
    }

    #[test]
    fn each_keyframe_is_credited_once_to_the_first_map_holding_it() {
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        let mut l = Latencies::default();
        l.arrived(&BTreeMap::from([(1, 2), (2, 1)]), at(0));
        l.arrived(&BTreeMap::from([(1, 3), (2, 1)]), at(100));
        l.mapped(&map(1, &[(1, 2), (2, 0)]), at(1000));
        assert_eq!(l.ms, [1000.0, 1000.0]);
        assert_eq!(l.unmapped(), 2);
        l.mapped(&map(2, &[(1, 3), (2, 1)]), at(2000));
        assert_eq!(l.ms, [1000.0, 1000.0, 1900.0, 2000.0]);
        assert_eq!((l.unmapped(), l.revision), (0, 2));
    }

    #[test]
    fn a_load_without_keyframes_is_invalid() {
        let ok = LoadConfig { robots: 2, rate_hz: 5.0, seconds: 3.0, ..LoadConfig::new() };
        assert_eq!(ok.keyframes_per_robot().unwrap(), 15);
        for bad in [
            LoadConfig { robots: 0, ..ok.clone() },
            LoadConfig { rate_hz: 0.0, ..ok.clone() },
            LoadConfig { rate_hz: f64::NAN, ..ok.clone() },
            LoadConfig { seconds: -1.0, ..ok.clone() },
            LoadConfig { seconds: 0.01, ..ok.clone() },
        ] {
            assert!(matches!(bad.keyframes_per_robot(), Err(LoadError::Invalid(_))), "{bad:?}");
        }
    }
}
