//! One merge job, run on a blocking thread: each robot's local map from its keyframes and latest
//! poses, the long-lived [`Merger`] over them, and the `GlobalMap` message of the result. The
//! merger's rounds of estimation run beside the jobs ([`super::estimator`]): a job applies the
//! round that finished, starts the next, and composes the global map from the placements found
//! so far.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use cloud::PointCloud;
use cloud::memory::{HeapSize, map_bytes, vec_bytes};
use cloud::scan_context::Comparable;
use cloud::visibility::{RangeImage, View, Views, VisibilityConfig};
use cloud::voxel::VoxelMap;
use nalgebra::{Isometry3, Point3};
use prost::Message;
use proto::codec::{self, CodecConfig};
use proto::{CompressedCloud, Fleet, GlobalMap, MergeEdge, MergeStatus, RobotPlacement, Timestamp};
use rayon::prelude::*;
use rustc_hash::{FxHashMap, FxHashSet};

use super::estimator::{Estimator, Notify};
use super::fleet_state::{Basis, FleetState, Member};
use super::ingest;
use crate::merge::places::{Place, Places};
use crate::merge::{MergeConfig, MergeError, MergeReport, Merger, PairVerdict, RoundTiming};

/// One robot session's input to a job: its keyframe clouds with their poses, at one map revision.
#[derive(Clone, Debug)]
pub struct RobotSnapshot {
    /// Robot id.
    pub robot: u32,
    /// The robot's session: each session is a map of its own.
    pub session: u64,
    /// The robot's map revision.
    pub revision: u64,
    /// Keyframe clouds (sensor frame) and the poses that move them into the robot's odometry frame.
    pub keyframes: Vec<PlacedKeyframe>,
    /// What this snapshot is built from.
    pub basis: Basis,
}

/// A keyframe and its best pose.
#[derive(Clone, Debug)]
pub struct PlacedKeyframe {
    /// Sequence number.
    pub seq: u64,
    /// The keyframe as received: its cloud, in the sensor frame, is decoded when the job needs it
    /// (see [`super::fleet_state`]).
    pub bytes: Arc<[u8]>,
    /// Moves the cloud into the robot's odometry frame.
    pub pose: Isometry3<f64>,
}

impl RobotSnapshot {
    /// The robot session it is of.
    pub fn member(&self) -> Member {
        Member::new(self.robot, self.session)
    }
}

/// Snapshots of every robot session, cheap to take (payloads are shared).
pub fn snapshot(state: &FleetState) -> Vec<RobotSnapshot> {
    state
        .robots()
        .iter()
        .map(|(&member, r)| RobotSnapshot {
            robot: member.robot,
            session: member.session,
            revision: r.revision(),
            keyframes: r
                .keyframes()
                .iter()
                .filter_map(|(&seq, kf)| Some(PlacedKeyframe { seq, bytes: Arc::clone(&kf.bytes), pose: r.pose(seq)? }))
                .collect(),
            basis: r.basis(),
        })
        .collect()
}

/// What a job produced.
#[derive(Clone, Debug)]
pub struct MergeOutcome {
    /// The message to publish.
    pub map: GlobalMap,
    /// Its protobuf encoding, exactly what is published and persisted.
    pub bytes: Vec<u8>,
    /// Per robot session, what its map was built from.
    pub basis: BTreeMap<Member, Basis>,
    /// Wall time of the job.
    pub elapsed: Duration,
    /// The round of estimation this job applied, if one had finished: its wall time.
    pub round: Option<Duration>,
    /// A round of estimation is running: the station is called back when it finishes.
    pub estimating: bool,
    /// The global map's points as merged, before the codec, with their robots (for the live view).
    pub cloud: MapCloud,
    /// Per robot session, the bytes the merge keeps for it between jobs (see [`MergeWorker::memory`]).
    pub memory: BTreeMap<Member, u64>,
}

/// The global map's points with the robot each came from.
#[derive(Clone, Debug, Default)]
pub struct MapCloud {
    /// The points, in the global frame.
    pub cloud: PointCloud,
    /// Per point, its robot.
    pub robots: Vec<u32>,
    /// Per point, its robot's session (ids beyond `u32::MAX` saturate).
    pub sessions: Vec<u32>,
}

