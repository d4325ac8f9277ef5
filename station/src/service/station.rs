//! The station's event loop: one task owns the state and reacts to samples, liveliness changes,
//! backfill replies, global-map queries, the merge timer and finished merge jobs.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::mpsc::Sender;
use std::time::{Duration, Instant};

use prost::Message;
use proto::{Fleet, GlobalMap, KeyframeRequest, StationStatus, Timestamp, Topic, keyexpr};
use tokio::sync::{mpsc, oneshot, watch};
use tokio::task::{JoinError, JoinHandle};
use tracing::{debug, error, info, warn};
use zenoh::Session;
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::CongestionControl;
use zenoh::query::{ConsolidationMode, Query, Queryable};
use zenoh::sample::{Sample, SampleKind};

use super::backfill::{Backfill, Ended, Want};
use super::client::global_map_cloud;
use super::fleet_state::{Basis, FleetState, Inserted, Member, ReceivedKeyframe};
use super::ingest::{self, Malformed};
use super::live_view::StationView;
use super::merge_job::{MapCloud, MergeOutcome, MergeWorker, snapshot};
use super::merge_queue::MergeQueue;
use super::ros2_view::StationRos2;
use super::store::{self, Persisted, Store, Write};
use super::{RobotMemory, StationConfig, StationError, StationProgress, StationSummary};
use crate::merge::{MergeConfig, MergeError};

/// How long a backfill request waits for the robot's replies: a request that times out is made again
/// for what is still missing, but the replies of an expired query still cross the link (the robot
/// cannot know), so a short timeout on a slow link would pile stale replies in front of the new
/// ones. 30 s carries about 2 MB (30 keyframes) over a link left with 67 kB/s by 20 % loss.
const BACKFILL_TIMEOUT: Duration = Duration::from_secs(30);

/// How soon the same gaps may be asked for again.
const BACKFILL_RETRY: Duration = Duration::from_secs(2);

/// A running station.
pub struct Station {
    task: Option<JoinHandle<Result<StationSummary, StationError>>>,
    stop: Option<oneshot::Sender<()>>,
    progress: watch::Receiver<StationProgress>,
}

impl Station {
    /// Opens the database (if any), reloads it, declares the station's Zenoh entities, publishes
    /// the persisted global map and starts the event loop.
    pub async fn start(session: Session, config: StationConfig) -> Result<Station, StationError> {
        let (events_tx, events) = mpsc::unbounded_channel();
        let worker = new_worker(&config.merge, &events_tx)?;
        let (store, persisted) = open_store(&config).await?;
        let (progress_tx, progress) = watch::channel(StationProgress::default());
        let progress_tx = Arc::new(progress_tx);
        let writer = store.map(|s| spawn_writer(s, &progress_tx));
        let fleet = config.fleet.clone();
        let reloaded = tokio::task::spawn_blocking(move || reload(&fleet, persisted))
            .await
            .map_err(|e| StationError::Task(e.to_string()))?;
        let endpoints = Endpoints::declare(&session, &config.fleet).await?;
        let ros2 = match config.ros2_domain {
            Some(domain) => Some(StationRos2::declare(&session, &config.fleet, domain).await?),
            None => None,
        };
        let mut core = Core::new(session, &config, worker, writer, progress_tx, events_tx, reloaded);
        core.ros2 = ros2;
        core.publish_reloaded(&endpoints).await;
        let (stop, stopped) = oneshot::channel();
        let status_period = config.status_period;
        let task = tokio::spawn(async move {
            let stopped = async {
                let _ = stopped.await;
            };
            core.run(endpoints, events, status_period, stopped).await
        });
        Ok(Station { task: Some(task), stop: Some(stop), progress })
    }

    /// A receiver of the station's progress; e.g. wait with
    /// `rx.wait_for(|p| p.total_keyframes() == n && p.up_to_date())`.
    pub fn progress(&self) -> watch::Receiver<StationProgress> {
        self.progress.clone()
    }

    /// Stops the station: ends the loop, commits the last database batch and returns the summary.
    pub async fn stop(mut self) -> Result<StationSummary, StationError> {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        let task = self.task.take().expect("the task is only taken by stop and kill");
        task.await.map_err(|e| StationError::Task(e.to_string()))?
    }

