//! The incremental merger: per-map preparations cached by revision, pair verdicts by revision pair.
//!
//! Robots send map updates one at a time; recomputing all N(N-1)/2 pairs for each would waste most
//! of the station's time on pairs that did not change. A map's preparation is redone only when its
//! revision changes, and a pair only when either revision does.

use std::collections::BTreeMap;
use std::sync::Arc;

use cloud::stopwatch::{Stopwatch, timed};
use cloud::{Channels, PointCloud};
use rayon::prelude::*;
use rustc_hash::FxHashMap;

use super::graph::{self, Chained, GraphEdge};
use super::{
    MapReport, MapStatus, MergeConfig, MergeError, MergeReport, MergeTiming, PairReport, PairVerdict, PreparedMap,
    Unmerged, estimate_pair,
};

/// One map slot: the latest revision and its preparation once computed.
struct Slot {
    revision: u64,
    /// The cloud of a revision not prepared yet.
    pending: Option<PointCloud>,
    prepared: Option<Arc<PreparedMap>>,
}

/// A pair verdict and the revisions it was computed for.
struct CachedPair {
    revisions: (u64, u64),
    verdict: PairVerdict,
}

/// How much work the merger has done since it was created.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MergerStats {
    /// Maps prepared (features and Gaussians).
    pub preparations: usize,
    /// Pairwise estimates computed (cache misses).
    pub pair_estimates: usize,
}

/// Merges maps that change over time, recomputing only what a change affects.
pub struct Merger {
    config: MergeConfig,
    maps: BTreeMap<usize, Slot>,
    pairs: FxHashMap<(usize, usize), CachedPair>,
    stats: MergerStats,
}

impl Merger {
    /// An empty merger; fails on an invalid configuration.
    pub fn new(config: MergeConfig) -> Result<Self, MergeError> {
        config.validate()?;
        Ok(Self { config, maps: BTreeMap::new(), pairs: FxHashMap::default(), stats: MergerStats::default() })
    }

    /// The settings.
    pub fn config(&self) -> &MergeConfig {
        &self.config
    }

    /// Work done so far.
    pub fn stats(&self) -> MergerStats {
        self.stats
    }

    /// Sets map `id` to `cloud` at `revision`; a revision already held is ignored.
    pub fn update(&mut self, id: usize, revision: u64, cloud: PointCloud) {
        if self.maps.get(&id).is_some_and(|s| s.revision == revision) {
            return;
        }
        self.maps.insert(id, Slot { revision, pending: Some(cloud), prepared: None });
    }

    /// Forgets map `id` and its pairs.
    pub fn remove(&mut self, id: usize) {
        self.maps.remove(&id);
        self.pairs.retain(|&(a, b), _| a != id && b != id);
    }

    /// Merges the current revisions of all maps.
    pub fn merge(&mut self) -> Result<MergeReport, MergeError> {
        let watch = Stopwatch::start();
        let ((), features) = timed(|| self.prepare_stale());
        let ids: Vec<usize> = self.maps.keys().copied().collect();
        let prepared: Vec<Arc<PreparedMap>> =
            self.maps.values().map(|s| Arc::clone(s.prepared.as_ref().expect("all maps are prepared"))).collect();
        let reference = self.reference_position(&ids, &prepared)?;
        let (pairs, pairs_time) = timed(|| self.estimate_pairs(&ids, &prepared));
        let (layout, graph) = timed(|| layout(&prepared, &pairs, reference));
        let maps = self.map_reports(&ids, &prepared, &pairs, &layout.chained);
        let ((global_map, origins), assemble) = timed(|| assemble(&prepared, &maps, self.config.output_voxel));
        let timing = MergeTiming { features, pairs: pairs_time, graph, assemble, total: watch.elapsed() };
        Ok(MergeReport { maps, pairs, reference: layout.root, tree: layout.tree, global_map, origins, timing })
    }