// Map ids hold a robot id and a session's rank (see `MapIds`).
const _: () = assert!(usize::BITS >= 64);

/// The merger's map id of each robot session: the robot id in the high 32 bits, the session's rank
/// among the robot's sessions (as first given) in the low ones. Maps keep the order of their robot
/// ids (the merger breaks ties by id), and a fleet without restarts orders as it always did.
#[derive(Default)]
struct MapIds {
    ids: BTreeMap<Member, usize>,
    members: FxHashMap<usize, Member>,
}

impl MapIds {
    /// The id of `member`, given one the first time.
    fn id(&mut self, member: Member) -> usize {
        if let Some(&id) = self.ids.get(&member) {
            return id;
        }
        let rank = self.ids.range(Member::new(member.robot, 0)..=Member::new(member.robot, u64::MAX)).count();
        let id = ((member.robot as usize) << 32) | rank;
        self.ids.insert(member, id);
        self.members.insert(id, member);
        id
    }

    /// The map id of the session of `member`'s robot just before it, if it has one.
    fn previous(&self, member: Member) -> Option<usize> {
        self.ids.range(Member::new(member.robot, 0)..member).next_back().map(|(_, &id)| id)
    }

    /// The robot session of map `id` (ids come from [`MapIds::id`]).
    fn member(&self, id: usize) -> Member {
        self.members.get(&id).copied().unwrap_or_default()
    }
}

/// One robot's local map as the worker built it: grown keyframe by keyframe while the poses stay.
struct LocalMap {
    /// Map revision last given to the merger.
    revision: u64,
    /// The pose-graph revision the poses came from.
    pose_revision: Option<u64>,
    /// Keyframes already in `map`.
    included: FxHashSet<u64>,
    /// Every keyframe went in after those of lower sequence numbers. A map grown out of order (a
    /// gap filled by backfill, a restarted station's store) holds the same voxels in another
    /// order, with other rounding of their centroids, and the search finds a slightly different
    /// placement: a settling merge rebuilds it in order ([`RobotState::update`]).
    in_order: bool,
    /// Highest sequence number in `map`.
    newest: Option<u64>,
    map: VoxelMap,
}

/// The merger and what it has been given, kept across jobs so that re-merges reuse its caches.
pub struct MergeWorker {
    merger: Merger,
    estimator: Estimator,
    /// Per robot session, what the jobs keep of it.
    robots: BTreeMap<Member, RobotState>,
    ids: MapIds,
    voxel: f32,
}

/// What the jobs keep of one robot session. Each robot's is brought up to its snapshot on its own, the
/// robots in parallel: adding new keyframes to the local maps one robot after the other took most
/// of a merge at 16 robots (each point a lookup in a grid of a few hundred thousand voxels).
#[derive(Default)]
struct RobotState {
    /// The local map given to the merger; `None` until the first snapshot.
    local: Option<LocalMap>,
    /// Each keyframe's range image (sensor frame: new poses only move it).
    images: BTreeMap<u64, Arc<RangeImage>>,
    /// Its keyframes' place descriptors (independent of poses).
    places: RobotPlaces,
}

/// A robot's local map brought up to its snapshot: what the merger is given for it.
struct Update {
    id: usize,
    revision: u64,
    cloud: PointCloud,
    /// Built anew (new poses, or put in order), not grown.
    rebuilt: bool,
    views: Views,
    places: Option<Arc<Places>>,
}

/// One robot's place descriptors, in the order its keyframes were first decoded.
#[derive(Default)]
struct RobotPlaces {
    described: Vec<Described>,
    /// The places given to the merger last: of how many keyframes, at which poses.
    given: Option<GivenPlaces>,
}

/// A keyframe's place descriptor.
struct Described {
    seq: u64,
    /// `None` for a keyframe that came without a usable descriptor.
    context: Option<Arc<Comparable>>,
}

/// Places given to the merger.
struct GivenPlaces {
    keyframes: usize,
    pose_revision: Option<u64>,
    places: Arc<Places>,
}

