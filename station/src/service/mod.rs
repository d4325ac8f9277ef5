//! The networked station (`emr-station run`): collects every robot's keyframes and poses over Zenoh,
//! merges their maps off the async runtime and publishes the global map and its own status.
//!
//! - [`fleet_state`]: keyframes by sequence number and latest poses per robot; idempotent inserts.
//! - [`ingest`]: payload checks (a malformed payload is counted and logged, never fatal).
//! - [`backfill`]: which keyframes to ask a robot's keyframe store for, one request at a time.
//! - [`merge_queue`]: coalesced, debounced merge scheduling.
//! - [`merge_job`]: local maps, the long-lived merger and the `GlobalMap` message.
//! - [`estimator`]: the merger's rounds of estimation, on threads of their own beside the jobs.
//! - [`live_view`]: the live view and recording (`--foxglove`, `--record`), when one is given.
//! - [`ros2_view`]: the ROS 2 topics (`--ros2`), when asked for.
//! - [`store`]: persistence in redb, written in batches by a writer thread.
//! - [`station`]: the event loop tying them together; [`Station`] and [`run`] start it.
//! - [`client`]: what other processes use: fetching the global map, summarising samples.
//!
//! For an in-process station, [`Station::start`] returns a handle whose [`Station::progress`]
//! receiver tells when the station is idle; [`run`] is the same until a shutdown future resolves.

pub mod backfill;
pub mod client;
pub mod estimator;
pub mod fleet_state;
pub mod ingest;
pub mod joint_input;
pub mod live_view;
pub mod merge_job;
pub mod merge_queue;
pub mod ros2_view;
pub mod station;
pub mod store;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use live::Live;
use proto::{Fleet, GlobalMap};

use crate::merge::{MergeConfig, MergeError};
pub use fleet_state::Member;
pub use station::Station;
pub use store::{Committed, StoreError};

/// Everything `emr-station run` can be told.
#[derive(Clone, Debug)]
pub struct StationConfig {
    /// The fleet whose robots to collect.
    pub fleet: Fleet,
    /// Where the database lives (`DIR/station.redb`); `None` keeps everything in memory only.
    pub data_dir: Option<PathBuf>,
    /// The merge settings.
    pub merge: MergeConfig,
    /// Quiet time after the last change before a merge starts.
    pub debounce: Duration,
    /// Longest a change waits for its merge, however busy the robots are.
    pub max_delay: Duration,
    /// Period of the `StationStatus` messages.
    pub status_period: Duration,
    /// Where the live view goes (a Foxglove server, an MCAP recording); `None`: nowhere.
    pub live: Option<Arc<Live>>,
    /// The ROS domain to publish the station's ROS 2 topics in ([`ros2_view`]); `None`: none.
    pub ros2_domain: Option<u32>,
}

impl StationConfig {
    /// In-memory, outdoor merge preset (see `emr-station run --preset`), 1 s debounce, 2 s at most, status every second, no live view.
    pub fn new(fleet: Fleet) -> Self {
        Self {
            fleet,
            data_dir: None,
            merge: MergeConfig::outdoor(),
            debounce: Duration::from_secs(1),
            max_delay: Duration::from_secs(2),
            status_period: Duration::from_secs(1),
            live: None,
            ros2_domain: None,
        }
    }
}

