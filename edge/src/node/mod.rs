//! The robot's network service: odometry on a scan source, keyframes published on Zenoh, a keyframe
//! store answering backfill requests, and a liveliness token while it runs.
//!
//! The source, the odometry and the loop closure run on a blocking thread (`worker`); this module's
//! async half publishes what it registers, keeps the encoded keyframes (`store`) and serves them
//! (`serve`), and publishes each pose-graph update, answering queries on the pose-graph key with
//! the newest one (it supersedes the earlier ones).
//!
//! Backfill replies all carry the store's key expression (`emr/{fleet}/robot/{id}/keyframes`), one
//! sample per keyframe: an asker must `get` with `ConsolidationMode::None`, or zenoh's default
//! consolidation keeps a single reply.

mod ros2;
mod serve;
pub mod state_dir;
mod store;
mod worker;

use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use nalgebra::Isometry3;
use proto::codec::{CodecConfig, EncodeError};
use proto::{Fleet, keyexpr};
use sim::SimConfig;
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinHandle;
use tracing::{info, warn};
use zenoh::Session;
use zenoh::bytes::ZBytes;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Publisher;
use zenoh::qos::CongestionControl;

use crate::loops::{self, LoopCloser, LoopError};
use crate::odometry::{Odometry, OdometryConfig, OdometryError};
use crate::recording::RecordingOptions;
use crate::ros2_topic::Link;
use crate::source::{Source, SourceError, SourceLosses, SourceSpec};
use state_dir::StateDir;
use store::Store;
use worker::{EncodedKeyframe, EncodedPoseGraph, Made, Registered, Worker};

/// Default budget of the keyframe store: 256 MiB of encoded keyframes.
pub const DEFAULT_STORE_BYTES: usize = 256 << 20;

/// Registered scans in flight between the odometry thread and the publisher.
const CHANNEL_SCANS: usize = 32;

/// How long the first keyframe waits for a subscriber before it is published anyway.
const MATCH_PATIENCE: Duration = Duration::from_secs(2);

/// Scans between two progress lines.
const PROGRESS_EVERY: usize = 100;

/// How fast the source is read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rate {
    /// Scans are paced by their stamps, as a live sensor would deliver them.
    Realtime,
    /// As fast as the odometry goes.
    Max,
}

/// Everything a node needs besides its session.
#[derive(Clone, Debug)]
pub struct NodeConfig {
    /// Fleet the robot belongs to.
    pub fleet: Fleet,
    /// Robot id within the fleet.
    pub robot: u32,
    /// This start's session, carried by every keyframe and pose-graph update: a robot that
    /// restarts begins a new odometry frame and numbers its keyframes from 0 again, and the
    /// station keeps each session as a map of its own. Must be higher than every earlier session
    /// of the robot ([`new_session`] gives one).
    pub session: u64,
    /// Where scans come from.
    pub source: SourceSpec,
    /// Leave out the source's first scans (a restart reproduced from a recording or the
    /// simulator: the robot starts where it stopped, in a new odometry frame).
    pub start_at: usize,
    /// Stop after this many scans (counted from `start_at`).
    pub max_frames: Option<usize>,
    /// How fast the source is read.
    pub rate: Rate,
    /// The odometry's configuration (its `loops` section configures the loop closure).
    pub odometry: OdometryConfig,
    /// Close loops and publish the pose graph (EMR mode); off: odometry only (MR mode).
    pub loops: bool,
    /// Simulated sensor settings (for `sim:` sources).
    pub sim: SimConfig,
    /// How recordings are read.
    pub recording: RecordingOptions,
    /// How keyframe clouds are compressed.
    pub codec: CodecConfig,
    /// Bytes of encoded keyframes kept for backfill; the oldest are evicted first.
    pub store_bytes: usize,
    /// Where the keyframes are kept on disk too, every session's, for backfill after a crash
    /// (`emr-edge run --state DIR`); `None`: in memory only.
    pub state: Option<Arc<Mutex<StateDir>>>,
    /// After the source ends, keep serving backfill requests until shutdown.
    pub linger: bool,
    /// Called once when the source has ended and its keyframes are published (before lingering).
    pub on_source_end: Option<SourceEnd>,
    /// The ROS domain to publish the odometry and keyframes in as ROS 2 topics; `None`: none.
    pub ros2_domain: Option<u32>,
}