impl RobotPlaces {
    /// The robot's places at the snapshot's poses, when every keyframe has a descriptor (a map
    /// described in part could overlap another where it is not described).
    fn places(&mut self, r: &RobotSnapshot) -> Option<Arc<Places>> {
        if let Some(given) = &self.given
            && given.keyframes == self.described.len()
            && given.pose_revision == r.basis.pose_revision
        {
            return Some(Arc::clone(&given.places));
        }
        let positions: FxHashMap<u64, Point3<f32>> =
            r.keyframes.iter().map(|kf| (kf.seq, Point3::from(kf.pose.translation.vector.cast::<f32>()))).collect();
        let places: Vec<Place> = self
            .described
            .iter()
            .map(|d| Some(Place { context: Arc::clone(d.context.as_ref()?), position: *positions.get(&d.seq)? }))
            .collect::<Option<_>>()?;
        let places = Arc::new(Places::new(places));
        let pose_revision = r.basis.pose_revision;
        self.given = Some(GivenPlaces { keyframes: self.described.len(), pose_revision, places: Arc::clone(&places) });
        Some(places)
    }

    fn heap_bytes(&self) -> usize {
        let contexts: usize = self.described.iter().filter_map(|d| d.context.as_ref()).map(|c| c.heap_bytes()).sum();
        contexts + vec_bytes(&self.described) + self.given.as_ref().map_or(0, |g| g.places.index_bytes())
    }
}

impl MergeWorker {
    /// A worker with an empty merger; `notify` is called when a round of estimation finishes.
    pub fn new(config: MergeConfig, notify: Notify) -> Result<Self, MergeError> {
        let voxel = local_map_voxel(&config);
        let estimator = Estimator::new(notify).map_err(|e| MergeError::Threads(e.to_string()))?;
        Ok(Self { merger: Merger::new(config)?, estimator, robots: BTreeMap::new(), ids: MapIds::default(), voxel })
    }

    /// Merges the robots' current maps into global map `revision` of `fleet` at the placements
    /// found so far: applies the round of estimation that has finished, if one has, and starts the
    /// next; `settle` when the robots have gone quiet (see [`Merger::settle`]).
    pub fn run(
        &mut self,
        fleet: &Fleet,
        revision: u64,
        robots: &[RobotSnapshot],
        settle: bool,
    ) -> Result<MergeOutcome, MergeError> {
        let clock = Instant::now();
        self.give(robots, settle);
        let keyframes = clock.elapsed();
        if settle {
            self.merger.settle();
        } else {
            self.merger.unsettle();
        }
        let round = self.take_round();
        if !self.estimator.busy()
            && let Some(next) = self.merger.plan()
        {
            self.estimator.start(next);
        }
        let report = self.merger.compose()?;
        let message = Instant::now();
        let map = global_map(fleet, revision, &report, robots, &self.ids);
        let bytes = map.encode_to_vec();
        log_report(&report, &self.ids, round.as_ref(), keyframes, message.elapsed());
        let basis = robots.iter().map(|r| (r.member(), r.basis)).collect();
        let origins: Vec<Member> = report.origins.iter().map(|&id| self.ids.member(id)).collect();
        let cloud = MapCloud {
            robots: origins.iter().map(|m| m.robot).collect(),
            sessions: origins.iter().map(|m| u32::try_from(m.session).unwrap_or(u32::MAX)).collect(),
            cloud: report.global_map,
        };
        // A merge frees hundreds of megabytes of preparations, decoded keyframes and pair work on
        // rayon's threads; glibc keeps what each thread freed in its own arena until told.
        cloud::memory::release_free_memory();
        Ok(MergeOutcome {
            map,
            bytes,
            basis,
            elapsed: clock.elapsed(),
            round: round.map(|t| t.total),
            estimating: self.estimator.busy(),
            cloud,
            memory: self.memory(),
        })
    }

    /// True while a round of estimation runs or waits to be applied.
    pub fn estimating(&self) -> bool {
        self.estimator.busy()
    }

    /// Applies the round that has finished, if one has; its timing.
    fn take_round(&mut self) -> Option<RoundTiming> {
        match self.estimator.finished()? {
            Ok(round) => {
                let timing = round.timing();
                self.merger.apply(round);
                Some(timing)
            }
            Err(e) => {
                // Its maps and pairs are as they were: the next round takes them again.
                tracing::error!("round of estimation failed: {e}");
                self.merger.abandon();
                None
            }
        }
    }