/// Why the station could not start or stopped abnormally (nothing a robot sends causes this).
#[derive(Debug, thiserror::Error)]
pub enum StationError {
    /// The database could not be opened or read.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The merge settings are invalid.
    #[error(transparent)]
    Merge(#[from] MergeError),
    /// Zenoh refused a declaration.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// The ROS 2 topics could not be set up.
    #[error(transparent)]
    Ros2(#[from] ros2_view::StationRos2Error),
    /// The station's task panicked or was cancelled.
    #[error("station task: {0}")]
    Task(String),
}

/// Where the station stands: published on a watch channel after every event.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StationProgress {
    /// Keyframes held per robot, over its sessions.
    pub keyframes: BTreeMap<u32, usize>,
    /// Newest pose-graph revision accepted per robot, of its newest session (robots whose newest
    /// session sent none are absent).
    pub pose_revisions: BTreeMap<u32, u64>,
    /// Keyframes held per robot session.
    pub sessions: BTreeMap<Member, usize>,
    /// Newest pose-graph revision accepted per robot session (sessions that sent none are absent).
    pub session_pose_revisions: BTreeMap<Member, u64>,
    /// Keyframes known to be missing (gaps below each robot's newest), over all robots.
    pub missing: usize,
    /// Payloads rejected since start.
    pub malformed: u64,
    /// Keyframes that came again in the same session with different bytes (the first were kept).
    pub conflicts: u64,
    /// Keyframes received through backfill requests.
    pub backfilled: u64,
    /// Backfill requests sent.
    pub backfill_requests: u64,
    /// Backfill requests outstanding.
    pub backfill_in_flight: usize,
    /// Merges published since start.
    pub merges: u64,
    /// Revision of the latest global map (0: none yet).
    pub revision: u64,
    /// A merge is waiting for its debounce.
    pub merge_pending: bool,
    /// A merge is running.
    pub merge_running: bool,
    /// A round of estimation is running (or finished and not yet applied by a merge).
    pub estimating: bool,
    /// What the station holds per robot.
    pub memory: BTreeMap<u32, RobotMemory>,
    /// What the database has committed (all zero without a data directory).
    pub committed: Committed,
}

/// What the station holds in memory for one robot, bytes, counted from its containers' capacities
/// (see [`cloud::memory::HeapSize`]). Both parts grow with what the robot has mapped, not with time
/// spent: a robot that stands still adds nothing.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RobotMemory {
    /// Its keyframes as received, every one kept (the merge rebuilds the robot's map from them
    /// when a pose-graph update moves them), decoded only while the merge needs their points.
    pub keyframes: u64,
    /// Its local map, its keyframes' range images and the merge's preparation of its map (features,
    /// Gaussians), as of the last merge.
    pub map: u64,
}

impl RobotMemory {
    /// Both parts.
    pub fn total(&self) -> u64 {
        self.keyframes + self.map
    }
}

impl StationProgress {
    /// Keyframes held over all robots.
    pub fn total_keyframes(&self) -> usize {
        self.keyframes.values().sum()
    }

    /// True when a global map is published and was built from everything held, with every
    /// estimate done: nothing pending, nothing running.
    pub fn up_to_date(&self) -> bool {
        self.revision > 0 && !self.merge_pending && !self.merge_running && !self.estimating
    }
}

/// What a station did, returned when it stops.
#[derive(Clone, Debug, Default)]
pub struct StationSummary {
    /// The latest global map, if any.
    pub global_map: Option<GlobalMap>,
    /// Keyframes held per robot, over its sessions.
    pub keyframes: BTreeMap<u32, usize>,
    /// Keyframes held per robot session.
    pub sessions: BTreeMap<Member, usize>,
    /// Every robot session's keyframes and newest poses as the station held them last (payloads shared).
    pub fleet: Vec<merge_job::RobotSnapshot>,
    /// Payloads rejected.
    pub malformed: u64,
    /// Conflicting keyframes.
    pub conflicts: u64,
    /// Keyframes received through backfill.
    pub backfilled: u64,
    /// Merges published by this run.
    pub merges: u64,
    /// Wall time of each merge, milliseconds.
    pub merge_ms: Vec<f64>,
    /// Wall time of each round of estimation the merges applied, milliseconds.
    pub round_ms: Vec<f64>,
}

/// Runs a station on `session` until `shutdown` resolves, then commits the last database batch.
pub async fn run(
    session: zenoh::Session,
    config: StationConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<StationSummary, StationError> {
    let station = Station::start(session, config).await?;
    shutdown.await;
    station.stop().await
}
