//! A round of estimation: the maps' preparations and the pairs' verdicts, taken out of the
//! [`Merger`](super::Merger) so that they can run while the merger goes on publishing maps.
//!
//! Composing a global map from the placements already found takes a fraction of a second; finding
//! placements (preparing grown maps, tracking links, searching pairs) takes seconds at 16 robots.
//! map_merge_3d runs the two at separate rates for the same reason. A round owns what it works on
//! (the maps' clouds and preparations are shared, not copied; the pair cache is cloned), so
//! [`Round::run`] needs no access to the merger; [`super::Merger::apply`] takes its results back.
//! Everything a round decides is decided as the synchronous merge decided it: which maps to
//! prepare, which pairs to track, search or hold back.

use std::sync::Arc;
use std::time::Duration;

use cloud::PointCloud;
use cloud::stopwatch::{Stopwatch, timed};
use cloud::visibility::Views;
use rayon::prelude::*;
use rustc_hash::{FxHashMap, FxHashSet};

use super::places::{Candidate, Places, Since};
use super::{MergeConfig, PairRejection, PairVerdict, PreparedMap, estimate_pair, keep_link, track_pair};

/// A map's preparation and what it was made from.
#[derive(Clone)]
pub(super) struct Preparation {
    pub map: Arc<PreparedMap>,
    /// Bumped at every preparation of the map; pair verdicts are cached against it.
    pub generation: u64,
}

/// A pair verdict and what it was computed from.
#[derive(Clone)]
pub(super) struct CachedPair {
    /// Generations of the two maps' preparations.
    pub generations: (u64, u64),
    pub verdict: PairVerdict,
    /// Points of the two prepared maps when the last global registration ran.
    pub searched_at: (usize, usize),
    /// Round of the last global registration: the longest-waiting pair is searched first.
    pub searched_in: u64,
    /// Generations of the two maps' preparations when the last global registration ran.
    pub searched_with: (u64, u64),
}

/// How far two maps' places were compared, and the closest candidate found so far.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Compared {
    pub since: Since,
    pub best: Option<Candidate>,
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
    /// Merges run (global maps composed).
    pub merges: usize,
    /// Searches not run because no place of either map looked like one of the other's.
    pub unmatched: usize,
    /// Searches that found their link around a place candidate (the features near the two
    /// keyframes that look alike), not over the whole maps.
    pub around: usize,
    /// Rounds of estimation run.
    pub rounds: usize,
}

impl std::ops::AddAssign for MergerStats {
    fn add_assign(&mut self, other: Self) {
        self.preparations += other.preparations;
        self.pair_estimates += other.pair_estimates;
        self.tracked += other.tracked;
        self.merges += other.merges;
        self.unmatched += other.unmatched;
        self.around += other.around;
        self.rounds += other.rounds;
    }
}

/// One map as a round sees it.
pub(super) struct RoundMap {
    pub cloud: Arc<PointCloud>,
    pub views: Option<Arc<Views>>,
    pub places: Option<Arc<Places>>,
    pub prepared: Option<Preparation>,
    pub reshaped: bool,
    /// The map's shape counter when the round was planned.
    pub shape: u64,
}

impl RoundMap {
    /// Whether the round must prepare the map (new or reshaped), may (grown past
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

/// Pairs of maps by their positions.
type Positions = Vec<(usize, usize)>;

/// What one pair needs this round.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PairWork {
    /// Its cached verdict stands.
    Cached,
    /// Linked before: follow the link.
    Track,
    /// A global registration (or, over budget, wait).
    Search,
}

/// Wall time of a round's steps.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RoundTiming {
    /// Preparing maps (features, Gaussians).
    pub features: Duration,
    /// Tracking and searching pairs.
    pub pairs: Duration,
    /// Of `pairs`: comparing the places of the pairs waiting for a search.
    pub places: Duration,
    /// End to end.
    pub total: Duration,
}