    /// Brings every robot's local map up to its snapshot (the robots in parallel, see
    /// [`RobotState`]) and gives the merger the maps that changed.
    fn give(&mut self, robots: &[RobotSnapshot], settle: bool) {
        for r in robots {
            self.robots.entry(r.member()).or_default();
        }
        let snapshots: FxHashMap<Member, (&RobotSnapshot, usize)> =
            robots.iter().map(|r| (r.member(), (r, self.ids.id(r.member())))).collect();
        for r in robots {
            if let Some((previous, id)) = self.ids.previous(r.member()).zip(self.ids.ids.get(&r.member())) {
                self.merger.relate(previous, *id);
            }
        }
        let (voxel, visibility) = (self.voxel, &self.merger.config().visibility);
        let mut work: Vec<(&RobotSnapshot, usize, &mut RobotState)> = self
            .robots
            .iter_mut()
            .filter_map(|(member, state)| {
                let (r, id) = *snapshots.get(member)?;
                Some((r, id, state))
            })
            .collect();
        let updates: Vec<Update> =
            work.par_iter_mut().filter_map(|(r, id, state)| state.update(r, *id, settle, voxel, visibility)).collect();
        for u in updates {
            if u.rebuilt {
                // At the revision the merger holds when only the order changed.
                self.merger.rebuild(u.id, u.revision, u.cloud);
            } else {
                self.merger.grow(u.id, u.revision, u.cloud);
            }
            self.merger.set_views(u.id, Arc::new(u.views));
            self.merger.set_places(u.id, u.places);
        }
    }

    /// Per robot session, the bytes kept for it between jobs: its local map, its keyframes' range
    /// images and place descriptors, and the merger's copy of its map with the map's preparation
    /// (features, Gaussians).
    pub fn memory(&self) -> BTreeMap<Member, u64> {
        self.robots
            .iter()
            .filter_map(|(&member, state)| {
                let local = state.local.as_ref()?;
                let images = state.images.values().map(|i| i.heap_bytes()).sum::<usize>()
                    + state.images.len() * std::mem::size_of::<(u64, Arc<RangeImage>)>();
                let merger = self.ids.ids.get(&member).and_then(|&id| self.merger.heap_bytes_of(id)).unwrap_or(0);
                let included = map_bytes::<u64, ()>(local.included.capacity());
                let places = state.places.heap_bytes();
                Some((member, (local.map.heap_bytes() + included + images + places + merger) as u64))
            })
            .collect()
    }
}

impl RobotState {
    /// Brings the local map up to snapshot `r`: new keyframes are added to it (the map grows); new
    /// poses rebuild it (the map changes shape), and so does a `settle` of a map that grew out of
    /// order: a fleet at rest gets the map its keyframes give in sequence order, whatever order
    /// the network brought them in. `None` when the merger already holds this revision.
    fn update(
        &mut self,
        r: &RobotSnapshot,
        id: usize,
        settle: bool,
        voxel: f32,
        visibility: &VisibilityConfig,
    ) -> Option<Update> {
        let current =
            self.local.as_ref().filter(|m| m.pose_revision == r.basis.pose_revision && (m.in_order || !settle));
        if current.is_some_and(|m| m.revision == r.revision) {
            return None;
        }
        let rebuilt = current.is_none();
        if rebuilt {
            self.local = Some(LocalMap {
                revision: 0,
                pose_revision: r.basis.pose_revision,
                included: FxHashSet::default(),
                in_order: true,
                newest: None,
                map: VoxelMap::new(voxel).expect("local_map_voxel is validated positive"),
            });
        }
        let local = self.local.as_mut().expect("set above");
        let (images, places) = (&mut self.images, &mut self.places);
        let missing: Vec<&PlacedKeyframe> = r
            .keyframes
            .iter()
            .filter(|kf| !local.included.contains(&kf.seq) || !images.contains_key(&kf.seq))
            .collect();
        // A piece at a time: a rebuild at new poses decodes every keyframe of the robot.
        for piece in missing.chunks(DECODED_AT_ONCE) {
            for kf in decode(r.member(), piece, images, visibility) {
                if let Some(first) = kf.first {
                    images.insert(kf.seq, first.image);
                    places.described.push(Described { seq: kf.seq, context: first.context });
                }
                if local.included.insert(kf.seq) {
                    local.in_order &= local.newest.is_none_or(|n| kf.seq > n);
                    local.newest = local.newest.max(Some(kf.seq));
                    let pose = kf.pose.cast::<f32>();
                    local.map.insert(kf.cloud.points.iter().map(|p| pose * p));
                }
            }
        }
        local.revision = r.revision;
        let cloud = local.map.cloud();
        if settle {
            tracing::debug!(
                "{}: settling on a map of {} keyframes, {} points{}, digest {:016x}",
                r.member(),
                local.included.len(),
                cloud.len(),
                if rebuilt { ", rebuilt" } else { "" },
                digest(&cloud)
            );
        }
        let places = places.places(r);
        Some(Update { id, revision: r.revision, cloud, rebuilt, views: self.views(r), places })
    }

