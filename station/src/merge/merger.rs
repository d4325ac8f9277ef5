//! The incremental merger: per-map preparations cached by generation, pair verdicts by the
//! generations of their two maps, links tracked instead of searched again, and a bounded amount of
//! global registration per round of estimation.
//!
//! Robots send map updates one at a time; recomputing all N(N-1)/2 pairs for each would waste most
//! of the station's time on pairs that did not change. A map that only grows ([`Merger::grow`]) is
//! prepared again once it has grown by [`MergeConfig::refresh_growth`]; until then its newest
//! points enter the global map at the placement found on the last preparation. When a preparation
//! changes, a linked pair is tracked from its last transform ([`super::track_pair`], VGICP: tens of
//! milliseconds) and searched again by global registration only when tracking fails its checks or
//! a map has grown by [`MergeConfig::reverify_growth`] since the link was found; pairs never linked
//! are searched at most [`MergeConfig::max_searches`] per round, those likeliest to place an unplaced
//! map first (a placed and an unplaced map whose places look alike), the longest-waiting first
//! among equals.
//!
//! That estimation is a [`Round`]: planned from the merger's state ([`Merger::plan`]), run on its
//! own ([`Round::run`], no access to the merger) and taken back ([`Merger::apply`]). The global
//! map is composed from the placements found so far ([`Merger::compose`]), so a service can
//! publish fresh maps every second while a round takes several; [`Merger::merge`] runs the steps
//! one after the other.

use std::collections::BTreeMap;
use std::sync::Arc;

use cloud::PointCloud;
use cloud::memory::HeapSize;
use cloud::stopwatch::{Stopwatch, timed};
use cloud::visibility::Views;
use rustc_hash::{FxHashMap, FxHashSet};

use super::assembly::{Assembly, Placed};
use super::graph::{self, Chained, GraphEdge};
use super::places::Places;
use super::round::{CachedPair, Compared, Preparation, RoundMap, usable_pairs};
pub use super::round::{MergerStats, Round, RoundTiming};
use super::{
    MapReport, MapStatus, MergeConfig, MergeError, MergeReport, MergeTiming, PairRejection, PairReport, PairVerdict,
    PreparedMap, Unmerged,
};

/// One map slot: its newest cloud and the preparation pairs are estimated on.
struct Slot {
    revision: u64,
    /// The newest cloud, finite points only: what the global map is built from.
    cloud: Arc<PointCloud>,
    dropped_non_finite: usize,
    /// The preparation: of this revision, or of an earlier one while the map only grew.
    prepared: Option<Preparation>,
    /// The map changed other than by growing since it was prepared.
    reshaped: bool,
    /// Bumped whenever the map changes other than by growing (the global map takes it anew).
    shape: u64,
    /// What the map's sensor saw, if given: taken into the next preparation.
    views: Option<Arc<Views>>,
    /// Its keyframes' place descriptors, if given.
    places: Option<Arc<Places>>,
}

/// What the last round applied left for the merges after it.
#[derive(Clone, Debug, Default)]
struct LastRound {
    /// Grown maps and pairs it left for a later round.
    pending: usize,
    /// It settled and left nothing pending.
    settled: bool,
    /// The merger's change counter when it was planned.
    changes: u64,
    /// Pairs (ids) it computed, until a merge has reported them.
    fresh: FxHashSet<(usize, usize)>,
    /// Its timing, until a merge has reported it.
    timing: Option<RoundTiming>,
}

/// Merges maps that change over time, recomputing only what a change affects.
pub struct Merger {
    config: MergeConfig,
    maps: BTreeMap<usize, Slot>,
    pairs: FxHashMap<(usize, usize), CachedPair>,
    stats: MergerStats,
    next_generation: u64,
    /// The next round settles (see [`Merger::settle`]).
    settling: bool,
    /// Ids of the maps the last merge placed in the global map.
    merged: FxHashSet<usize>,
    /// The global map, kept between merges.
    assembly: Assembly,
    /// Per pair of map ids, how much of their places was compared, and whether a candidate was found.
    compared: FxHashMap<(usize, usize), Compared>,
    /// Bumped at every change of a map (set, removed): a round settles only the maps it saw.
    changes: u64,
    /// A round is out ([`Merger::plan`]) and not yet applied.
    out: bool,
    last: LastRound,
    /// Pairs of map ids (lower first) that are sessions of one robot ([`Merger::relate`]).
    kin: FxHashSet<(usize, usize)>,
}