/// A callback told what the node did when its source ends: the demo and `emr-edge run --summary`
/// learn there that the robot is done while it still serves backfill requests.
#[derive(Clone)]
pub struct SourceEnd(pub Arc<dyn Fn(&NodeSummary) + Send + Sync>);

impl std::fmt::Debug for SourceEnd {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SourceEnd(..)")
    }
}

impl NodeConfig {
    /// Defaults: session 0, realtime, indoor odometry, 1 mm codec, a 256 MiB store, lingering after the source.
    pub fn new(fleet: Fleet, robot: u32, source: SourceSpec) -> Self {
        NodeConfig {
            fleet,
            robot,
            session: 0,
            source,
            start_at: 0,
            max_frames: None,
            rate: Rate::Realtime,
            odometry: OdometryConfig::indoor(),
            loops: true,
            sim: SimConfig::default(),
            recording: RecordingOptions::default(),
            codec: CodecConfig::default(),
            store_bytes: DEFAULT_STORE_BYTES,
            state: None,
            linger: true,
            on_source_end: None,
            ros2_domain: None,
        }
    }
}

/// A session id for a start now: the wall clock in seconds, so that each start of a robot gets a
/// higher one than the last without anything kept between starts; above `after` (the newest session
/// the robot is known to have had) whatever the clock says.
pub fn new_session(after: Option<u64>) -> u64 {
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
    after.map_or(now, |a| now.max(a.saturating_add(1)))
}

/// What a node did.
#[derive(Clone, Debug, Default)]
pub struct NodeSummary {
    /// Scans registered.
    pub frames: usize,
    /// Keyframes published.
    pub keyframes: u64,
    /// Sensor pose at each scan's sweep end, odometry frame.
    pub poses: Vec<Isometry3<f64>>,
    /// Each scan's sweep start, seconds.
    pub stamps: Vec<f64>,
    /// Each scan's ground-truth pose (world frame), when the source knows it.
    pub ground_truth: Vec<Option<Isometry3<f64>>>,
    /// Bytes of keyframe messages published.
    pub published_bytes: u64,
    /// Loops in the pose graph.
    pub loops: usize,
    /// Pose-graph updates published (the newest one's revision).
    pub posegraph_revision: u64,
    /// Each scan's keyframe: the newest one at or before it.
    pub keyframe_of_scan: Vec<usize>,
    /// Each keyframe's odometry pose.
    pub keyframe_poses: Vec<Isometry3<f64>>,
    /// Each keyframe's pose in the newest pose graph (empty while no loop was closed).
    pub optimised_keyframes: Vec<Isometry3<f64>>,
    /// Wall time of the odometry on each scan, milliseconds (loop closure and publishing apart).
    pub odometry_ms: Vec<f64>,
    /// What the node held of its keyframes when it stopped.
    pub held: Held,
    /// What the source lost before the odometry (a live sensor's dropped scans, packet gaps).
    pub source_losses: SourceLosses,
}

/// What a node holds of the keyframes it made, bytes, by its own count of its buffers: exact and
/// deterministic, where the process's resident memory also moves with the allocator. Everything
/// else the node keeps is bounded whatever the link does (the channel's scan count, zenoh's queues,
/// the newest pose graph), so these are what may grow while the station cannot be reached.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Held {
    /// Keyframes the odometry thread has made and encoded so far.
    pub made: u64,
    /// Encoded keyframes in the backfill store.
    pub store: u64,
    /// Encoded keyframes made but not yet taken by the publisher.
    pub in_flight: u64,
    /// What the loop closure keeps of each keyframe: its thinned cloud and its descriptor.
    pub loops: u64,
}