    /// Stops the station the hard way, as `kill -9` would, as far as one process can: the loop is
    /// cancelled wherever it is; only the database batch already handed to the writer is committed.
    pub async fn kill(mut self) {
        if let Some(task) = self.task.take() {
            task.abort();
            let _ = task.await;
        }
    }
}

impl Drop for Station {
    fn drop(&mut self) {
        if let Some(task) = &self.task {
            task.abort();
        }
    }
}

async fn open_store(config: &StationConfig) -> Result<(Option<Store>, Persisted), StationError> {
    let Some(dir) = config.data_dir.clone() else { return Ok((None, Persisted::default())) };
    let (store, persisted) = tokio::task::spawn_blocking(move || -> Result<_, StationError> {
        let store = Store::open(&dir)?;
        let persisted = store.load()?;
        Ok((store, persisted))
    })
    .await
    .map_err(|e| StationError::Task(e.to_string()))??;
    let map = if persisted.global_map.is_some() { "a global map" } else { "no global map" };
    info!("{}: {} keyframes, {map}", store.path().display(), persisted.keyframes.len());
    Ok((Some(store), persisted))
}

fn spawn_writer(store: Store, progress: &Arc<watch::Sender<StationProgress>>) -> WriterHandle {
    let progress = Arc::clone(progress);
    let (tx, thread) = store::spawn_writer(store, move |c| progress.send_modify(|p| p.committed = c));
    WriterHandle { tx, thread }
}

/// The writer thread and its channel.
struct WriterHandle {
    tx: Sender<Write>,
    thread: std::thread::JoinHandle<()>,
}

/// The state rebuilt from the database.
#[derive(Default)]
struct Reloaded {
    state: FleetState,
    latest: Option<Published>,
    basis: BTreeMap<Member, Basis>,
    /// Persisted records that no longer pass the checks (skipped).
    rejected: u64,
}

/// A published global map and its bytes as published.
struct Published {
    map: GlobalMap,
    bytes: Arc<[u8]>,
}

/// Rebuilds the state through the same checks and inserts as live samples.
fn reload(fleet: &Fleet, persisted: Persisted) -> Reloaded {
    let mut out = Reloaded { basis: persisted.basis, ..Reloaded::default() };
    for (member, seq, bytes) in persisted.keyframes {
        let origin = format!("{} keyframe {seq} of {member}", store::FILE_NAME);
        match ingest::keyframe(fleet, member.robot, &origin, &bytes) {
            Ok(kf) => {
                out.state.insert_keyframe(&kf);
            }
            Err(e) => reject(&mut out.rejected, &e),
        }
    }
    for (member, bytes) in persisted.posegraphs {
        let origin = format!("{} pose graph of {member}", store::FILE_NAME);
        match ingest::poses(fleet, member.robot, &origin, &bytes) {
            Ok(p) => {
                out.state.apply_poses(p.member(), p.revision, p.poses);
            }
            Err(e) => reject(&mut out.rejected, &e),
        }
    }
    out.latest = persisted.global_map.and_then(|bytes| match GlobalMap::decode(bytes.as_slice()) {
        Ok(map) => Some(Published { map, bytes: bytes.into() }),
        Err(e) => {
            warn!("{}: the stored global map does not decode ({e}); a new one will be merged", store::FILE_NAME);
            None
        }
    });
    out
}

fn reject(count: &mut u64, e: &Malformed) {
    warn!("{e}");
    *count += 1;
}

/// The station's Zenoh entities.
struct Endpoints {
    robots: Subscriber<FifoChannelHandler<Sample>>,
    alive: Subscriber<FifoChannelHandler<Sample>>,
    queries: Queryable<FifoChannelHandler<Query>>,
    global_map: Publisher<'static>,
    status: Publisher<'static>,
}