impl Merger {
    /// An empty merger; fails on an invalid configuration.
    pub fn new(config: MergeConfig) -> Result<Self, MergeError> {
        config.validate()?;
        Ok(Self {
            maps: BTreeMap::new(),
            pairs: FxHashMap::default(),
            stats: MergerStats::default(),
            next_generation: 1,
            settling: false,
            merged: FxHashSet::default(),
            assembly: Assembly::new(config.output_voxel),
            compared: FxHashMap::default(),
            changes: 0,
            out: false,
            last: LastRound::default(),
            kin: FxHashSet::default(),
            config,
        })
    }

    /// The settings.
    pub fn config(&self) -> &MergeConfig {
        &self.config
    }

    /// Work done so far.
    pub fn stats(&self) -> MergerStats {
        self.stats
    }

    /// Sets map `id` to `cloud` at `revision`, a map of any shape: it is prepared again by the
    /// next round. A revision already held is ignored.
    pub fn update(&mut self, id: usize, revision: u64, cloud: PointCloud) {
        if !self.holds(id, revision) {
            self.set(id, revision, cloud, true);
        }
    }

    /// Sets map `id` to `cloud` at `revision` even when that revision is held: the same map built
    /// again (its points in another order, see [`Merger::grow`]). Prepared again by the next round.
    pub fn rebuild(&mut self, id: usize, revision: u64, cloud: PointCloud) {
        self.set(id, revision, cloud, true);
    }

    /// Map `id` as last given, if held.
    pub fn cloud_of(&self, id: usize) -> Option<&PointCloud> {
        self.maps.get(&id).map(|slot| slot.cloud.as_ref())
    }

    fn holds(&self, id: usize, revision: u64) -> bool {
        self.maps.get(&id).is_some_and(|s| s.revision == revision)
    }

    /// Sets map `id` to `cloud` at `revision`, a map that holds everything the previous revision
    /// held and more (a robot's map gaining keyframes): prepared again only once it has grown by
    /// [`MergeConfig::refresh_growth`]. A revision already held is ignored.
    ///
    /// The previous revision's points must come first, in their order (as a [`cloud::voxel::VoxelMap`]
    /// gives them): the global map takes only the points after them. They may have moved a little
    /// (a voxel's centroid as points join it); the global map keeps them where they were until the
    /// map's placement or shape changes.
    pub fn grow(&mut self, id: usize, revision: u64, cloud: PointCloud) {
        if !self.holds(id, revision) {
            self.set(id, revision, cloud, false);
        }
    }

    fn set(&mut self, id: usize, revision: u64, mut cloud: PointCloud, reshaped: bool) {
        self.changes += 1;
        let dropped_non_finite = cloud.retain_finite();
        let cloud = Arc::new(cloud);
        match self.maps.get_mut(&id) {
            Some(slot) => {
                *slot = Slot {
                    revision,
                    cloud,
                    dropped_non_finite,
                    prepared: slot.prepared.take(),
                    reshaped: slot.reshaped || reshaped,
                    shape: slot.shape + u64::from(reshaped),
                    views: slot.views.take(),
                    places: slot.places.take(),
                }
            }
            None => {
                let slot = Slot {
                    revision,
                    cloud,
                    dropped_non_finite,
                    prepared: None,
                    reshaped: false,
                    // Unique: a round planned before the map was removed and set again must not
                    // take this map for the one it prepared.
                    shape: self.changes,
                    views: None,
                    places: None,
                };
                self.maps.insert(id, slot);
            }
        }
    }

    /// Gives map `id` (set before) the views its sensor saw, in the frame of its current cloud: the
    /// free-space check of [`super::estimate_pair`] uses them from the map's next preparation on. A
    /// map without views is merged without that check.
    pub fn set_views(&mut self, id: usize, views: Arc<Views>) {
        if let Some(slot) = self.maps.get_mut(&id) {
            slot.views = Some(views);
        }
    }

    /// Gives map `id` (set before) its keyframes' place descriptors, in the order the keyframes
    /// came (a map's places only grow: what was compared once is not compared again). A settling
    /// merge searches a pair of placed maps that both have places only when some keyframe of one
    /// looks like some keyframe of the other ([`super::places`]); a map without places is searched
    /// with every other.
    pub fn set_places(&mut self, id: usize, places: Option<Arc<Places>>) {
        if let Some(slot) = self.maps.get_mut(&id) {
            slot.places = places;
        }
    }