    /// The robot's keyframes as its sensor saw them, at the snapshot's poses.
    fn views(&self, r: &RobotSnapshot) -> Views {
        let views = r
            .keyframes
            .iter()
            .filter_map(|kf| Some(View { pose: kf.pose.cast::<f32>(), image: Arc::clone(self.images.get(&kf.seq)?) }))
            .collect();
        Views::new(views)
    }
}

/// A keyframe decoded for the job, with what is made of it once when it is decoded the first time.
struct Decoded {
    seq: u64,
    pose: Isometry3<f64>,
    cloud: PointCloud,
    first: Option<FirstDecode>,
}

/// What is kept of a keyframe from its first decode (sensor frame: new poses do not change it).
struct FirstDecode {
    image: Arc<RangeImage>,
    /// Its place descriptor, laid out for comparing; `None` without a usable one.
    context: Option<Arc<Comparable>>,
}

/// Keyframes decoded together: enough to keep the cores busy, few enough that their points (about
/// 144 kB each) stay a few megabytes while a robot's whole map is rebuilt.
const DECODED_AT_ONCE: usize = 64;

/// Decodes `keyframes` of `robot` (a session) in parallel and, for those without a range image yet, makes it
/// and lays out their place descriptors (once per keyframe: in the sensor frame, new poses only
/// move them). A keyframe that no longer decodes (it
/// passed the checks when it arrived) is logged and left out.
fn decode(
    robot: Member,
    keyframes: &[&PlacedKeyframe],
    images: &BTreeMap<u64, Arc<RangeImage>>,
    config: &VisibilityConfig,
) -> Vec<Decoded> {
    keyframes
        .par_iter()
        .filter_map(|kf| match ingest::held_keyframe(&kf.bytes) {
            Ok(held) => {
                let first = (!images.contains_key(&kf.seq)).then(|| FirstDecode {
                    image: Arc::new(RangeImage::new(&held.cloud.points, config)),
                    context: match held.context {
                        Some(Ok(c)) => Some(Arc::new(Comparable::new(&c))),
                        Some(Err(e)) => {
                            tracing::warn!(
                                "{robot} keyframe {}: unusable scan context ({e}); the robot's map is searched against every other",
                                kf.seq
                            );
                            None
                        }
                        None => None,
                    },
                });
                Some(Decoded { seq: kf.seq, pose: kf.pose, cloud: held.cloud, first })
            }
            Err(e) => {
                tracing::error!("{robot} keyframe {} no longer decodes, left out of its map: {e}", kf.seq);
                None
            }
        })
        .collect()
}

/// A digest of a map's points (their bits, in order): two stations' logs tell whether they merged
/// the same map.
fn digest(cloud: &PointCloud) -> u64 {
    use std::hash::{Hash, Hasher};
    let mut hasher = rustc_hash::FxHasher::default();
    for p in &cloud.points {
        p.coords.iter().for_each(|c| c.to_bits().hash(&mut hasher));
    }
    hasher.finish()
}