impl Endpoints {
    async fn declare(session: &Session, fleet: &Fleet) -> Result<Endpoints, StationError> {
        let z = |e: zenoh::Error| StationError::Zenoh(e.to_string());
        let map_key = keyexpr::global_map(fleet);
        Ok(Endpoints {
            robots: session.declare_subscriber(keyexpr::all_robots(fleet)).await.map_err(z)?,
            // history: robots already alive are reported at once, as a liveliness get would.
            alive: session.liveliness().declare_subscriber(keyexpr::all_alive(fleet)).history(true).await.map_err(z)?,
            queries: session.declare_queryable(map_key.clone()).await.map_err(z)?,
            global_map: session
                .declare_publisher(map_key)
                .congestion_control(CongestionControl::Block)
                .await
                .map_err(z)?,
            status: session.declare_publisher(keyexpr::station_status(fleet)).await.map_err(z)?,
        })
    }
}

/// Messages from the station's helper tasks to its loop.
enum Event {
    /// A reply to a backfill request to `robot`: a keyframe, or the robot's newest pose graph.
    Reply { robot: u32, sample: Box<Sample> },
    /// The backfill request to `robot` has ended, as said.
    BackfillDone { robot: u32, ended: Ended },
    /// A round of estimation has finished: the next merge job applies it.
    Estimated,
}

/// Where a keyframe came from.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Origin {
    Live,
    Backfill,
}

/// A merge worker whose finished rounds of estimation call for a merge.
fn new_worker(config: &MergeConfig, events: &mpsc::UnboundedSender<Event>) -> Result<MergeWorker, MergeError> {
    let events = events.clone();
    MergeWorker::new(config.clone(), Arc::new(move || drop(events.send(Event::Estimated))))
}

/// The result of a merge job, with the worker handed back.
type JobResult = (MergeWorker, Result<MergeOutcome, MergeError>);

/// Counters beyond the state.
#[derive(Default)]
struct Counters {
    malformed: u64,
    backfilled: u64,
    backfill_requests: u64,
    merges: u64,
    merge_ms: Vec<f64>,
    round_ms: Vec<f64>,
    /// Per robot session, the merge's bytes as of the last merge.
    map_memory: BTreeMap<Member, u64>,
}

/// Everything the loop owns.
struct Core {
    session: Session,
    fleet: Fleet,
    merge_config: MergeConfig,
    state: FleetState,
    queue: MergeQueue,
    backfill: Backfill,
    /// The merger, `None` while a job has it.
    worker: Option<MergeWorker>,
    /// The last merge job left a round of estimation running.
    estimating: bool,
    latest: Option<Published>,
    next_revision: u64,
    counters: Counters,
    writer: Option<WriterHandle>,
    progress: Arc<watch::Sender<StationProgress>>,
    events: mpsc::UnboundedSender<Event>,
    /// The live view, when one is configured.
    view: Option<StationView>,
    /// The ROS 2 topics, when asked for.
    ros2: Option<StationRos2>,
}

impl Core {
    fn new(
        session: Session,
        config: &StationConfig,
        worker: MergeWorker,
        writer: Option<WriterHandle>,
        progress: Arc<watch::Sender<StationProgress>>,
        events: mpsc::UnboundedSender<Event>,
        reloaded: Reloaded,
    ) -> Core {
        let mut queue = MergeQueue::new(config.debounce, config.max_delay);
        // Re-merge only when the state differs from what the persisted map was built from, or that
        // map was merged while robots streamed (not settled).
        let settled = reloaded.latest.as_ref().is_some_and(|l| l.map.settled);
        let current = settled && reloaded.basis == reloaded.state.basis();
        if !current && reloaded.state.total_keyframes() > 0 {
            queue.changed(Instant::now());
        }
        Core {
            session,
            fleet: config.fleet.clone(),
            merge_config: config.merge.clone(),
            next_revision: reloaded.latest.as_ref().map_or(1, |p| p.map.revision + 1),
            state: reloaded.state,
            queue,
            backfill: Backfill::new(BACKFILL_RETRY),
            worker: Some(worker),
            estimating: false,
            latest: reloaded.latest,
            counters: Counters { malformed: reloaded.rejected, ..Counters::default() },
            writer,
            progress,
            events,
            view: config.live.clone().map(StationView::new),
            ros2: None,
        }
    }