    /// Says that maps `a` and `b` are sessions of one robot (it restarted in between): while one of
    /// them is not placed, their pair is searched before every other, since a robot usually starts
    /// again where it stopped.
    pub fn relate(&mut self, a: usize, b: usize) {
        if a != b {
            self.kin.insert((a.min(b), a.max(b)));
        }
    }

    /// Makes the next round exact rather than quick, for when the robots have gone quiet: every
    /// map that grew at all is prepared again and every pair whose maps changed, or whose edge was
    /// tracked, is searched again with every check (still at most [`MergeConfig::max_refreshes`]
    /// maps and [`MergeConfig::max_searches`] searches per round; the report's `pending` says
    /// when more settling merges are needed). A fleet at rest thus gets the placements a
    /// from-scratch merge of its final maps would give, except that a link the new search does
    /// not find again is kept when it still passes its checks ([`super::keep_link`]).
    pub fn settle(&mut self) {
        self.settling = true;
    }

    /// Takes back a [`Merger::settle`] no round has taken yet: the robots stream again.
    pub fn unsettle(&mut self) {
        self.settling = false;
    }

    /// Bytes the merger holds for map `id`: its newest cloud, its preparation and its part of the
    /// global map (`None` for a map it does not hold).
    pub fn heap_bytes_of(&self, id: usize) -> Option<usize> {
        let slot = self.maps.get(&id)?;
        let prepared = slot.prepared.as_ref().map_or(0, |p| p.map.heap_bytes());
        Some(slot.cloud.heap_bytes() + prepared + self.assembly.heap_bytes_of(id))
    }

    /// Forgets map `id` and its pairs.
    pub fn remove(&mut self, id: usize) {
        self.changes += 1;
        self.maps.remove(&id);
        self.pairs.retain(|&(a, b), _| a != id && b != id);
        self.compared.retain(|&(a, b), _| a != id && b != id);
        self.kin.retain(|&(a, b)| a != id && b != id);
    }

    /// Merges the current revisions of all maps: a round of estimation ([`Merger::plan`],
    /// [`Round::run`], [`Merger::apply`]) and then the global map ([`Merger::compose`]). A
    /// service that must publish while a round runs calls those steps itself.
    pub fn merge(&mut self) -> Result<MergeReport, MergeError> {
        let watch = Stopwatch::start();
        if let Some(mut round) = self.plan() {
            round.run();
            self.apply(round);
        }
        let mut report = self.compose()?;
        report.timing.total = watch.elapsed();
        Ok(report)
    }

    /// The next round of estimation, with everything it works on; `None` while another round is
    /// out, or when running one would change nothing (then a settle asked for is done at once).
    /// At most one round is out at a time: [`Merger::apply`] or [`Merger::abandon`] it.
    pub fn plan(&mut self) -> Option<Round> {
        if self.out {
            return None;
        }
        let maps = self
            .maps
            .iter()
            .map(|(&id, slot)| {
                let map = RoundMap {
                    cloud: Arc::clone(&slot.cloud),
                    views: slot.views.clone(),
                    places: slot.places.clone(),
                    prepared: slot.prepared.clone(),
                    reshaped: slot.reshaped,
                    shape: slot.shape,
                };
                (id, map)
            })
            .collect();
        let round = Round {
            config: self.config.clone(),
            number: self.stats.rounds as u64 + 1,
            settling: self.settling,
            changes: self.changes,
            merged: self.merged.clone(),
            maps,
            pairs: self.pairs.clone(),
            compared: self.compared.clone(),
            kin: self.kin.clone(),
            next_generation: self.next_generation,
            prepared: Vec::new(),
            done: FxHashSet::default(),
            pending: 0,
            stats: MergerStats::default(),
            timing: RoundTiming::default(),
            ran: false,
        };
        if round.idle() {
            // Nothing is pending when nothing needs doing.
            self.last.pending = 0;
            if std::mem::take(&mut self.settling) {
                self.last.settled = true;
                self.last.changes = self.changes;
            }
            return None;
        }
        self.settling = false;
        self.out = true;
        Some(round)
    }