/// Why pairs were refused and where the time went: what an operator needs when a robot stays out.
/// `keyframes` is the time spent bringing the robots' local maps up to their snapshots,
/// `message` the time spent making and encoding the published message.
fn log_report(report: &MergeReport, ids: &MapIds, round: Option<&RoundTiming>, keyframes: Duration, message: Duration) {
    let id = |position: usize| ids.member(report.maps[position].id);
    for pair in report.pairs.iter().filter(|p| !p.cached) {
        match &pair.verdict {
            PairVerdict::Edge(e) => tracing::info!(
                "{} and {}: edge{}, confidence {:.3}, {} inliers, acceptance {}; placement ({:.2}, {:.2}, {:.2}) m, yaw {:.1} deg",
                id(pair.a),
                id(pair.b),
                match (e.tracked, e.around) {
                    (true, _) => " (tracked)",
                    (false, true) => " (found around a place candidate)",
                    (false, false) => "",
                },
                e.confidence.score,
                e.inliers,
                e.acceptance.map_or("unchecked".to_string(), |a| a.to_string()),
                e.transform.translation.x,
                e.transform.translation.y,
                e.transform.translation.z,
                e.transform.rotation.euler_angles().2.to_degrees()
            ),
            PairVerdict::Rejected { reason, best_transform: Some(t), .. } => {
                // Where the best candidate would have put the robot: with the truth at hand (a
                // simulation, a surveyed start) it tells a wrong look-alike from a refused true link.
                let (x, y, z) = (t.translation.x, t.translation.y, t.translation.z);
                let yaw = t.rotation.euler_angles().2.to_degrees();
                tracing::info!(
                    "{} and {}: no edge ({reason}); best placement ({x:.2}, {y:.2}, {z:.2}) m, yaw {yaw:.1} deg",
                    id(pair.a),
                    id(pair.b)
                )
            }
            PairVerdict::Rejected { reason, best_transform: None, .. } => {
                tracing::info!("{} and {}: no edge ({reason})", id(pair.a), id(pair.b))
            }
        }
    }
    let t = &report.timing;
    let ms = cloud::stopwatch::millis;
    if let Some(r) = round {
        tracing::info!(
            "round: features {:.0} ms, pairs {:.0} ms (places {:.0} ms), {:.0} ms in all",
            ms(r.features),
            ms(r.pairs),
            ms(r.places),
            ms(r.total)
        );
    }
    tracing::info!(
        "merge: keyframes {:.0} ms, graph {:.0} ms, assembly {:.0} ms, message {:.0} ms",
        ms(keyframes),
        ms(t.graph),
        ms(t.assemble),
        ms(message)
    );
}

/// The finest voxel any merge stage works at: coarser local maps would starve it, finer ones only
/// cost time (indoor 0.1 m; outdoor 0.2 m, the output voxel).
fn local_map_voxel(config: &MergeConfig) -> f32 {
    config.pairwise.global.preprocess.voxel_size.min(config.refine_voxel).min(config.output_voxel)
}

/// The `GlobalMap` message of a merge report: one placement per robot session.
fn global_map(fleet: &Fleet, revision: u64, report: &MergeReport, robots: &[RobotSnapshot], ids: &MapIds) -> GlobalMap {
    let keyframes: BTreeMap<Member, u64> = robots.iter().map(|r| (r.member(), r.keyframes.len() as u64)).collect();
    let member_of = |position: usize| ids.member(report.maps[position].id);
    let placements = report
        .maps
        .iter()
        .map(|m| {
            let member = ids.member(m.id);
            RobotPlacement {
                robot: member.robot,
                transform: Some(m.transform().into()),
                confidence: m.confidence(),
                status: if m.is_merged() { MergeStatus::Merged } else { MergeStatus::Unmerged } as i32,
                keyframes: keyframes.get(&member).copied().unwrap_or(0),
                session: member.session,
            }
        })
        .collect();
    let edges = report
        .edges()
        .filter(|e| report.tree.contains(&(e.a, e.b)) || report.tree.contains(&(e.b, e.a)))
        .map(|e| {
            let (a, b) = (member_of(e.a), member_of(e.b));
            MergeEdge {
                robot_a: a.robot,
                robot_b: b.robot,
                transform: Some(e.transform.into()),
                confidence: e.confidence.score,
                inliers: e.inliers as u64,
                session_a: a.session,
                session_b: b.session,
            }
        })
        .collect();
    let reference = report.reference.map(member_of).unwrap_or_default();
    GlobalMap {
        fleet: fleet.to_string(),
        revision,
        reference_robot: reference.robot,
        reference_session: reference.session,
        robots: placements,
        edges,
        cloud: Some(compress(&report.global_map)),
        stamp: Some(Timestamp::now()),
        settled: report.settled,
    }
}