    /// Publishes the persisted global map at once, same revision and bytes, for late joiners.
    async fn publish_reloaded(&mut self, endpoints: &Endpoints) {
        if let Some(p) = &self.latest {
            info!("serving persisted global map revision {}", p.map.revision);
            if let Err(e) = endpoints.global_map.put(p.bytes.to_vec()).await {
                warn!("cannot publish the global map: {e}");
            }
            if self.view.is_some() || self.ros2.is_some() {
                // Which robot each point came from is not persisted: the reloaded map has no labels.
                let cloud =
                    MapCloud { cloud: global_map_cloud(&p.map).unwrap_or_default(), robots: vec![], sessions: vec![] };
                if let Some(view) = &self.view {
                    view.map(&p.map, &cloud, &self.state);
                }
                if let Some(ros2) = &mut self.ros2 {
                    ros2.map(&p.map, &cloud, &self.state).await;
                }
            }
        }
        self.report_progress();
    }

    async fn run(
        mut self,
        endpoints: Endpoints,
        mut events: mpsc::UnboundedReceiver<Event>,
        status_period: Duration,
        stopped: impl Future<Output = ()>,
    ) -> Result<StationSummary, StationError> {
        let mut status = tokio::time::interval(status_period);
        status.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut job: Option<JoinHandle<JobResult>> = None;
        tokio::pin!(stopped);
        loop {
            let deadline = self.queue.deadline().map(tokio::time::Instant::from_std);
            tokio::select! {
                () = &mut stopped => break,
                sample = endpoints.robots.recv_async() => match sample {
                    Ok(s) => self.on_robot_sample(&s),
                    Err(_) => break,
                },
                Ok(sample) = endpoints.alive.recv_async() => self.on_liveliness(&sample),
                Ok(query) = endpoints.queries.recv_async() => self.answer(&query).await,
                Some(event) = events.recv() => self.on_event(event),
                _ = status.tick() => {
                    self.backfill.recheck(&self.state);
                    self.publish_status(&endpoints.status).await;
                }
                () = sleep_until(deadline), if deadline.is_some() => job = self.start_merge(),
                joined = join(&mut job), if job.is_some() => {
                    job = None;
                    self.finish_merge(joined, &endpoints.global_map).await;
                }
            }
            self.send_backfills();
            self.report_progress();
        }
        Ok(self.shut_down().await)
    }

    fn on_robot_sample(&mut self, sample: &Sample) {
        let key = sample.key_expr().as_str();
        let bytes = sample.payload().to_bytes();
        match Topic::parse(key) {
            Some(Topic::Keyframe { robot, .. }) => self.on_keyframe(robot, key, &bytes, Origin::Live),
            Some(Topic::PoseGraph { robot, .. }) => self.on_poses(robot, key, &bytes),
            _ => debug!("ignoring a sample on {key}"),
        }
    }

    fn on_keyframe(&mut self, robot: u32, key: &str, bytes: &[u8], origin: Origin) {
        match ingest::keyframe(&self.fleet, robot, key, bytes) {
            Ok(kf) => self.insert(kf, origin),
            Err(e) => self.malformed(&e),
        }
    }

    fn insert(&mut self, kf: ReceivedKeyframe, origin: Origin) {
        let (member, seq, bytes) = (kf.member(), kf.seq, Arc::clone(&kf.bytes));
        let first = self.state.robot(member).is_none();
        match self.state.insert_keyframe(&kf) {
            Inserted::New => {
                if let Some(view) = &self.view {
                    view.keyframe(&kf, &self.state);
                }
                self.persist(Write::Keyframe { member, seq, bytes });
                self.queue.changed(Instant::now());
                if first {
                    self.new_session(member, origin);
                }
                if origin == Origin::Backfill {
                    self.counters.backfilled += 1;
                } else if self.state.robot(member).is_some_and(|r| r.missing_count() > 0) {
                    self.backfill.want(member, Want::Gaps);
                }
            }
            Inserted::Duplicate => debug!("{member} keyframe {seq} again"),
            Inserted::Conflict => warn!("{member} sent other bytes for keyframe {seq}: keeping the first"),
        }
    }