    /// Prepares, in parallel, every map whose revision has no preparation yet.
    fn prepare_stale(&mut self) {
        let config = &self.config;
        let mut stale: Vec<&mut Slot> = self.maps.values_mut().filter(|s| s.prepared.is_none()).collect();
        self.stats.preparations += stale.len();
        stale.par_iter_mut().for_each(|slot| {
            let cloud = slot.pending.take().unwrap_or_default();
            slot.prepared = Some(Arc::new(PreparedMap::new(cloud, config)));
        });
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

    /// Verdicts of all pairs of usable maps: cached ones reused, the others computed in parallel.
    fn estimate_pairs(&mut self, ids: &[usize], prepared: &[Arc<PreparedMap>]) -> Vec<PairReport> {
        let revision = |p: usize| self.maps[&ids[p]].revision;
        let usable: Vec<usize> = (0..ids.len()).filter(|&p| prepared[p].usable().is_some()).collect();
        let all: Vec<(usize, usize)> =
            usable.iter().flat_map(|&a| usable.iter().filter(move |&&b| b > a).map(move |&b| (a, b))).collect();
        let is_cached = |&(a, b): &(usize, usize)| {
            self.pairs.get(&(ids[a], ids[b])).is_some_and(|c| c.revisions == (revision(a), revision(b)))
        };
        let stale: Vec<(usize, usize)> = all.iter().copied().filter(|p| !is_cached(p)).collect();
        let config = &self.config;
        let fresh: Vec<PairVerdict> =
            stale.par_iter().map(|&(a, b)| estimate_pair((a, &prepared[a]), (b, &prepared[b]), config)).collect();
        self.stats.pair_estimates += stale.len();
        for (&(a, b), verdict) in stale.iter().zip(fresh) {
            let revisions = (revision(a), revision(b));
            self.pairs.insert((ids[a], ids[b]), CachedPair { revisions, verdict });
        }
        all.into_iter()
            .map(|(a, b)| PairReport {
                a,
                b,
                verdict: with_positions(&self.pairs[&(ids[a], ids[b])].verdict, a, b),
                cached: !stale.contains(&(a, b)),
            })
            .collect()
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
            .map(|p| MapReport {
                id: ids[p],
                revision: self.maps[&ids[p]].revision,
                points: prepared[p].cloud.len(),
                dropped_non_finite: prepared[p].dropped_non_finite,
                status: status(p, &prepared[p], pairs, chained[p].as_ref()),
            })
            .collect()
    }
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

/// Paper eq. 11: the union of the merged maps in the global frame, voxelised to fuse duplicates;
/// with each point's map id.
fn assemble(prepared: &[Arc<PreparedMap>], maps: &[MapReport], voxel: f32) -> (PointCloud, Vec<usize>) {
    let merged: Vec<usize> = (0..maps.len()).filter(|&p| maps[p].is_merged()).collect();
    // Ring and time are per-sweep quantities, meaningless in a global map; intensity is kept when
    // every merged map has it. The ring channel carries each point's map position through the
    // voxel grid instead (a voxel keeps its first point's), and is taken out again below.
    let intensity = merged.iter().all(|&p| prepared[p].cloud.intensity.is_some());
    let moved: Vec<PointCloud> = merged
        .par_iter()
        .enumerate()
        .map(|(k, &p)| {
            let c = &prepared[p].cloud;
            let label = Some(vec![k as u16; c.len()]);
            let bare = PointCloud { points: c.points.clone(), intensity: c.intensity.clone(), ring: label, time: None };
            bare.transformed(&maps[p].transform().cast::<f32>())
        })
        .collect();
    let n = moved.iter().map(PointCloud::len).sum();
    let mut union = PointCloud::with_capacity(n, Channels { intensity, ring: true, time: false });
    for c in &moved {
        union.extend(c);
    }
    let mut global = cloud::voxel::downsample(&union, voxel).expect("output_voxel is validated positive");
    let labels = global.ring.take().unwrap_or_default();
    let origins = labels.iter().map(|&k| maps[merged[usize::from(k)]].id).collect();
    (global, origins)
}