    /// Takes a round's results (running it first if it has not run): the preparations it made,
    /// the verdicts it found, the places it compared. Maps removed since it was planned are
    /// skipped; a map whose shape changed since keeps the preparation but is prepared again by the
    /// next round.
    pub fn apply(&mut self, mut round: Round) {
        round.run();
        self.out = false;
        for id in &round.prepared {
            let (Some(slot), Some(map)) = (self.maps.get_mut(id), round.maps.get_mut(id)) else { continue };
            slot.prepared = map.prepared.take();
            slot.reshaped = slot.shape != map.shape;
        }
        self.next_generation = self.next_generation.max(round.next_generation);
        let held = |&(a, b): &(usize, usize)| self.maps.contains_key(&a) && self.maps.contains_key(&b);
        for key in round.done.iter().filter(|k| held(k)) {
            if let Some(pair) = round.pairs.remove(key) {
                self.pairs.insert(*key, pair);
            }
        }
        for (key, compared) in round.compared.into_iter().filter(|(k, _)| held(k)) {
            self.compared.insert(key, compared);
        }
        self.stats += round.stats;
        let fresh = round.done.into_iter().filter(|k| held(k)).collect();
        let settled = round.settling && round.pending == 0 && round.changes == self.changes;
        self.last =
            LastRound { pending: round.pending, settled, changes: round.changes, fresh, timing: Some(round.timing) };
    }

    /// Forgets the round that is out (it failed): the next [`Merger::plan`] plans it again.
    pub fn abandon(&mut self) {
        self.out = false;
    }

    /// The global map of the current maps at the placements the rounds applied so far found (a
    /// map not yet prepared waits, unmerged): paper eq. 11, a fraction of a second.
    pub fn compose(&mut self) -> Result<MergeReport, MergeError> {
        let watch = Stopwatch::start();
        self.stats.merges += 1;
        let ids: Vec<usize> = self.maps.keys().copied().collect();
        let prepared: Vec<Option<Arc<PreparedMap>>> =
            self.maps.values().map(|s| s.prepared.as_ref().map(|p| Arc::clone(&p.map))).collect();
        let reference = self.reference_position(&ids, &prepared)?;
        let pairs = self.pair_reports(&ids, &prepared);
        let (layout, graph) = timed(|| layout(&prepared, &pairs, reference));
        let maps = self.map_reports(&ids, &prepared, &pairs, &layout.chained);
        let ((global_map, origins), assemble) = timed(|| self.assemble(&maps));
        let round = self.last.timing.take().unwrap_or_default();
        let timing = MergeTiming {
            features: round.features,
            pairs: round.pairs,
            places: round.places,
            graph,
            assemble,
            total: watch.elapsed(),
        };
        let unchanged = self.last.changes == self.changes;
        let settled = self.last.settled && unchanged && !self.out;
        self.merged = maps.iter().filter(|m| m.is_merged()).map(|m| m.id).collect();
        Ok(MergeReport {
            maps,
            pairs,
            reference: layout.root,
            tree: layout.tree,
            global_map,
            origins,
            timing,
            pending: self.last.pending,
            settled,
        })
    }

    /// True while a round is out.
    pub fn estimating(&self) -> bool {
        self.out
    }

    /// The position of the configured reference map, checked: `Waiting` while it is not prepared.
    fn reference_position(
        &self,
        ids: &[usize],
        prepared: &[Option<Arc<PreparedMap>>],
    ) -> Result<Reference, MergeError> {
        let Some(reference) = self.config.reference else { return Ok(Reference::Centre) };
        let pos = ids
            .iter()
            .position(|&id| id == reference)
            .ok_or(MergeError::NoSuchReference { reference, maps: ids.len() })?;
        match prepared[pos].as_deref().map(|p| &p.features) {
            None => Ok(Reference::Waiting),
            Some(Ok(_)) => Ok(Reference::Map(pos)),
            Some(Err(reason)) => Err(MergeError::UnusableReference { reference, reason: reason.clone() }),
        }
    }

    /// Every pair of usable maps with its verdict (positions renumbered to `ids`), marked fresh
    /// when the round applied last computed it and no merge has reported it yet.
    fn pair_reports(&mut self, ids: &[usize], prepared: &[Option<Arc<PreparedMap>>]) -> Vec<PairReport> {
        let usable = |p: usize| prepared[p].as_ref().is_some_and(|m| m.usable().is_some());
        let fresh = std::mem::take(&mut self.last.fresh);
        let pending = PairVerdict::Rejected { reason: PairRejection::Pending, best: None, best_transform: None };
        usable_pairs(ids.len(), usable)
            .into_iter()
            .map(|(a, b)| {
                let key = (ids[a], ids[b]);
                let verdict = self.pairs.get(&key).map_or(&pending, |c| &c.verdict);
                PairReport { a, b, verdict: with_positions(verdict, a, b), cached: !fresh.contains(&key) }
            })
            .collect()
    }