    /// A robot session seen for the first time. One that came through backfill (the reply to which
    /// session the robot is in now) is asked for in full. The session before it ended without a
    /// word, perhaps in a crash: anything it published after what the station holds of it is asked
    /// for (a robot that keeps its keyframes on disk still has them).
    fn new_session(&mut self, member: Member, origin: Origin) {
        if origin == Origin::Backfill {
            self.backfill.want(member, Want::Everything);
        }
        if let Some(previous) = self.state.previous_session(member) {
            info!("{member}: a new session of robot {}, after {previous}", member.robot);
            self.backfill.want(previous, Want::Everything);
        }
    }

    fn on_poses(&mut self, robot: u32, key: &str, bytes: &[u8]) {
        match ingest::poses(&self.fleet, robot, key, bytes) {
            Ok(p) => {
                let member = p.member();
                if self.state.apply_poses(member, p.revision, p.poses) {
                    self.persist(Write::PoseGraph { member, bytes: Arc::from(bytes) });
                    self.queue.changed(Instant::now());
                    if let Some(view) = &mut self.view {
                        view.poses(member, p.loops, &self.state);
                    }
                }
            }
            Err(e) => self.malformed(&e),
        }
    }

    fn malformed(&mut self, e: &Malformed) {
        warn!("{e}");
        self.counters.malformed += 1;
    }

    fn on_liveliness(&mut self, sample: &Sample) {
        let key = sample.key_expr().as_str();
        let Some(Topic::Alive { robot, .. }) = Topic::parse(key) else {
            return debug!("ignoring liveliness of {key}");
        };
        match sample.kind() {
            SampleKind::Put => {
                info!("robot {robot} is alive");
                self.backfill.appeared(robot, &self.state);
            }
            SampleKind::Delete => info!("robot {robot} is gone"),
        }
    }

    /// Answers a global-map query with the latest map, or an error reply when there is none yet.
    async fn answer(&self, query: &Query) {
        let key = keyexpr::global_map(&self.fleet);
        let sent = match &self.latest {
            Some(p) => query.reply(key, p.bytes.to_vec()).await,
            None => query.reply_err("no global map yet").await,
        };
        if let Err(e) = sent {
            debug!("cannot answer a global-map query: {e}");
        }
    }

    fn on_event(&mut self, event: Event) {
        match event {
            Event::Reply { robot, sample } => {
                let (key, bytes) = (sample.key_expr().as_str(), sample.payload().to_bytes());
                match Topic::parse(key) {
                    Some(Topic::PoseGraph { .. }) => self.on_poses(robot, key, &bytes),
                    _ => self.on_keyframe(robot, key, &bytes, Origin::Backfill),
                }
            }
            Event::BackfillDone { robot, ended } => self.backfill.done(robot, ended, Instant::now()),
            Event::Estimated => self.queue.changed(Instant::now()),
        }
    }

    /// Sends the backfill requests that are due, each from its own task.
    fn send_backfills(&mut self) {
        for (robot, request) in self.backfill.requests(&self.state, Instant::now()) {
            debug!(
                "asking robot {robot} for {} keyframes, from {:?}, of session {:?}",
                request.seqs.len(),
                request.from_seq,
                request.session
            );
            self.counters.backfill_requests += 1;
            let key = keyexpr::keyframe_store(&self.fleet, robot);
            // A robot that (re)appeared may have optimised its graph while this station was not
            // listening: its newest update supersedes all earlier ones, so it is asked for too.
            if request.from_seq.is_some() {
                let posegraph = keyexpr::posegraph(&self.fleet, robot);
                tokio::spawn(fetch_posegraph(self.session.clone(), posegraph, robot, self.events.clone()));
            }
            tokio::spawn(fetch(self.session.clone(), key, robot, request, self.events.clone()));
        }
    }