impl std::fmt::Display for Held {
    /// `robot R: S scans, K keyframes (` is the progress line's start; this is its rest, read by the
    /// multi-host test: keep the words.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} keyframes made, holding {} bytes of them (store {}, in flight {}) and {} bytes for loops",
            self.made,
            self.store + self.in_flight,
            self.store,
            self.in_flight,
            self.loops
        )
    }
}

impl NodeSummary {
    /// Each scan's pose with the newest pose graph applied: its keyframe's optimised pose and the
    /// odometry's motion since that keyframe (the odometry poses while no loop was closed).
    pub fn corrected_poses(&self) -> Vec<Isometry3<f64>> {
        self.poses
            .iter()
            .zip(&self.keyframe_of_scan)
            .map(|(pose, &k)| match (self.optimised_keyframes.get(k), self.keyframe_poses.get(k)) {
                (Some(optimised), Some(odometry)) => loops::graph::follow(optimised, odometry, pose),
                _ => *pose,
            })
            .collect()
    }
}

/// Why a node stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    /// The source could not be opened.
    #[error("source {input}: {source}")]
    Source {
        /// The source as given.
        input: String,
        /// What went wrong (boxed: it is large, and rare).
        source: Box<SourceError>,
    },
    /// The odometry configuration is unusable.
    #[error("odometry: {0}")]
    OdometryConfig(#[source] OdometryError),
    /// A scan could not be registered.
    #[error("scan {index}: {source}")]
    Odometry {
        /// Position of the scan in the source.
        index: usize,
        /// What the odometry said.
        source: OdometryError,
    },
    /// The loop closure failed on a keyframe.
    #[error("loop closure at keyframe {seq}: {source}")]
    Loops {
        /// Keyframe sequence number.
        seq: u64,
        /// What the loop closure said.
        source: LoopError,
    },
    /// A keyframe's cloud could not be encoded.
    #[error("keyframe {seq}: {source}")]
    Encode {
        /// Keyframe sequence number.
        seq: u64,
        /// What the codec said.
        source: EncodeError,
    },
    /// Zenoh refused a declaration or a publication.
    #[error("zenoh: cannot {what} {key}: {message}")]
    Zenoh {
        /// What was attempted.
        what: &'static str,
        /// The key expression.
        key: String,
        /// What zenoh said.
        message: String,
    },
    /// The odometry thread panicked.
    #[error("the odometry thread failed: {0}")]
    Worker(String),
    /// The ROS 2 topics could not be set up.
    #[error("ROS 2: {0}")]
    Ros2(String),
}

