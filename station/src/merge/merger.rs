//! The incremental merger: per-map preparations cached by generation, pair verdicts by the
//! generations of their two maps, links tracked instead of searched again, and a bounded amount of
//! global registration per merge.
//!
//! Robots send map updates one at a time; recomputing all N(N-1)/2 pairs for each would waste most
//! of the station's time on pairs that did not change. A map that only grows ([`Merger::grow`]) is
//! prepared again once it has grown by [`MergeConfig::refresh_growth`]; until then its newest
//! points enter the global map at the placement found on the last preparation. When a preparation
//! changes, a linked pair is tracked from its last transform ([`track_pair`], VGICP: tens of
//! milliseconds) and searched again by global registration only when tracking fails its checks or
//! a map has grown by [`MergeConfig::reverify_growth`] since the link was found; pairs never linked
//! are searched at most [`MergeConfig::max_searches`] per merge, the longest-waiting first.

use std::collections::BTreeMap;
use std::sync::Arc;

use cloud::PointCloud;
use cloud::memory::HeapSize;
use cloud::stopwatch::{Stopwatch, timed};
use cloud::visibility::Views;
use rayon::prelude::*;
use rustc_hash::{FxHashMap, FxHashSet};

use super::assembly::{Assembly, Placed};
use super::graph::{self, Chained, GraphEdge};
use super::places::{Places, Since};
use super::{
    MapReport, MapStatus, MergeConfig, MergeError, MergeReport, MergeTiming, PairRejection, PairReport, PairVerdict,
    PreparedMap, Unmerged, estimate_pair, track_pair,
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

/// A map's preparation and what it was made from.
struct Preparation {
    map: Arc<PreparedMap>,
    /// Bumped at every preparation of the map; pair verdicts are cached against it.
    generation: u64,
}

impl Slot {
    /// Whether the next merge must prepare the map (new or reshaped), may (grown past
    /// `refresh_growth`, the growth it shows), or need not.
    fn staleness(&self, refresh_growth: f64) -> Staleness {
        match &self.prepared {
            None => Staleness::Required,
            Some(_) if self.reshaped => Staleness::Required,
            Some(p) => {
                let growth = self.cloud.len() as f64 / p.map.points.max(1) as f64 - 1.0;
                if growth >= refresh_growth { Staleness::Grown(growth) } else { Staleness::Fresh }
            }
        }
    }
}

enum Staleness {
    Required,
    Grown(f64),
    Fresh,
}

/// A pair verdict and what it was computed from.
struct CachedPair {
    /// Generations of the two maps' preparations.
    generations: (u64, u64),
    verdict: PairVerdict,
    /// Points of the two prepared maps when the last global registration ran.
    searched_at: (usize, usize),
    /// Merge counter of the last global registration: the longest-waiting pair is searched first.
    searched_in: u64,
}

/// How much work the merger has done since it was created.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MergerStats {
    /// Maps prepared (features and Gaussians).
    pub preparations: usize,
    /// Global registrations of pairs (searches).
    pub pair_estimates: usize,
    /// Linked pairs followed by VGICP from their last transform and kept.
    pub tracked: usize,
    /// Merges run.
    pub merges: usize,
    /// Searches not run because no place of either map looked like one of the other's.
    pub unmatched: usize,
}

/// Pairs of maps by their positions.
type Positions = Vec<(usize, usize)>;

/// What one pair needs this merge.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PairWork {
    /// Its cached verdict stands.
    Cached,
    /// Linked before: follow the link.
    Track,
    /// A global registration (or, over budget, wait).
    Search,
}

/// Merges maps that change over time, recomputing only what a change affects.
pub struct Merger {
    config: MergeConfig,
    maps: BTreeMap<usize, Slot>,
    pairs: FxHashMap<(usize, usize), CachedPair>,
    stats: MergerStats,
    next_generation: u64,
    /// The next merge settles (see [`Merger::settle`]).
    settling: bool,
    /// Ids of the maps the last merge placed in the global map.
    merged: FxHashSet<usize>,
    /// The global map, kept between merges.
    assembly: Assembly,
    /// Per pair of map ids, how much of their places was compared, and whether a candidate was found.
    compared: FxHashMap<(usize, usize), Compared>,
}