    fn start_merge(&mut self) -> Option<JoinHandle<JobResult>> {
        let now = Instant::now();
        // Robots gone quiet: this merge may take the time to be exact (see `Merger::settle`).
        let quiet = self.queue.quiet(now);
        if !self.queue.start(now) {
            return None;
        }
        let mut worker = self.worker.take().expect("no job runs, so the worker is home");
        let robots = snapshot(&self.state);
        let (fleet, revision) = (self.fleet.clone(), self.next_revision);
        Some(tokio::task::spawn_blocking(move || {
            let outcome = worker.run(&fleet, revision, &robots, quiet);
            (worker, outcome)
        }))
    }

    async fn finish_merge(&mut self, joined: Result<JobResult, JoinError>, publisher: &Publisher<'static>) {
        self.queue.finished();
        match joined {
            Ok((worker, outcome)) => {
                self.estimating = worker.estimating();
                self.worker = Some(worker);
                match outcome {
                    Ok(outcome) => {
                        // Merged while robots streamed, or work left over (searches over the
                        // budget): merge again, changes or not, so that the fleet at rest gets a
                        // settled map (see `Merger::settle`). While a round of estimation runs,
                        // its end calls for the next merge.
                        if !outcome.map.settled && !outcome.estimating {
                            self.queue.changed(Instant::now());
                        }
                        self.publish_map(outcome, publisher).await
                    }
                    Err(e) => error!("merge failed: {e}"),
                }
            }
            Err(e) => {
                error!("merge job failed: {e}");
                self.estimating = false;
                self.worker = new_worker(&self.merge_config, &self.events).ok();
            }
        }
    }

    async fn publish_map(&mut self, outcome: MergeOutcome, publisher: &Publisher<'static>) {
        let MergeOutcome { map, bytes, basis, elapsed, round, cloud, memory, .. } = outcome;
        self.counters.map_memory = memory;
        let ms = cloud::stopwatch::millis(elapsed);
        let merged = map.robots.iter().filter(|r| r.status == proto::MergeStatus::Merged as i32).count();
        info!(
            "global map revision {}: {merged} of {} robot sessions merged ({ms:.0} ms)",
            map.revision,
            map.robots.len()
        );
        self.counters.merges += 1;
        self.counters.merge_ms.push(ms);
        self.counters.round_ms.extend(round.map(cloud::stopwatch::millis));
        self.next_revision = map.revision + 1;
        let bytes: Arc<[u8]> = bytes.into();
        // Committed before it is published: after a crash the station must never publish a
        // different map under a revision number its subscribers have already seen.
        self.persist(Write::GlobalMap { revision: map.revision, bytes: Arc::clone(&bytes), basis });
        self.await_committed(map.revision).await;
        if let Err(e) = publisher.put(bytes.to_vec()).await {
            warn!("cannot publish the global map: {e}");
        }
        if let Some(view) = &self.view {
            view.map(&map, &cloud, &self.state);
        }
        if let Some(ros2) = &mut self.ros2 {
            ros2.map(&map, &cloud, &self.state).await;
        }
        self.latest = Some(Published { map, bytes });
    }

    async fn publish_status(&self, publisher: &Publisher<'static>) {
        let status = StationStatus {
            fleet: self.fleet.to_string(),
            robots: self.state.keyframe_counts().into_keys().collect(),
            keyframes: self.state.total_keyframes() as u64,
            merge_queue_depth: self.queue.depth(),
            last_merge_ms: self.counters.merge_ms.last().copied().unwrap_or(0.0),
            estimating: self.estimating,
            last_round_ms: self.counters.round_ms.last().copied().unwrap_or(0.0),
            global_map_revision: self.revision(),
            malformed_payloads: self.counters.malformed,
            stamp: Some(Timestamp::now()),
            memory: self
                .memory()
                .into_iter()
                .map(|(robot, m)| proto::RobotMemory { robot, keyframe_bytes: m.keyframes, map_bytes: m.map })
                .collect(),
            sessions: self
                .state
                .robots()
                .iter()
                .map(|(m, r)| proto::SessionKeyframes {
                    robot: m.robot,
                    session: m.session,
                    keyframes: r.keyframes().len() as u64,
                    conflicts: r.conflicts(),
                })
                .collect(),
        };
        if let Some(view) = &self.view {
            view.status(&status, self.counters.merges);
        }
        if let Some(ros2) = &self.ros2 {
            ros2.status(&status).await;
        }
        if let Err(e) = publisher.put(status.encode_to_vec()).await {
            debug!("cannot publish the status: {e}");
        }
    }