/// The global map through the codec; reordered, since a voxelised map has no sensor order to keep.
fn compress(cloud: &PointCloud) -> CompressedCloud {
    let config = CodecConfig { reorder: true, ..CodecConfig::default() };
    match codec::encode(cloud, &config) {
        Ok(data) => CompressedCloud { data: data.into(), points: cloud.len() as u64 },
        Err(e) => {
            // Only a point beyond 2^31 mm (2000 km) can fail: publish the placements without a cloud.
            tracing::error!("cannot encode the global map: {e}");
            CompressedCloud::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Point3;
    use proto::{Keyframe, Pose};

    use super::*;

    const ROBOT: u32 = 1;

    /// Keyframe `seq`: the floor all keyframes see and a wall post of its own `seq` metres along x,
    /// so that keyframes share voxels and each adds some.
    fn placed(seq: u64) -> PlacedKeyframe {
        let pose = Isometry3::identity();
        let grid = |n: usize| (0..n).map(|i| i as f32 * 0.13);
        let mut points = Vec::new();
        for a in grid(40) {
            for b in grid(20) {
                points.extend([Point3::new(seq as f32 + 0.05, a - 2.0, b), Point3::new(a, b - 1.3, -1.0)]);
            }
        }
        let cloud = PointCloud::from_points(points);
        let data = codec::encode(&cloud, &CodecConfig::default()).unwrap();
        let msg = Keyframe {
            fleet: "order".into(),
            robot: ROBOT,
            seq,
            stamp: Some(Timestamp::from_secs_f64(seq as f64)),
            odom_pose: Some(Pose::from(pose)),
            scan_context: None,
            cloud: Some(CompressedCloud { data: data.into(), points: cloud.len() as u64 }),
            session: 0,
        };
        PlacedKeyframe { seq, bytes: msg.encode_to_vec().into(), pose }
    }

    /// The robot's snapshot holding keyframes `seqs` (its revision counts them).
    fn snapshot_of(seqs: &[u64]) -> RobotSnapshot {
        RobotSnapshot {
            robot: ROBOT,
            session: 0,
            revision: seqs.len() as u64,
            keyframes: seqs.iter().map(|&s| placed(s)).collect(),
            basis: Basis { keyframes: seqs.len() as u64, pose_revision: None },
        }
    }

    /// The robot's local map, checked to be what the merger holds.
    fn local_map(worker: &MergeWorker) -> Vec<Point3<f32>> {
        let member = Member::from(ROBOT);
        let points = worker.robots[&member].local.as_ref().expect("given").map.cloud().points;
        let given = worker.merger.cloud_of(worker.ids.ids[&member]).expect("the merger holds the map");
        assert!(given.points == points, "the merger holds another map than the local one");
        points
    }

    #[test]
    fn a_settled_map_is_the_one_its_keyframes_give_in_order_whatever_order_they_came_in() {
        let worker = || MergeWorker::new(MergeConfig::default(), Arc::new(|| {})).unwrap();
        let all = [0, 1, 2, 3];
        let mut ordered = worker();
        ordered.give(&[snapshot_of(&all)], false);
        // A gap filled later, as backfill does: 2 comes after 3, 1 after both.
        let mut gapped = worker();
        gapped.give(&[snapshot_of(&[0, 3])], false);
        gapped.give(&[snapshot_of(&[0, 2, 3])], false);
        gapped.give(&[snapshot_of(&all)], false);
        assert!(local_map(&gapped) != local_map(&ordered), "the keyframes must fill voxels in another order");
        gapped.give(&[snapshot_of(&all)], true);
        assert!(local_map(&gapped) == local_map(&ordered), "the settled map is not the in-order one");
        // A map that grew in order is kept as it is by a settle, and stays the same.
        let in_order = |w: &MergeWorker| w.robots[&Member::from(ROBOT)].local.as_ref().is_some_and(|l| l.in_order);
        assert!(in_order(&ordered) && in_order(&gapped));
        ordered.give(&[snapshot_of(&all)], true);
        assert!(local_map(&gapped) == local_map(&ordered), "a settle changed a map that grew in order");
    }
}