/// How far two maps' places were compared.
#[derive(Clone, Copy, Debug, Default)]
struct Compared {
    since: Since,
    found: bool,
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

    /// Sets map `id` to `cloud` at `revision`, a map of any shape: it is prepared again at the
    /// next merge. A revision already held is ignored.
    pub fn update(&mut self, id: usize, revision: u64, cloud: PointCloud) {
        self.set(id, revision, cloud, true);
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
        self.set(id, revision, cloud, false);
    }

    fn set(&mut self, id: usize, revision: u64, mut cloud: PointCloud, reshaped: bool) {
        if self.maps.get(&id).is_some_and(|s| s.revision == revision) {
            return;
        }
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
                    shape: 0,
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

    /// Makes the next merge exact rather than quick, for when the robots have gone quiet: every map
    /// that grew at all is prepared again and every pair whose maps changed, or whose edge was
    /// tracked, is searched again with every check (still at most [`MergeConfig::max_refreshes`]
    /// maps and [`MergeConfig::max_searches`] searches per merge; the report's `pending` says
    /// when more settling merges are needed). A fleet at rest thus gets the placements a
    /// from-scratch merge of its final maps would give.
    pub fn settle(&mut self) {
        self.settling = true;
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
        self.maps.remove(&id);
        self.pairs.retain(|&(a, b), _| a != id && b != id);
        self.compared.retain(|&(a, b), _| a != id && b != id);
    }

    /// Merges the current revisions of all maps.
    pub fn merge(&mut self) -> Result<MergeReport, MergeError> {
        let watch = Stopwatch::start();
        self.stats.merges += 1;
        let (deferred_maps, features) = timed(|| self.prepare_stale());
        let ids: Vec<usize> = self.maps.keys().copied().collect();
        let prepared: Vec<Arc<PreparedMap>> =
            self.maps.values().map(|s| Arc::clone(&s.prepared.as_ref().expect("all maps are prepared").map)).collect();
        let reference = self.reference_position(&ids, &prepared)?;
        let ((pairs, deferred_pairs, places), pairs_time) =
            timed(|| self.estimate_pairs(&ids, &prepared, &deferred_maps));
        let (layout, graph) = timed(|| layout(&prepared, &pairs, reference));
        let maps = self.map_reports(&ids, &prepared, &pairs, &layout.chained);
        let ((global_map, origins), assemble) = timed(|| self.assemble(&maps));
        let timing = MergeTiming { features, pairs: pairs_time, places, graph, assemble, total: watch.elapsed() };
        let pending = deferred_maps.len() + deferred_pairs;
        let settled = std::mem::take(&mut self.settling) && pending == 0;
        self.merged = maps.iter().filter(|m| m.is_merged()).map(|m| m.id).collect();
        Ok(MergeReport {
            maps,
            pairs,
            reference: layout.root,
            tree: layout.tree,
            global_map,
            origins,
            timing,
            pending,
            settled,
        })
    }

    /// Prepares, in parallel, every map that must be (new, reshaped) and up to
    /// [`MergeConfig::max_refreshes`] of the grown ones, unmerged before merged and then the most
    /// grown first, settling or not (a settling merge that prepared every map at once took 19 s at
    /// 16 robots); returns the ids of the grown maps that wait for a later merge. Once every usable
    /// map is placed, a placed one counts as grown only at [`MergeConfig::merged_refresh_growth`].
    fn prepare_stale(&mut self) -> Vec<usize> {
        let config = &self.config;
        let mut required = Vec::new();
        let mut grown = Vec::new();
        // While a usable map waits to be placed, its searches need the others' newest parts.
        let unusable = |slot: &Slot| slot.prepared.as_ref().is_some_and(|p| p.map.usable().is_none());
        let all_placed = self.maps.iter().all(|(id, slot)| self.merged.contains(id) || unusable(slot));
        for (&id, slot) in &self.maps {
            let merged = self.merged.contains(&id);
            // Settling: any growth at all counts.
            let refresh_growth = match (self.settling, merged && all_placed) {
                (true, _) => f64::MIN_POSITIVE,
                (false, true) => config.merged_refresh_growth,
                (false, false) => config.refresh_growth,
            };
            match slot.staleness(refresh_growth) {
                Staleness::Required => required.push(id),
                Staleness::Grown(g) => grown.push((id, merged, g)),
                Staleness::Fresh => {}
            }
        }
        grown.sort_by(|a, b| a.1.cmp(&b.1).then(b.2.total_cmp(&a.2)));
        let (now, later) = grown.split_at(grown.len().min(config.max_refreshes));
        required.extend(now.iter().map(|&(id, ..)| id));
        let deferred: Vec<usize> = later.iter().map(|&(id, ..)| id).collect();
        self.stats.preparations += required.len();
        let fresh: Vec<(usize, PreparedMap)> = required
            .par_iter()
            .map(|id| {
                let slot = &self.maps[id];
                (*id, PreparedMap::new(PointCloud::clone(&slot.cloud), slot.views.clone(), config))
            })
            .collect();
        for (id, map) in fresh {
            let slot = self.maps.get_mut(&id).expect("prepared maps exist");
            slot.prepared = Some(Preparation { map: Arc::new(map), generation: self.next_generation });
            slot.reshaped = false;
            self.next_generation += 1;
        }
        deferred
    }

    /// The position of the configured reference map, checked.
    fn reference_position(&self, ids: &[usize], prepared: &[Arc<PreparedMap>]) -> Result<Option<usize>, MergeError> {
        let Some(reference) = self.config.reference else { return Ok(None) };
        let pos = ids
            .iter()
            .position(|&id| id == reference)
            .ok_or(MergeError::NoSuchReference { reference, maps: ids.len() })?;
        match &prepared[pos].features {
            Ok(_) => Ok(Some(pos)),
            Err(reason) => Err(MergeError::UnusableReference { reference, reason: reason.clone() }),
        }
    }

    /// What pair `(a, b)` (positions) needs, given the maps' current generations.
    fn work(&self, (ida, idb): (usize, usize), generations: (u64, u64), points: (usize, usize)) -> PairWork {
        let Some(cached) = self.pairs.get(&(ida, idb)) else { return PairWork::Search };
        let tracked = cached.verdict.edge().is_some_and(|e| e.tracked);
        if self.settling && (cached.generations != generations || tracked) {
            return PairWork::Search;
        }
        // Held back while both maps were placed: a map that lost its place needs every pair again.
        let held_back = matches!(cached.verdict, PairVerdict::Rejected { reason: PairRejection::NoCandidate, .. });
        if held_back && !(self.merged.contains(&ida) && self.merged.contains(&idb)) {
            return PairWork::Search;
        }
        if cached.generations == generations {
            return PairWork::Cached;
        }
        let grown = |now: usize, then: usize| now as f64 >= (1.0 + self.config.reverify_growth) * then.max(1) as f64;
        let reverify = grown(points.0, cached.searched_at.0) || grown(points.1, cached.searched_at.1);
        if cached.verdict.edge().is_some() && !reverify { PairWork::Track } else { PairWork::Search }
    }

    /// Verdicts of all pairs of usable maps: cached ones reused, links tracked, and at most
    /// [`MergeConfig::max_searches`] global registrations, all in parallel; with the number of
    /// pairs left waiting for a search and the time spent comparing places. While settling, a pair
    /// with a map still waiting to be prepared (`deferred`, ids) waits too: searching it now would
    /// only be done again.
    fn estimate_pairs(
        &mut self,
        ids: &[usize],
        prepared: &[Arc<PreparedMap>],
        deferred: &[usize],
    ) -> (Vec<PairReport>, usize, std::time::Duration) {
        let current: Vec<u64> =
            ids.iter().map(|id| self.maps[id].prepared.as_ref().map_or(0, |x| x.generation)).collect();
        let generation = |p: usize| current[p];
        let usable: Vec<usize> = (0..ids.len()).filter(|&p| prepared[p].usable().is_some()).collect();
        let all: Vec<(usize, usize)> =
            usable.iter().flat_map(|&a| usable.iter().filter(move |&&b| b > a).map(move |&b| (a, b))).collect();
        let points = |(a, b): (usize, usize)| (prepared[a].points, prepared[b].points);
        let generations = |(a, b): (usize, usize)| (generation(a), generation(b));
        let work: Vec<PairWork> =
            all.iter().map(|&p| self.work((ids[p.0], ids[p.1]), generations(p), points(p))).collect();
        let tracks: Vec<(usize, usize)> = select(&all, &work, PairWork::Track);
        let waits =
            |&(a, b): &(usize, usize)| self.settling && (deferred.contains(&ids[a]) || deferred.contains(&ids[b]));
        let (waiting, mut searches): (Vec<_>, Vec<_>) =
            select(&all, &work, PairWork::Search).into_iter().partition(waits);
        let waited = |&(a, b): &(usize, usize)| self.pairs.get(&(ids[a], ids[b])).map_or(0, |c| c.searched_in);
        searches.sort_by_key(waited);
        let config = &self.config;
        let followed: Vec<Option<PairVerdict>> = tracks
            .par_iter()
            .map(|&(a, b)| {
                let previous = self.pairs[&(ids[a], ids[b])].verdict.edge().expect("tracked pairs are linked");
                track_pair((a, &prepared[a]), (b, &prepared[b]), previous, config).map(PairVerdict::Edge)
            })
            .collect();
        let mut done: Vec<(usize, usize)> = Vec::new();
        for (&(a, b), verdict) in tracks.iter().zip(followed) {
            match verdict {
                Some(verdict) => {
                    let cached = self.pairs.get_mut(&(ids[a], ids[b])).expect("tracked pairs are cached");
                    cached.verdict = verdict;
                    cached.generations = generations((a, b));
                    self.stats.tracked += 1;
                    done.push((a, b));
                }
                // Lost: search again, first in line.
                None => searches.insert(0, (a, b)),
            }
        }
        let ((mut searches, unmatched), places_time) = timed(|| self.with_candidates(ids, searches));
        let merge = self.stats.merges as u64;
        for &(a, b) in &unmatched {
            let verdict =
                PairVerdict::Rejected { reason: PairRejection::NoCandidate, best: None, best_transform: None };
            let before = self.pairs.get(&(ids[a], ids[b]));
            let pair = CachedPair {
                generations: generations((a, b)),
                verdict,
                searched_at: before.map_or(points((a, b)), |c| c.searched_at),
                searched_in: before.map_or(0, |c| c.searched_in),
            };
            self.pairs.insert((ids[a], ids[b]), pair);
            self.stats.unmatched += 1;
            done.push((a, b));
        }
        let config = &self.config;
        let over_budget = searches.split_off(searches.len().min(config.max_searches));
        let found: Vec<PairVerdict> =
            searches.par_iter().map(|&(a, b)| estimate_pair((a, &prepared[a]), (b, &prepared[b]), config)).collect();
        self.stats.pair_estimates += searches.len();
        for (&(a, b), verdict) in searches.iter().zip(found) {
            let pair = CachedPair {
                generations: generations((a, b)),
                verdict,
                searched_at: points((a, b)),
                searched_in: merge,
            };
            self.pairs.insert((ids[a], ids[b]), pair);
            done.push((a, b));
        }
        let pending = PairVerdict::Rejected { reason: PairRejection::Pending, best: None, best_transform: None };
        let reports = all
            .into_iter()
            .map(|(a, b)| {
                let verdict = self.pairs.get(&(ids[a], ids[b])).map_or(&pending, |c| &c.verdict);
                PairReport { a, b, verdict: with_positions(verdict, a, b), cached: !done.contains(&(a, b)) }
            })
            .collect();
        (reports, over_budget.len() + waiting.len(), places_time)
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

    /// Step 2a: while settling, holds back the pairs waiting for a search that are not worth one:
    /// two placed maps whose places show no candidate overlap (a link between them would only
    /// duplicate what places both already). Only while settling: comparing two large maps' places
    /// the first time costs tens of milliseconds, and doing it for the pairs of every re-prepared
    /// map added 0.3-0.6 s to a streaming 16-robot merge, whose searches the budget bounds anyway;
    /// a settling merge searches every changed pair, and there the gate saves the most (the
    /// 16-robot load caught up in 48 s instead of 68). A pair with an unplaced map is searched even
    /// without a candidate: two maps can overlap where no two keyframes stand at one place (one
    /// robot saw from afar what the other drove through; the 16-robot campus load had a robot
    /// linked only that way). A pair once linked is never held back: its link is the evidence.
    fn with_candidates(&mut self, ids: &[usize], pairs: Vec<(usize, usize)>) -> (Positions, Positions) {
        let (mut searched, mut unmatched) = (Vec::new(), Vec::new());
        for (a, b) in pairs {
            let key = (ids[a], ids[b]);
            let placed = self.settling && self.merged.contains(&key.0) && self.merged.contains(&key.1);
            if placed && self.candidate(key) == Some(false) { unmatched.push((a, b)) } else { searched.push((a, b)) }
        }
        (searched, unmatched)
    }

    /// Whether the places of maps `key` show a candidate overlap; `None` when they cannot tell (a
    /// map without places, places not comparable) or the pair is linked.
    fn candidate(&mut self, key: (usize, usize)) -> Option<bool> {
        let linked = self.pairs.get(&key).is_some_and(|c| c.verdict.edge().is_some());
        let pa = self.maps[&key.0].places.as_deref()?;
        let pb = self.maps[&key.1].places.as_deref()?;
        if linked || !pa.comparable(pb) {
            return None;
        }
        let compared = self.compared.entry(key).or_default();
        if !compared.found {
            // The first time (or when a map was replaced by a smaller one), the smaller map's
            // keyframes against the larger's: the descriptor distance is symmetric, and comparing
            // both ways doubled the cost of a settling merge's first comparisons.
            let fresh =
                compared.since == Since::default() || compared.since.a > pa.len() || compared.since.b > pb.len();
            let since = match (fresh, pa.len() <= pb.len()) {
                (false, _) => compared.since,
                (true, true) => Since { a: 0, b: pb.len() },
                (true, false) => Since { a: pa.len(), b: 0 },
            };
            compared.found = pa.best_match(pb, since, &self.config.places).is_some();
            compared.since = Places::since(pa, pb);
        }
        Some(compared.found)
    }

    /// Per-map reports from the chained tree.
    fn map_reports(
        &self,
        ids: &[usize],
        prepared: &[Arc<PreparedMap>],
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
                    status: status(p, &prepared[p], pairs, chained[p].as_ref()),
                }
            })
            .collect()
    }
}