    fn persist(&self, write: Write) {
        if let Some(w) = &self.writer
            && w.tx.send(write).is_err()
        {
            error!("the database writer has stopped: this write is kept in memory only");
        }
    }

    /// Waits (boundedly: a failing disk must not stop the maps) until the writer has committed
    /// global map `revision`; at once without a database.
    async fn await_committed(&self, revision: u64) {
        if self.writer.is_none() {
            return;
        }
        let mut progress = self.progress.subscribe();
        let committed = progress.wait_for(|p| p.committed.map_revision >= revision || p.committed.failures > 0);
        if tokio::time::timeout(Duration::from_secs(5), committed).await.is_err() {
            warn!("global map revision {revision} not committed after 5 s: publishing it anyway");
        }
    }

    fn revision(&self) -> u64 {
        self.latest.as_ref().map_or(0, |p| p.map.revision)
    }

    /// What the station holds per robot (over its sessions): its keyframes, and the merge's share
    /// as of the last merge.
    fn memory(&self) -> BTreeMap<u32, RobotMemory> {
        let mut memory = BTreeMap::<u32, RobotMemory>::new();
        for (member, r) in self.state.robots() {
            let m = memory.entry(member.robot).or_default();
            m.keyframes += r.keyframe_bytes();
            m.map += self.counters.map_memory.get(member).copied().unwrap_or(0);
        }
        memory
    }

    fn report_progress(&self) {
        let s = &self.state;
        let c = &self.counters;
        let keyframes = s.keyframe_counts();
        let sessions = s.session_counts();
        let session_pose_revisions: BTreeMap<Member, u64> =
            s.robots().iter().filter_map(|(&m, state)| Some((m, state.pose_revision()?))).collect();
        // A robot's newest session's: revisions count per session.
        let mut pose_revisions = BTreeMap::new();
        for (m, &revision) in &session_pose_revisions {
            if s.newest_session(m.robot) == Some(*m) {
                pose_revisions.insert(m.robot, revision);
            }
        }
        let missing = s.robots().values().map(|r| r.missing_count() as usize).sum();
        self.progress.send_if_modified(|p| {
            let next = StationProgress {
                keyframes,
                pose_revisions,
                sessions,
                session_pose_revisions,
                missing,
                malformed: c.malformed,
                conflicts: s.total_conflicts(),
                backfilled: c.backfilled,
                backfill_requests: c.backfill_requests,
                backfill_in_flight: self.backfill.in_flight(),
                merges: c.merges,
                revision: self.revision(),
                merge_pending: self.queue.depth() > 0,
                merge_running: self.queue.running(),
                estimating: self.estimating,
                memory: self.memory(),
                committed: p.committed,
            };
            let changed = *p != next;
            *p = next;
            changed
        });
    }

    /// Lets the writer commit its last batch and sums up.
    async fn shut_down(mut self) -> StationSummary {
        if let Some(WriterHandle { tx, thread }) = self.writer.take() {
            drop(tx);
            if tokio::task::spawn_blocking(move || thread.join()).await.is_err() {
                error!("the database writer failed while committing its last batch");
            }
        }
        StationSummary {
            global_map: self.latest.map(|p| p.map),
            keyframes: self.state.keyframe_counts(),
            sessions: self.state.session_counts(),
            fleet: super::merge_job::snapshot(&self.state),
            malformed: self.counters.malformed,
            conflicts: self.state.total_conflicts(),
            backfilled: self.counters.backfilled,
            merges: self.counters.merges,
            merge_ms: self.counters.merge_ms,
            round_ms: self.counters.round_ms,
        }
    }
}

/// How often a request that nobody answered is made (see [`ask_until_answered`]).
const FETCH_ATTEMPTS: usize = 5;
/// The pause before such a request is made again.
const FETCH_RETRY: Duration = Duration::from_millis(500);