/// Runs a robot until its source ends (and, when `linger`, until `shutdown`) or `shutdown` resolves:
/// then it publishes the keyframes already made, undeclares everything and says what it did.
pub async fn run(
    session: &Session,
    config: NodeConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<NodeSummary, NodeError> {
    // Set on shutdown: a live source stops waiting for its next scan.
    let interrupt = Arc::new(AtomicBool::new(false));
    let worker = Worker {
        source: open_source(session, &config).await?.until(interrupt.clone()),
        odometry: Odometry::new(config.odometry.clone()).map_err(NodeError::OdometryConfig)?,
        fleet: config.fleet.clone(),
        robot: config.robot,
        session: config.session,
        codec: config.codec.clone(),
        rate: config.rate,
        loops: config.loops.then(|| LoopCloser::new(config.odometry.loops.clone())),
        scan_context: config.odometry.loops.scan_context.clone(),
        made: Arc::new(Mutex::new(Made::default())),
        keep_clouds: config.ros2_domain.is_some(),
    };
    let links = Links::declare(session, &config).await?;
    let made = worker.made.clone();
    let (tx, rx) = mpsc::channel(CHANNEL_SCANS);
    let thread = tokio::task::spawn_blocking(move || worker.run(tx));
    let mut outbox = Outbox::new(&links, config.robot, made);
    let shutdown = async move {
        shutdown.await;
        interrupt.store(true, Ordering::Relaxed);
    };
    let pumped = pump(&mut outbox, rx, thread, &config, shutdown).await;
    outbox.summary.held = outbox.held();
    let summary = outbox.summary;
    links.undeclare().await;
    pumped?;
    Ok(summary)
}

/// Opens the source off the async threads (a simulated world is built, a recording indexed); a
/// ROS 2 topic is read on the node's own session.
async fn open_source(session: &Session, config: &NodeConfig) -> Result<Source, NodeError> {
    let (spec, frames, sim, recording) =
        (config.source.clone(), config.max_frames, config.sim.clone(), config.recording.clone());
    let start_at = config.start_at;
    let link = Link::Session(session.clone());
    let opened = tokio::task::spawn_blocking(move || {
        let source = match &spec {
            SourceSpec::Ros2 { topic, domain, .. } => Source::ros2(link, *domain, topic, frames, &recording),
            _ => Source::open(&spec, frames, &sim, &recording),
        };
        source.map(|source| source.starting_at(start_at))
    })
    .await
    .map_err(|e| NodeError::Worker(e.to_string()))?;
    opened.map_err(|e| NodeError::Source { input: config.source.to_string(), source: Box::new(e) })
}

/// Publishes what the worker registers until it is done, then lingers if asked; on `shutdown`
/// closes the channel (the worker stops after its current scan) and drains what is in it.
async fn pump(
    outbox: &mut Outbox<'_>,
    mut rx: mpsc::Receiver<Registered>,
    thread: JoinHandle<Result<(), NodeError>>,
    config: &NodeConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<(), NodeError> {
    let linger = config.linger;
    let mut shutdown = std::pin::pin!(shutdown);
    let mut thread = Some(thread);
    let mut stopping = false;
    loop {
        tokio::select! {
            () = &mut shutdown, if !stopping => {
                info!("robot {}: shutting down, publishing the keyframes already made", outbox.robot);
                stopping = true;
                rx.close();
            }
            scan = rx.recv(), if thread.is_some() => match scan {
                Some(scan) => outbox.send(scan).await?,
                None => if let Some(thread) = thread.take() {
                    finish(thread).await?;
                    // The last scan's progress line, unless it has just been written.
                    if !outbox.summary.frames.is_multiple_of(PROGRESS_EVERY) {
                        outbox.progress();
                    }
                    info!("robot {}: source done after {} scans", outbox.robot, outbox.summary.frames);
                    if let Some(SourceEnd(tell)) = &config.on_source_end && !stopping {
                        tell(&outbox.summary);
                    }
                },
            },
            else => break,
        }
        if thread.is_none() && (stopping || !linger) {
            break;
        }
    }
    Ok(())
}

/// The worker's outcome once its channel has closed.
async fn finish(thread: JoinHandle<Result<(), NodeError>>) -> Result<(), NodeError> {
    thread.await.map_err(|e| NodeError::Worker(e.to_string()))?
}

/// What a node declares on its session.
struct Links<'a> {
    token: LivelinessToken,
    publisher: Publisher<'a>,
    store: Arc<Mutex<Store>>,
    serving: JoinHandle<()>,
    stop_serving: oneshot::Sender<()>,
    posegraph: Publisher<'a>,
    /// The newest pose-graph update: it supersedes every earlier one, so it is all a late
    /// subscriber needs.
    latest_posegraph: Arc<Mutex<Option<ZBytes>>>,
    serving_posegraph: JoinHandle<()>,
    stop_serving_posegraph: oneshot::Sender<()>,
    /// The ROS 2 topics, when asked for.
    ros2: Option<ros2::EdgeRos2>,
}

impl<'a> Links<'a> {
    /// The liveliness token, the keyframe publisher and the store's queryable.
    async fn declare(session: &'a Session, config: &NodeConfig) -> Result<Self, NodeError> {
        let (fleet, robot) = (&config.fleet, config.robot);
        let alive = keyexpr::alive(fleet, robot);
        let token = session.liveliness().declare_token(&alive).await.map_err(zenoh_error("declare", &alive))?;
        let key = keyexpr::keyframe(fleet, robot);
        // Block, not the default Drop: a keyframe dropped under load would leave a gap to backfill.
        // Reliability is zenoh's default (reliable); setting it explicitly is an unstable API.
        let publisher = session
            .declare_publisher(key.clone())
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(zenoh_error("declare", &key))?;
        let key = keyexpr::keyframe_store(fleet, robot);
        let queryable = session.declare_queryable(key.clone()).await.map_err(zenoh_error("declare", &key))?;
        let store =
            Arc::new(Mutex::new(Store::new(config.session, config.store_bytes).with_disk(config.state.clone())));
        let (stop_serving, stop) = oneshot::channel();
        let serving = tokio::spawn(serve::serve(queryable, store.clone(), stop));
        let key = keyexpr::posegraph(fleet, robot);
        let posegraph = session
            .declare_publisher(key.clone())
            .congestion_control(CongestionControl::Block)
            .await
            .map_err(zenoh_error("declare", &key))?;
        let queryable = session.declare_queryable(key.clone()).await.map_err(zenoh_error("declare", &key))?;
        let latest_posegraph = Arc::new(Mutex::new(None));
        let (stop_serving_posegraph, stop) = oneshot::channel();
        let serving_posegraph = tokio::spawn(serve::serve_latest(queryable, latest_posegraph.clone(), stop));
        let ros2 = match config.ros2_domain {
            Some(domain) => Some(ros2::EdgeRos2::declare(session, fleet, robot, domain).await?),
            None => None,
        };
        Ok(Links {
            token,
            publisher,
            store,
            serving,
            stop_serving,
            posegraph,
            latest_posegraph,
            serving_posegraph,
            stop_serving_posegraph,
            ros2,
        })
    }

    /// Stops serving and undeclares everything; failures are only logged (the node is done anyway).
    async fn undeclare(self) {
        let _ = self.stop_serving.send(());
        if let Err(e) = self.serving.await {
            warn!("the keyframe queryable task failed: {e}");
        }
        let _ = self.stop_serving_posegraph.send(());
        if let Err(e) = self.serving_posegraph.await {
            warn!("the pose-graph queryable task failed: {e}");
        }
        if let Err(e) = self.posegraph.undeclare().await {
            warn!("cannot undeclare the pose-graph publisher: {e}");
        }
        if let Err(e) = self.publisher.undeclare().await {
            warn!("cannot undeclare the keyframe publisher: {e}");
        }
        if let Err(e) = self.token.undeclare().await {
            warn!("cannot undeclare the liveliness token: {e}");
        }
    }
}

/// Maps a zenoh error to [`NodeError::Zenoh`].
fn zenoh_error(what: &'static str, key: &str) -> impl FnOnce(zenoh::Error) -> NodeError {
    let key = key.to_owned();
    move |e| NodeError::Zenoh { what, key, message: e.to_string() }
}

/// The publishing side: stores and publishes keyframes, and keeps the summary.
struct Outbox<'l> {
    links: &'l Links<'l>,
    robot: u32,
    matched: bool,
    summary: NodeSummary,
    /// The worker's side of the count of what is held.
    made: Arc<Mutex<Made>>,
}