    /// Paper eq. 11: the union of the merged maps in the global frame, voxelised to fuse
    /// duplicates (kept between merges, see [`Assembly`]); with each point's map id.
    fn assemble(&mut self, maps: &[MapReport]) -> (PointCloud, Vec<usize>) {
        let placed: Vec<Placed<'_>> = maps
            .iter()
            .filter(|m| m.is_merged())
            .map(|m| {
                let slot = &self.maps[&m.id];
                Placed { id: m.id, cloud: &slot.cloud, shape: slot.shape, transform: m.transform() }
            })
            .collect();
        self.assembly.update(&placed)
    }

    /// Per-map reports from the chained tree.
    fn map_reports(
        &self,
        ids: &[usize],
        prepared: &[Option<Arc<PreparedMap>>],
        pairs: &[PairReport],
        chained: &[Option<Chained>],
    ) -> Vec<MapReport> {
        (0..ids.len())
            .map(|p| {
                let slot = &self.maps[&ids[p]];
                MapReport {
                    id: ids[p],
                    revision: slot.revision,
                    points: slot.cloud.len(),
                    dropped_non_finite: slot.dropped_non_finite,
                    status: status(p, prepared[p].as_deref(), pairs, chained[p].as_ref()),
                }
            })
            .collect()
    }
}

/// Which map the global frame is: a configured one, one still waiting for its preparation (then no
/// map is placed yet), or the tree centre.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Reference {
    Map(usize),
    Waiting,
    Centre,
}

/// A cached verdict with its edge renumbered to the current map positions (maps may have been
/// added or removed since it was computed).
fn with_positions(verdict: &PairVerdict, a: usize, b: usize) -> PairVerdict {
    match verdict {
        PairVerdict::Edge(e) => PairVerdict::Edge(super::Edge { a, b, ..e.clone() }),
        rejected => rejected.clone(),
    }
}

/// The spanning tree, its root and every map's chained transform.
struct Layout {
    root: Option<usize>,
    tree: Vec<(usize, usize)>,
    chained: Vec<Option<Chained>>,
}

/// Builds the match graph from the accepted edges and chains the reference component's tree.
fn layout(prepared: &[Option<Arc<PreparedMap>>], pairs: &[PairReport], reference: Reference) -> Layout {
    let n = prepared.len();
    let nothing = || Layout { root: None, tree: Vec::new(), chained: vec![None; n] };
    let edges: Vec<GraphEdge> = pairs
        .iter()
        .filter_map(|p| p.verdict.edge())
        .map(|e| GraphEdge { a: e.a, b: e.b, transform: e.transform, weight: e.confidence.score })
        .collect();
    let forest = graph::maximum_spanning_forest(n, &edges);
    let components = graph::components(n, &edges, &forest);
    let usable = |p: usize| prepared[p].as_ref().is_some_and(|m| m.usable().is_some());
    // Without a configured reference: the largest component among usable maps (an unusable or
    // unprepared map is a component of one and must not win a tie against a usable one).
    let (component, reference) = match reference {
        Reference::Waiting => return nothing(),
        Reference::Map(r) => (components.iter().find(|c| c.contains(&r)), Some(r)),
        Reference::Centre => (components.iter().find(|c| usable(c[0])), None),
    };
    let Some(component) = component else { return nothing() };
    let tree: Vec<usize> = forest.into_iter().filter(|&i| component.contains(&edges[i].a)).collect();
    let root = reference.or_else(|| graph::tree_centre(n, &edges, &tree, component)).expect("non-empty component");
    let chained = graph::chain(n, &edges, &tree, root);
    Layout { root: Some(root), tree: tree.iter().map(|&i| (edges[i].a, edges[i].b)).collect(), chained }
}

/// Where map `p` ended up, and why (`map`: its preparation, `None` while it waits for one).
fn status(p: usize, map: Option<&PreparedMap>, pairs: &[PairReport], chained: Option<&Chained>) -> MapStatus {
    let Some(map) = map else { return MapStatus::Unmerged(Unmerged::Waiting) };
    if let Err(e) = &map.features {
        return MapStatus::Unmerged(Unmerged::Unusable(e.clone()));
    }
    if let Some(c) = chained {
        return MapStatus::Merged { transform: c.transform, confidence: c.weakest.min(1.0), hops: c.hops };
    }
    let has_edge = pairs.iter().any(|q| (q.a == p || q.b == p) && q.verdict.edge().is_some());
    MapStatus::Unmerged(if has_edge { Unmerged::OtherComponent } else { Unmerged::NoOverlap })
}