/// What one query brought.
#[derive(Clone, Copy, Debug, Default)]
struct Asked {
    /// Replies, samples and errors.
    answers: usize,
    /// Replies that were samples (keyframes, for a keyframe request).
    keyframes: usize,
    /// An error reply came: the query timed out (zenoh's own reply then) or the robot refused it.
    failed: bool,
}

/// One query to a robot (its keyframe store with a `KeyframeRequest` payload, or its pose-graph
/// key with none); every reply goes to the loop.
async fn ask(
    session: &Session,
    key: &str,
    robot: u32,
    payload: Option<&[u8]>,
    events: &mpsc::UnboundedSender<Event>,
) -> Asked {
    // No consolidation: every reply is a distinct keyframe, possibly on the same key.
    let mut get = session.get(key).consolidation(ConsolidationMode::None).timeout(BACKFILL_TIMEOUT);
    if let Some(payload) = payload {
        get = get.payload(payload.to_vec());
    }
    let asked = get.await;
    let mut out = Asked::default();
    match asked {
        Ok(replies) => {
            while let Ok(reply) = replies.recv_async().await {
                out.answers += 1;
                match reply.result() {
                    Ok(sample) => {
                        out.keyframes += 1;
                        let _ = events.send(Event::Reply { robot, sample: Box::new(sample.clone()) });
                    }
                    Err(e) => {
                        out.failed = true;
                        debug!("robot {robot} on {key}: {:?}", e.payload().to_bytes());
                    }
                }
            }
        }
        Err(e) => {
            out.failed = true;
            warn!("cannot query {key}: {e}");
        }
    }
    out
}

/// [`ask`], made again a few times a moment later while nobody answers.
///
/// A robot's liveliness token and its queryables are declared separately and may reach this
/// session in either order: a query made on the token alone can find no queryable yet. (A robot
/// without a pose graph yet does not answer either, which cannot be told apart: it is asked
/// [`FETCH_ATTEMPTS`] times.)
async fn ask_until_answered(
    session: &Session,
    key: &str,
    robot: u32,
    payload: Option<&[u8]>,
    events: &mpsc::UnboundedSender<Event>,
) -> Asked {
    let mut asked = Asked::default();
    for attempt in 1..=FETCH_ATTEMPTS {
        asked = ask(session, key, robot, payload, events).await;
        if asked.answers > 0 || attempt == FETCH_ATTEMPTS {
            break;
        }
        tokio::time::sleep(FETCH_RETRY).await;
    }
    asked
}

/// Asks a robot for its newest pose graph; the reply goes to the loop.
async fn fetch_posegraph(session: Session, key: String, robot: u32, events: mpsc::UnboundedSender<Event>) {
    ask_until_answered(&session, &key, robot, None, &events).await;
}

/// Sleeps until `deadline` (forever when there is none).
async fn sleep_until(deadline: Option<tokio::time::Instant>) {
    match deadline {
        Some(d) => tokio::time::sleep_until(d).await,
        None => std::future::pending().await,
    }
}

/// Waits for the running job (forever when there is none).
async fn join(job: &mut Option<JoinHandle<JobResult>>) -> Result<JobResult, JoinError> {
    match job {
        Some(j) => j.await,
        None => std::future::pending().await,
    }
}

/// Asks a robot's keyframe store and forwards every reply to the loop; a request for everything is
/// made again while nobody answers (see [`ask_until_answered`]).
async fn fetch(
    session: Session,
    key: String,
    robot: u32,
    request: KeyframeRequest,
    events: mpsc::UnboundedSender<Event>,
) {
    let payload = request.encode_to_vec();
    let asked = if request.from_seq.is_some() {
        ask_until_answered(&session, &key, robot, Some(&payload), &events).await
    } else {
        ask(&session, &key, robot, Some(&payload), &events).await
    };
    let full = request.limit.is_some_and(|limit| asked.keyframes >= limit as usize);
    let ended = match (asked.failed, full) {
        (true, _) => Ended::TimedOut,
        (false, true) => Ended::Full,
        (false, false) => Ended::Complete,
    };
    let _ = events.send(Event::BackfillDone { robot, ended });
}