/// A round of estimation, planned by [`super::Merger::plan`], run anywhere by [`Round::run`] and
/// taken back by [`super::Merger::apply`].
pub struct Round {
    pub(super) config: MergeConfig,
    /// This round's number (1, 2, ...).
    pub(super) number: u64,
    pub(super) settling: bool,
    /// The merger's change counter when the round was planned.
    pub(super) changes: u64,
    /// Ids of the maps the last merge placed.
    pub(super) merged: FxHashSet<usize>,
    pub(super) maps: std::collections::BTreeMap<usize, RoundMap>,
    pub(super) pairs: FxHashMap<(usize, usize), CachedPair>,
    pub(super) compared: FxHashMap<(usize, usize), Compared>,
    /// Pairs of map ids (lower first) that are sessions of one robot.
    pub(super) kin: FxHashSet<(usize, usize)>,
    pub(super) next_generation: u64,
    /// Ids of the maps this round prepared.
    pub(super) prepared: Vec<usize>,
    /// Pairs (ids) whose verdict this round computed.
    pub(super) done: FxHashSet<(usize, usize)>,
    /// Grown maps and pairs left for a later round.
    pub(super) pending: usize,
    pub(super) stats: MergerStats,
    pub(super) timing: RoundTiming,
    pub(super) ran: bool,
}

impl Round {
    /// Prepares the stale maps, then tracks, compares places and searches pairs: the seconds of a
    /// merge. Idempotent: a round runs once.
    pub fn run(&mut self) {
        if self.ran {
            return;
        }
        self.ran = true;
        let watch = Stopwatch::start();
        let (deferred, features) = timed(|| self.prepare_stale());
        let ((deferred_pairs, places), pairs) = timed(|| self.estimate_pairs(&deferred));
        self.pending = deferred.len() + deferred_pairs;
        self.stats.rounds += 1;
        self.timing = RoundTiming { features, pairs, places, total: watch.elapsed() };
    }

    /// Wall time of its steps (zero before it ran).
    pub fn timing(&self) -> RoundTiming {
        self.timing
    }

    /// True when running it would change nothing: no map to prepare, no pair to track or search.
    pub(super) fn idle(&self) -> bool {
        let (required, grown) = self.stale();
        if !required.is_empty() || !grown.is_empty() {
            return false;
        }
        let (ids, prepared) = self.current();
        let all = usable_pairs(prepared.len(), |p| prepared[p].usable().is_some());
        all.iter().all(|&(a, b)| {
            let key = (ids[a], ids[b]);
            self.work(key, self.generations(key), (prepared[a].points, prepared[b].points)) == PairWork::Cached
        })
    }

    /// Maps that must be prepared (ids) and grown ones that may be (id, placed, growth).
    fn stale(&self) -> (Vec<usize>, Vec<(usize, bool, f64)>) {
        let config = &self.config;
        let mut required = Vec::new();
        let mut grown = Vec::new();
        // While a usable map waits to be placed, its searches need the others' newest parts.
        let unusable = |map: &RoundMap| map.prepared.as_ref().is_some_and(|p| p.map.usable().is_none());
        let all_placed = self.maps.iter().all(|(id, map)| self.merged.contains(id) || unusable(map));
        for (&id, map) in &self.maps {
            let merged = self.merged.contains(&id);
            // Settling: any growth at all counts.
            let refresh_growth = match (self.settling, merged && all_placed) {
                (true, _) => f64::MIN_POSITIVE,
                (false, true) => config.merged_refresh_growth,
                (false, false) => config.refresh_growth,
            };
            match map.staleness(refresh_growth) {
                Staleness::Required => required.push(id),
                Staleness::Grown(g) => grown.push((id, merged, g)),
                Staleness::Fresh => {}
            }
        }
        (required, grown)
    }

    /// Prepares, in parallel, every map that must be (new, reshaped) and up to
    /// [`MergeConfig::max_refreshes`] of the grown ones, unmerged before merged and then the most
    /// grown first, settling or not (a settling merge that prepared every map at once took 19 s at
    /// 16 robots); returns the ids of the grown maps that wait for a later round. Once every usable
    /// map is placed, a placed one counts as grown only at [`MergeConfig::merged_refresh_growth`].
    fn prepare_stale(&mut self) -> Vec<usize> {
        let (mut required, mut grown) = self.stale();
        grown.sort_by(|a, b| a.1.cmp(&b.1).then(b.2.total_cmp(&a.2)));
        let (now, later) = grown.split_at(grown.len().min(self.config.max_refreshes));
        required.extend(now.iter().map(|&(id, ..)| id));
        let deferred: Vec<usize> = later.iter().map(|&(id, ..)| id).collect();
        self.stats.preparations += required.len();
        let config = &self.config;
        let fresh: Vec<(usize, PreparedMap)> = required
            .par_iter()
            .map(|id| {
                let map = &self.maps[id];
                let cloud = PointCloud::clone(&map.cloud);
                // A map that only grew is estimated again around its changes only.
                let prepared = match map.prepared.as_ref().filter(|_| !map.reshaped) {
                    Some(earlier) => PreparedMap::grown(cloud, map.views.clone(), config, &earlier.map),
                    None => PreparedMap::new(cloud, map.views.clone(), config),
                };
                (*id, prepared)
            })
            .collect();
        for (id, prepared) in fresh {
            let map = self.maps.get_mut(&id).expect("prepared maps exist");
            map.prepared = Some(Preparation { map: Arc::new(prepared), generation: self.next_generation });
            map.reshaped = false;
            self.next_generation += 1;
            self.prepared.push(id);
        }
        deferred
    }