impl<'l> Outbox<'l> {
    fn new(links: &'l Links<'l>, robot: u32, made: Arc<Mutex<Made>>) -> Self {
        Outbox { links, robot, matched: false, summary: NodeSummary::default(), made }
    }

    /// What the node holds now: the worker's count and the store's, read together from this task,
    /// the only one that moves a keyframe from the channel to the store.
    fn held(&self) -> Held {
        let made = *self.made.lock().unwrap_or_else(PoisonError::into_inner);
        let store = self.links.store.lock().unwrap_or_else(PoisonError::into_inner).bytes() as u64;
        Held { made: made.keyframes, store, in_flight: made.in_flight, loops: made.loops }
    }

    /// Logs the progress line and keeps what is held in the summary.
    fn progress(&mut self) {
        self.summary.held = self.held();
        info!(
            "robot {}: {} scans, {} keyframes ({})",
            self.robot, self.summary.frames, self.summary.keyframes, self.summary.held
        );
        for warning in self.summary.source_losses.warnings() {
            warn!("robot {}: {warning}", self.robot);
        }
    }

    /// Records one registered scan and publishes its keyframe, if any.
    async fn send(&mut self, scan: Registered) -> Result<(), NodeError> {
        let s = &mut self.summary;
        s.frames += 1;
        s.poses.push(scan.pose);
        s.stamps.push(scan.stamp);
        s.ground_truth.push(scan.ground_truth);
        s.odometry_ms.push(scan.odometry_ms);
        s.source_losses.add(&scan.losses);
        if let Some(ros2) = &self.links.ros2 {
            ros2.odometry(scan.stamp, &scan.pose).await;
        }
        if let Some(mut kf) = scan.keyframe {
            s.keyframe_poses.push(scan.pose);
            if let (Some(ros2), Some(cloud)) = (&self.links.ros2, kf.cloud.take()) {
                ros2.keyframe(scan.stamp, &scan.pose, &cloud).await;
            }
            self.publish(kf).await?;
        }
        let s = &mut self.summary;
        s.keyframe_of_scan.push(s.keyframe_poses.len().saturating_sub(1));
        if let Some(update) = scan.posegraph {
            self.publish_posegraph(update).await?;
        }
        if self.summary.frames.is_multiple_of(PROGRESS_EVERY) {
            self.progress();
        }
        Ok(())
    }