/// The pairs whose work is `kind`.
fn select(all: &[(usize, usize)], work: &[PairWork], kind: PairWork) -> Vec<(usize, usize)> {
    all.iter().zip(work).filter(|(_, w)| **w == kind).map(|(p, _)| *p).collect()
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
fn layout(prepared: &[Arc<PreparedMap>], pairs: &[PairReport], reference: Option<usize>) -> Layout {
    let n = prepared.len();
    let edges: Vec<GraphEdge> = pairs
        .iter()
        .filter_map(|p| p.verdict.edge())
        .map(|e| GraphEdge { a: e.a, b: e.b, transform: e.transform, weight: e.confidence.score })
        .collect();
    let forest = graph::maximum_spanning_forest(n, &edges);
    let components = graph::components(n, &edges, &forest);
    // Without a configured reference: the largest component among usable maps (an unusable map is
    // a component of one and must not win a tie against a usable one).
    let component = match reference {
        Some(r) => components.iter().find(|c| c.contains(&r)),
        None => components.iter().find(|c| prepared[c[0]].usable().is_some()),
    };
    let Some(component) = component else {
        return Layout { root: None, tree: Vec::new(), chained: vec![None; n] };
    };
    let tree: Vec<usize> = forest.into_iter().filter(|&i| component.contains(&edges[i].a)).collect();
    let root = reference.or_else(|| graph::tree_centre(n, &edges, &tree, component)).expect("non-empty component");
    let chained = graph::chain(n, &edges, &tree, root);
    Layout { root: Some(root), tree: tree.iter().map(|&i| (edges[i].a, edges[i].b)).collect(), chained }
}

/// Where map `p` ended up, and why.
fn status(p: usize, map: &PreparedMap, pairs: &[PairReport], chained: Option<&Chained>) -> MapStatus {
    if let Err(e) = &map.features {
        return MapStatus::Unmerged(Unmerged::Unusable(e.clone()));
    }
    if let Some(c) = chained {
        return MapStatus::Merged { transform: c.transform, confidence: c.weakest.min(1.0), hops: c.hops };
    }
    let has_edge = pairs.iter().any(|q| (q.a == p || q.b == p) && q.verdict.edge().is_some());
    MapStatus::Unmerged(if has_edge { Unmerged::OtherComponent } else { Unmerged::NoOverlap })
}