    /// Ids and preparations of the prepared maps, in id order.
    fn current(&self) -> (Vec<usize>, Vec<Arc<PreparedMap>>) {
        self.maps.iter().filter_map(|(&id, m)| Some((id, Arc::clone(&m.prepared.as_ref()?.map)))).unzip()
    }

    /// Current generations of the preparations of maps `(a, b)` (ids).
    fn generations(&self, (a, b): (usize, usize)) -> (u64, u64) {
        let generation = |id: usize| self.maps[&id].prepared.as_ref().map_or(0, |p| p.generation);
        (generation(a), generation(b))
    }

    /// What pair `(ida, idb)` needs, given the maps' current generations.
    fn work(&self, (ida, idb): (usize, usize), generations: (u64, u64), points: (usize, usize)) -> PairWork {
        let Some(cached) = self.pairs.get(&(ida, idb)) else { return PairWork::Search };
        // A tracked link is searched again when settling, unless this very preparation was searched
        // and the link kept by tracking after all (see `estimate_pairs`).
        let tracked = cached.verdict.edge().is_some_and(|e| e.tracked) && cached.searched_with != generations;
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

    /// Verdicts of the pairs of usable maps that need one: links tracked, and at most
    /// [`MergeConfig::max_searches`] global registrations, all in parallel; returns the number of
    /// pairs left waiting for a search and the time spent comparing places. While settling, a
    /// pair with a map still waiting to be prepared (`deferred`, ids) waits too: searching it now
    /// would only be done again.
    fn estimate_pairs(&mut self, deferred: &[usize]) -> (usize, Duration) {
        let (ids, prepared) = self.current();
        let all = usable_pairs(prepared.len(), |p| prepared[p].usable().is_some());
        let key = |(a, b): (usize, usize)| (ids[a], ids[b]);
        let points = |(a, b): (usize, usize)| (prepared[a].points, prepared[b].points);
        let work: Vec<PairWork> = all.iter().map(|&p| self.work(key(p), self.generations(key(p)), points(p))).collect();
        let tracks: Positions = select(&all, &work, PairWork::Track);
        let waits =
            |&(a, b): &(usize, usize)| self.settling && (deferred.contains(&ids[a]) || deferred.contains(&ids[b]));
        let (waiting, mut searches): (Positions, Positions) =
            select(&all, &work, PairWork::Search).into_iter().partition(waits);
        let waited = |&p: &(usize, usize)| self.pairs.get(&key(p)).map_or(0, |c| c.searched_in);
        searches.sort_by_key(waited);
        let config = &self.config;
        let followed: Vec<Option<PairVerdict>> = tracks
            .par_iter()
            .map(|&(a, b)| {
                let previous = self.pairs[&key((a, b))].verdict.edge().expect("tracked pairs are linked");
                track_pair((a, &prepared[a]), (b, &prepared[b]), previous, config).map(PairVerdict::Edge)
            })
            .collect();
        let mut lost = Vec::new();
        for (&p, verdict) in tracks.iter().zip(followed) {
            match verdict {
                Some(verdict) => {
                    let generations = self.generations(key(p));
                    let cached = self.pairs.get_mut(&key(p)).expect("tracked pairs are cached");
                    cached.verdict = verdict;
                    cached.generations = generations;
                    self.stats.tracked += 1;
                    self.done.insert(key(p));
                }
                // Lost: search again, first in line.
                None => lost.push(p),
            }
        }
        let ((searches, unmatched), places_time) = timed(|| self.with_candidates(&ids, searches));
        let mut searches = [lost, searches].concat();
        for &p in &unmatched {
            let verdict =
                PairVerdict::Rejected { reason: PairRejection::NoCandidate, best: None, best_transform: None };
            let before = self.pairs.get(&key(p));
            let pair = CachedPair {
                generations: self.generations(key(p)),
                verdict,
                searched_at: before.map_or(points(p), |c| c.searched_at),
                searched_in: before.map_or(0, |c| c.searched_in),
                searched_with: before.map_or((0, 0), |c| c.searched_with),
            };
            self.pairs.insert(key(p), pair);
            self.stats.unmatched += 1;
            self.done.insert(key(p));
        }
        let over_budget = searches.split_off(searches.len().min(self.config.max_searches));
        let (arounds, looked) = timed(|| searches.iter().map(|&p| self.around(key(p))).collect::<Vec<_>>());
        let config = &self.config;
        // A linked pair searched again (grown past `reverify_growth`, or settling) keeps its link by
        // tracking it when the search finds none: RANSAC is seeded by the maps, and a grown map can
        // draw a worse sample; one unlucky draw must not unmerge a robot whose link passed every
        // check. Not for a pair whose tracking was just lost.
        let previous = |p: (usize, usize)| {
            let lost = tracks.contains(&p);
            self.pairs.get(&key(p)).and_then(|c| c.verdict.edge()).filter(|_| !lost)
        };
        let found: Vec<(PairVerdict, bool)> = searches
            .par_iter()
            .zip(&arounds)
            .map(|(&(a, b), around)| {
                let searched = estimate_pair((a, &prepared[a]), (b, &prepared[b]), config, around.as_ref());
                let kept = match (&searched, previous((a, b))) {
                    (PairVerdict::Rejected { .. }, Some(edge)) => {
                        keep_link((a, &prepared[a]), (b, &prepared[b]), edge, config)
                    }
                    _ => None,
                };
                kept.map_or((searched, false), |edge| (PairVerdict::Edge(edge), true))
            })
            .collect();
        self.stats.pair_estimates += searches.len();
        for (&p, (verdict, kept)) in searches.iter().zip(found) {
            self.stats.tracked += usize::from(kept);
            self.stats.around += usize::from(verdict.edge().is_some_and(|e| e.around && !kept));
            let pair = CachedPair {
                generations: self.generations(key(p)),
                verdict,
                searched_at: points(p),
                searched_in: self.number,
                searched_with: self.generations(key(p)),
            };
            self.pairs.insert(key(p), pair);
            self.done.insert(key(p));
        }
        (over_budget.len() + waiting.len(), places_time + looked)
    }

    /// Step 2a: holds back the pairs waiting for a search that are not worth one: two placed maps
    /// whose places show no candidate overlap (a link between them would only duplicate what
    /// places both already). A settling merge searches every changed pair, and there the gate saves
    /// the most (the 16-robot load caught up in 48 s instead of 68). While streaming it changes
    /// nothing measurable (docs/decisions/place-gating-of-pairs-with-an-unplaced-map.md), and a
    /// search is then never spent on what cannot add a placement. A pair with
    /// an unplaced map is searched even without a candidate: two maps can overlap where no two
    /// keyframes stand at one place (one robot saw from afar what the other drove through; the
    /// 16-robot campus load had a robot linked only that way). A pair once linked is never held
    /// back: its link is the evidence.
    ///
    /// The pairs to search come in the order of [`Promise`], longest-waiting first within each.
    fn with_candidates(&mut self, ids: &[usize], pairs: Positions) -> (Positions, Positions) {
        let (mut searched, mut unmatched) = (Vec::new(), Vec::new());
        for (a, b) in pairs {
            let key = (ids[a], ids[b]);
            let placed = (self.merged.contains(&key.0), self.merged.contains(&key.1));
            let promise = match placed {
                (false, _) | (_, false) if self.kin.contains(&(key.0.min(key.1), key.0.max(key.1))) => Promise::Kin,
                (true, true) if self.candidate(key) == Some(false) => {
                    unmatched.push((a, b));
                    continue;
                }
                (true, true) => Promise::Placed,
                // Not compared: early in a large fleet's run nearly every pair is of two unplaced
                // maps, and comparing them all cost more than the searches it would order
                // (32-robot load: 4.5-7.5 s of places per round against 0.1-1 s).
                (false, false) => Promise::Unknown,
                _ => match self.candidate(key) {
                    Some(true) => Promise::Candidate,
                    None => Promise::Unknown,
                    Some(false) => Promise::NoCandidate,
                },
            };
            searched.push((promise, (a, b)));
        }
        // Stable: the longest-waiting first within a class.
        searched.sort_by_key(|&(promise, _)| promise);
        (searched.into_iter().map(|(_, p)| p).collect(), unmatched)
    }

    /// Whether the places of maps `key` show a candidate overlap; `None` when they cannot tell (a
    /// map without places, places not comparable) or the pair is linked.
    fn candidate(&mut self, key: (usize, usize)) -> Option<bool> {
        let linked = self.pairs.get(&key).is_some_and(|c| c.verdict.edge().is_some());
        if linked {
            return None;
        }
        Some(self.compare(key)?.best.is_some())
    }

    /// Step 2b: where a search of maps `key` looks again when the whole maps give no link, around
    /// the closest candidate overlap their places show (see [`cloud::global::Around`]); `None`:
    /// the whole maps only.
    fn around(&mut self, key: (usize, usize)) -> Option<cloud::global::Around> {
        let best = self.compare(key)?.best?;
        best.around(self.maps[&key.0].places.as_deref()?, self.maps[&key.1].places.as_deref()?)
    }

    /// The places of maps `key` compared up to their newest keyframes; `None` when a map has none
    /// or they are not comparable. Only what was not compared before is compared: descriptors do
    /// not depend on poses.
    fn compare(&mut self, key: (usize, usize)) -> Option<&Compared> {
        let pa = self.maps[&key.0].places.as_deref()?;
        let pb = self.maps[&key.1].places.as_deref()?;
        if !pa.comparable(pb) {
            return None;
        }
        let compared = self.compared.entry(key).or_default();
        // A map replaced by a smaller one is compared afresh.
        if compared.since.a > pa.len() || compared.since.b > pb.len() {
            *compared = Compared::default();
        }
        let now = Places::since(pa, pb);
        if compared.since != now {
            // The first time, the smaller map's keyframes against the larger's: the descriptor
            // distance is symmetric, and comparing both ways doubled the cost of a settling
            // merge's first comparisons.
            let since = match (compared.since == Since::default(), pa.len() <= pb.len()) {
                (false, _) => compared.since,
                (true, true) => Since { a: 0, b: pb.len() },
                (true, false) => Since { a: pa.len(), b: 0 },
            };
            let found = pa.best_match(pb, since, &self.config.places);
            compared.best =
                [compared.best, found].into_iter().flatten().min_by(|x, y| x.distance.total_cmp(&y.distance));
            compared.since = now;
        }
        Some(compared)
    }
}

/// Step 2a's order of the searches a round can afford ([`MergeConfig::max_searches`]): a search
/// likeliest to place a map that is not placed goes first, so that the fleet shares one map sooner.
/// The order only decides which pairs wait for a later round, never whether a pair is searched.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Promise {
    /// Two sessions of one robot, one or both not placed: a robot usually starts again where it
    /// stopped, so its previous session is the likeliest overlap of all.
    Kin,
    /// One map is placed, the other not, and their places show a candidate overlap: a link there
    /// places a map at once, and is likeliest.
    Candidate,
    /// A map is not placed and the places cannot tell (no descriptors, not comparable, linked) or
    /// were not compared (neither map is placed).
    Unknown,
    /// Both maps are placed: the search can confirm or improve a placement, not add one.
    Placed,
    /// One map is placed, the other not, and no place of either looks like one of the other's: a
    /// link is still possible (one robot saw from afar what the other drove through), but least
    /// likely.
    NoCandidate,
}

/// Every pair (positions, `a < b`) of the maps at positions `0..n` that are `usable`.
pub(super) fn usable_pairs(n: usize, usable: impl Fn(usize) -> bool) -> Positions {
    let usable: Vec<usize> = (0..n).filter(|&p| usable(p)).collect();
    usable.iter().flat_map(|&a| usable.iter().filter(move |&&b| b > a).map(move |&b| (a, b))).collect()
}

/// The pairs whose work is `kind`.
fn select(all: &[(usize, usize)], work: &[PairWork], kind: PairWork) -> Positions {
    all.iter().zip(work).filter(|(_, w)| **w == kind).map(|(p, _)| *p).collect()
}