    /// Stores a keyframe (first, so a backfill request racing the publication finds it) and puts it.
    async fn publish(&mut self, kf: EncodedKeyframe) -> Result<(), NodeError> {
        if !self.matched {
            self.matched = true;
            self.await_subscriber().await;
        }
        let payload = ZBytes::from(kf.payload);
        let bytes = payload.len() as u64;
        self.made.lock().unwrap_or_else(PoisonError::into_inner).in_flight -= bytes;
        let evicted = self.links.store.lock().unwrap_or_else(PoisonError::into_inner).insert(kf.seq, payload.clone());
        if let Some(range) = evicted {
            warn!(
                "robot {}: keyframe store over its budget, evicted keyframes {}..={}",
                self.robot,
                range.start(),
                range.end()
            );
        }
        let key = self.links.publisher.key_expr();
        self.links.publisher.put(payload).await.map_err(zenoh_error("publish on", key.as_str()))?;
        self.summary.keyframes += 1;
        self.summary.published_bytes += bytes;
        Ok(())
    }

    /// Keeps the update for late askers (first, as keyframes are stored first) and puts it.
    async fn publish_posegraph(&mut self, update: EncodedPoseGraph) -> Result<(), NodeError> {
        let payload = ZBytes::from(update.payload);
        *self.links.latest_posegraph.lock().unwrap_or_else(PoisonError::into_inner) = Some(payload.clone());
        let key = self.links.posegraph.key_expr();
        self.links.posegraph.put(payload).await.map_err(zenoh_error("publish on", key.as_str()))?;
        self.summary.posegraph_revision = update.revision;
        self.summary.loops = update.loops;
        self.summary.optimised_keyframes = update.poses;
        info!("robot {}: pose graph revision {}, {} loops", self.robot, update.revision, self.summary.loops);
        Ok(())
    }

    /// Waits (a bounded time) for a subscriber so that the first keyframes are not sent into the void;
    /// whatever is missed anyway the station backfills.
    async fn await_subscriber(&self) {
        let publisher = &self.links.publisher;
        let deadline = tokio::time::Instant::now() + MATCH_PATIENCE;
        loop {
            match publisher.matching_status().await {
                Ok(status) if status.matching() => return,
                Ok(_) => {}
                Err(e) => {
                    warn!("robot {}: cannot ask for subscribers: {e}", self.robot);
                    return;
                }
            }
            if tokio::time::Instant::now() >= deadline {
                info!("robot {}: no subscriber yet, publishing anyway", self.robot);
                return;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}
