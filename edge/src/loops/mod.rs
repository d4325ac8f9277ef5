//! Loop closure on one robot, EMR-FLOAM's "E": each keyframe is described, compared with the places
//! the robot passed long enough ago, verified geometrically, checked against the odometry and the
//! other loops, and the keyframe pose graph is re-optimised when the accepted loops change.
//!
//! Per keyframe ([`LoopCloser::add`]):
//! 1. [`cloud::scan_context`]: the Scan Context descriptor and its ring key;
//! 2. candidates: the `candidates` nearest ring keys among keyframes at least
//!    `exclude_recent_m` metres of path behind, then the best by the full descriptor distance;
//! 3. [`verify`]: the keyframe registered against a submap around the best candidate, from the
//!    descriptor's yaw, accepted on overlap and constraint; not run when the odometry puts the
//!    candidate farther away than a fit within the verification's reach could agree with
//!    ([`consistency::reachable`]: the odometry test of step 4, decided before the fit);
//! 4. [`consistency`]: the loop against the odometry (a loop that agrees is then refined between
//!    the merged neighbourhoods of both keyframes, [`verify::refine`]), then the largest set of
//!    mutually consistent loops, which are the ones in the graph;
//! 5. [`graph`]: the pose graph re-optimised when that set changed.
//!
//! No I/O: the odometry pipeline and the node call it and write or publish what it says.

pub mod consistency;
pub mod graph;
pub mod track;
pub mod verify;

use std::collections::VecDeque;
use std::fmt;
use std::sync::Arc;

use cloud::registration::GaussianCloud;
use cloud::stopwatch::Stopwatch;
use cloud::{PointCloud, Preset};
use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::keyframe::Keyframe;
use cloud::pose_graph::{Edge, EdgeKind, PoseGraph, PoseGraphError, Report};
use cloud::scan_context::{Comparable, RingKeyIndex, ScanContext, ScanContextConfig};
use consistency::{ConsistencyConfig, LoopView};
use graph::{GraphConfig, KeyframeGraph};
use verify::{Fit, Verdict, VerifyConfig};

/// Settings of the loop closure, one section per step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LoopConfig {
    /// The descriptor.
    pub scan_context: ScanContextConfig,
    /// Ring-key neighbours compared by the full descriptor. Default 10 (Scan Context's).
    pub candidates: usize,
    /// A candidate farther than this descriptor distance is not verified. Default 0.35: looser
    /// than Scan Context's 0.13 (SC-A-LOAM uses 0.2-0.4), because verification and the consistency
    /// tests, not the descriptor, decide.
    pub max_descriptor_distance: f64,
    /// Keyframes less than this much path behind are not candidates (m): they trivially look
    /// alike and their relative pose is the odometry's. Default 30 m.
    pub exclude_recent_m: f64,
    /// Keyframes after a verified loop that are not verified themselves. Default 2: along a
    /// revisit every keyframe matches, and a loop every third keyframe constrains the graph as well
    /// as one at each (Scan Context's loop thread runs at 1 Hz for the same reason).
    pub cooldown_keyframes: usize,
    /// Geometric verification.
    pub verify: VerifyConfig,
    /// Consistency with the odometry and between loops.
    pub consistency: ConsistencyConfig,
    /// The pose graph.
    pub graph: GraphConfig,
}

impl Default for LoopConfig {
    fn default() -> Self {
        LoopConfig {
            scan_context: ScanContextConfig::default(),
            candidates: 10,
            max_descriptor_distance: 0.35,
            exclude_recent_m: 30.0,
            cooldown_keyframes: 2,
            verify: VerifyConfig::default(),
            consistency: ConsistencyConfig::default(),
            graph: GraphConfig::default(),
        }
    }
}

impl LoopConfig {
    /// The settings for a preset: indoors Scan Context covers 40 m (walls farther away are seen
    /// through racks, if at all), outdoors its 80 m and coarser verification clouds.
    pub fn preset(preset: Preset) -> Self {
        let mut config = LoopConfig::default();
        match preset {
            Preset::Indoor => config.scan_context.max_range = 40.0,
            Preset::Outdoor => {
                config.verify.voxel = 0.5;
                config.verify.overlap_distance = 1.0;
            }
        }
        config
    }
}

/// The most recently used places' covariances (least recently used evicted first).
#[derive(Default)]
struct GaussianCache {
    entries: VecDeque<(usize, Arc<GaussianCloud>)>,
}

impl GaussianCache {
    fn get_or_insert(&mut self, k: usize, capacity: usize, make: impl FnOnce() -> GaussianCloud) -> Arc<GaussianCloud> {
        let entry = match self.entries.iter().position(|(i, _)| *i == k) {
            Some(at) => self.entries.remove(at).expect("the position is in range"),
            None => (k, Arc::new(make())),
        };
        let cloud = entry.1.clone();
        self.entries.push_front(entry);
        self.entries.truncate(capacity.max(1));
        cloud
    }
}

/// A keyframe as the loop closure keeps it.
#[derive(Clone, Debug)]
pub struct Place {
    /// Keyframe sequence number.
    pub seq: u64,
    /// Index of the scan that made it.
    pub scan: usize,
    /// Odometry pose.
    pub odometry: Isometry3<f64>,
    /// Odometry path length from the first keyframe (m).
    pub path_m: f64,
    /// Its descriptor, laid out for the comparisons with every later keyframe.
    pub context: Comparable,
    /// Its cloud, thinned for verification.
    cloud: PointCloud,
}

impl Place {
    /// What it holds, bytes: its thinned cloud's positions and its descriptor.
    fn bytes(&self) -> u64 {
        (std::mem::size_of_val(self.cloud.points.as_slice()) + self.context.bytes()) as u64
    }
}

/// A loop between keyframes `a` (older) and `b`, verified geometrically.
#[derive(Clone, Debug, PartialEq)]
pub struct Loop {
    /// Older keyframe (index = sequence number).
    pub a: usize,
    /// Newer keyframe.
    pub b: usize,
    /// Scan Context distance of the pair.
    pub descriptor_distance: f64,
    /// The verification's fit: `transform` maps `b`'s points into `a`'s frame.
    pub fit: Fit,
}

/// Why a candidate did not become a loop in the graph.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Rejection {
    /// A cloud was too small or degenerate to register.
    Unregistrable,
    /// By odometry the keyframes are farther apart than any fit within the verification's reach
    /// could agree with (not registered).
    Unreachable,
    /// The fit moved farther from its start than the verification reaches.
    Wandered,
    /// Too little of the keyframe lay on the candidate's submap after the fit.
    LowOverlap,
    /// The fit left a translation direction nearly free (a corridor, a row of shelves).
    Degenerate,
    /// The loop disagrees with the odometry by more than it can have drifted.
    Odometry,
    /// The loop is not in the largest set of loops that agree with each other.
    Inconsistent,
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Rejection::Unregistrable => "too few points to register",
            Rejection::Unreachable => "farther apart by odometry than a fit within reach could agree with",
            Rejection::Wandered => "the fit moved beyond the verification's reach",
            Rejection::LowOverlap => "low overlap after registration",
            Rejection::Degenerate => "registration leaves a direction unconstrained",
            Rejection::Odometry => "disagrees with the odometry beyond its drift",
            Rejection::Inconsistent => "disagrees with the other loops",
        })
    }
}

/// A candidate that is not in the graph, and why.
#[derive(Clone, Debug, PartialEq)]
pub struct Rejected {
    /// Older keyframe.
    pub a: usize,
    /// Newer keyframe.
    pub b: usize,
    /// Scan Context distance of the pair.
    pub descriptor_distance: f64,
    /// The fit, when the registration ran.
    pub fit: Option<Fit>,
    /// Why.
    pub reason: Rejection,
}

/// What one keyframe did to the loop closure.
#[derive(Clone, Debug)]
pub struct Step {
    /// The keyframe's descriptor (for the wire).
    pub context: ScanContext,
    /// The optimisation, when the loops in the graph changed.
    pub optimised: Option<Report>,
    /// Milliseconds spent describing, searching and verifying (optimisation excluded).
    pub detect_ms: f64,
}

/// Why the loop closure failed.
#[derive(Debug, thiserror::Error)]
pub enum LoopError {
    /// The pose graph could not be optimised.
    #[error("pose graph: {0}")]
    Graph(#[from] PoseGraphError),
}

/// One robot's loop closure (see the module documentation).
pub struct LoopCloser {
    config: LoopConfig,
    places: Vec<Place>,
    index: RingKeyIndex,
    /// Places `..indexed` are in the ring-key index.
    indexed: usize,
    verified: Vec<Loop>,
    rejected: Vec<Rejected>,
    /// Indices into `verified` of the loops in the graph.
    in_graph: Vec<usize>,
    graph: KeyframeGraph,
    /// Covariances of recently used places, in their own frames.
    gaussians: GaussianCache,
    /// The last keyframe that verified a loop.
    last_loop: Option<usize>,
    /// What `places` hold, bytes.
    held_bytes: u64,
}

impl LoopCloser {
    /// A loop closure with no keyframe yet.
    pub fn new(config: LoopConfig) -> Self {
        LoopCloser {
            config,
            places: Vec::new(),
            index: RingKeyIndex::default(),
            indexed: 0,
            verified: Vec::new(),
            rejected: Vec::new(),
            in_graph: Vec::new(),
            graph: KeyframeGraph::default(),
            gaussians: GaussianCache::default(),
            last_loop: None,
            held_bytes: 0,
        }
    }

    /// What it keeps of the keyframes it was given, bytes: each one's thinned cloud and descriptor
    /// (the graph's poses and the bounded cache of fitted clouds apart).
    pub fn held_bytes(&self) -> u64 {
        self.held_bytes
    }

    /// Adds the next keyframe (keyframes come in sequence order, from 0): describes it, looks for
    /// a loop and re-optimises the graph if the loops in it changed.
    pub fn add(&mut self, keyframe: &Keyframe) -> Result<Step, LoopError> {
        let watch = Stopwatch::start();
        let (place, context) = self.describe(keyframe);
        self.graph.extend(self.places.last().map(|p| &p.odometry), &place.odometry);
        self.held_bytes += place.bytes();
        self.places.push(place);
        self.index_aged_places();
        let b = self.places.len() - 1;
        let cooling = self.last_loop.is_some_and(|l| b - l <= self.config.cooldown_keyframes);
        let candidate = if cooling { None } else { self.best_candidate(b) };
        let found = candidate.is_some_and(|(a, distance, yaw)| self.check(a, b, distance, yaw));
        if found {
            self.last_loop = Some(b);
        }
        let detect_ms = watch.elapsed_ms();
        let changed = found && self.update_loops_in_graph();
        let optimised = if changed {
            let odometry = self.odometry();
            Some(self.graph.optimise(&odometry, &self.loop_edges(), &self.config.graph)?)
        } else {
            None
        };
        Ok(Step { context, optimised, detect_ms })
    }

    /// Step 1: the place of a keyframe, and its descriptor as it goes on the wire.
    fn describe(&self, keyframe: &Keyframe) -> (Place, ScanContext) {
        let path_m = self.places.last().map_or(0.0, |p| p.path_m + graph::step_length(&p.odometry, &keyframe.pose));
        let context = ScanContext::new(&keyframe.cloud, &self.config.scan_context);
        let place = Place {
            seq: keyframe.seq,
            scan: keyframe.frame,
            odometry: keyframe.pose,
            path_m,
            context: Comparable::new(&context),
            cloud: verify::thin(&keyframe.cloud, &self.config.verify),
        };
        (place, context)
    }

    /// Puts the places that are now far enough behind into the ring-key index.
    fn index_aged_places(&mut self) {
        let Some(now) = self.places.last().map(|p| p.path_m) else { return };
        while self.indexed < self.places.len() && self.places[self.indexed].path_m <= now - self.config.exclude_recent_m
        {
            self.index.add(&self.places[self.indexed].context.ring_key, self.indexed);
            self.indexed += 1;
        }
    }

    /// Step 2: the candidate with the smallest descriptor distance to place `b`, if close enough:
    /// its index, the distance and the yaw of `b` in its frame.
    fn best_candidate(&self, b: usize) -> Option<(usize, f64, f64)> {
        let query = &self.places[b].context;
        self.index
            .nearest(&query.ring_key, self.config.candidates)
            .into_iter()
            .map(|a| (a, self.places[a].context.distance(query, self.config.scan_context.shift_window)))
            .min_by(|x, y| x.1.distance.total_cmp(&y.1.distance))
            .filter(|(_, m)| m.distance <= self.config.max_descriptor_distance)
            .map(|(a, m)| (a, m.distance, m.yaw))
    }

    /// Steps 3 and the odometry half of 4: whether the candidate became a verified loop.
    fn check(&mut self, a: usize, b: usize, descriptor_distance: f64, yaw: f64) -> bool {
        let initial = Isometry3::from_parts(Default::default(), UnitQuaternion::from_scaled_axis(Vector3::z() * yaw));
        let reject = |reason, fit| Rejected { a, b, descriptor_distance, fit, reason };
        let (pa, pb) = (&self.places[a], &self.places[b]);
        let path_m = (pb.path_m - pa.path_m).abs();
        let reach_m = self.config.verify.reach_m;
        if !consistency::reachable(&pa.odometry, &pb.odometry, path_m, &initial, reach_m, &self.config.consistency) {
            tracing::debug!(a, b, descriptor_distance, "loop candidate out of reach by odometry");
            self.rejected.push(reject(Rejection::Unreachable, None));
            return false;
        }
        let submap = self.submap(a);
        let keyframe = self.gaussians_of(b);
        let verdict = verify::verify(&keyframe, &submap, &initial, &self.config.verify);
        let rejected = match verdict {
            Verdict::Unregistrable => reject(Rejection::Unregistrable, None),
            Verdict::Wandered(fit) => reject(Rejection::Wandered, Some(fit)),
            Verdict::LowOverlap(fit) => reject(Rejection::LowOverlap, Some(fit)),
            Verdict::Degenerate(fit) => reject(Rejection::Degenerate, Some(fit)),
            Verdict::Loop(fit) => {
                let candidate = Loop { a, b, descriptor_distance, fit };
                let margin = consistency::odometry_margin(&self.view(&candidate), &self.config.consistency);
                tracing::debug!(a, b, margin, "odometry check");
                // Within the allowance (eq. 1 of `consistency`).
                if margin <= 1.0 {
                    let candidate = self.refine(candidate);
                    tracing::debug!(a, b, descriptor_distance, overlap = candidate.fit.overlap, "loop verified");
                    self.verified.push(candidate);
                    return true;
                }
                reject(Rejection::Odometry, Some(candidate.fit))
            }
        };
        tracing::debug!(a, b, descriptor_distance, reason = %rejected.reason, "loop candidate rejected");
        self.rejected.push(rejected);
        false
    }

    /// The keyframes around place `a`, in `a`'s frame by odometry, with their covariances.
    fn submap(&mut self, a: usize) -> GaussianCloud {
        let w = self.config.verify.submap_keyframes;
        let range = a.saturating_sub(w)..=(a + w).min(self.places.len() - 1);
        let origin = self.places[a].odometry.inverse();
        let (mut points, mut covariances) = (Vec::new(), Vec::new());
        for k in range {
            let (p, c) = self.gaussians_of(k).transformed(&(origin * self.places[k].odometry));
            points.extend(p);
            covariances.extend(c);
        }
        GaussianCloud::from_parts(points, covariances)
    }

    /// Step 3b: a loop that passed refined on the merged neighbourhoods of both keyframes
    /// ([`verify::refine`]); kept as it was where the refined fit fails the verification or
    /// the odometry test.
    fn refine(&self, l: Loop) -> Loop {
        let w = self.config.verify.refine_keyframes;
        if w == 0 {
            return l;
        }
        let last = self.places.len() - 1;
        let (source, target) = rayon::join(
            || self.merged(l.b, l.b.saturating_sub(w)..=l.b),
            || self.merged(l.a, l.a.saturating_sub(w)..=(l.a + w).min(last)),
        );
        let Some(fit) = verify::refine(&source, &target, &l.fit, &self.config.verify) else { return l };
        let refined = Loop { fit, ..l.clone() };
        if consistency::odometry_margin(&self.view(&refined), &self.config.consistency) <= 1.0 { refined } else { l }
    }

    /// The keyframes in `range` in place `origin`'s frame by odometry ([`verify::neighbourhood`]).
    fn merged(&self, origin: usize, range: std::ops::RangeInclusive<usize>) -> GaussianCloud {
        let to_origin = self.places[origin].odometry.inverse();
        let keyframes = range.map(|k| (&self.places[k].cloud, to_origin * self.places[k].odometry));
        verify::neighbourhood(keyframes, &self.config.verify)
    }

    /// Place `k`'s cloud with covariances, from the cache or estimated now.
    fn gaussians_of(&mut self, k: usize) -> Arc<GaussianCloud> {
        let (cloud, config) = (&self.places[k].cloud, &self.config.verify);
        self.gaussians.get_or_insert(k, config.cached_keyframes, || verify::gaussians(cloud, config))
    }

    /// The verified loop as the consistency tests see it.
    fn view(&self, l: &Loop) -> LoopView {
        let (a, b) = (&self.places[l.a], &self.places[l.b]);
        LoopView {
            odom_a: a.odometry,
            odom_b: b.odometry,
            path_a: a.path_m,
            path_b: b.path_m,
            transform: l.fit.transform,
        }
    }

    /// The second half of step 4: the loops in the graph become the largest consistent set; true
    /// when that changed it.
    fn update_loops_in_graph(&mut self) -> bool {
        let views: Vec<LoopView> = self.verified.iter().map(|l| self.view(l)).collect();
        let set = consistency::largest_consistent_set(&views, &self.config.consistency);
        let changed = set != self.in_graph;
        self.in_graph = set;
        changed
    }

    fn loop_edges(&self) -> Vec<Edge> {
        self.loops()
            .map(|l| Edge {
                from: l.a,
                to: l.b,
                measurement: l.fit.transform,
                information: l.fit.information,
                kind: EdgeKind::Loop,
            })
            .collect()
    }

    /// The loops in the graph, in the order they were found.
    pub fn loops(&self) -> impl Iterator<Item = &Loop> {
        self.in_graph.iter().map(|&i| &self.verified[i])
    }

    /// Every candidate not in the graph: those that failed a test, then the verified ones the
    /// other loops outvoted.
    pub fn rejected(&self) -> Vec<Rejected> {
        let mut all = self.rejected.clone();
        all.extend(self.verified.iter().enumerate().filter(|(i, _)| !self.in_graph.contains(i)).map(|(_, l)| {
            Rejected {
                a: l.a,
                b: l.b,
                descriptor_distance: l.descriptor_distance,
                fit: Some(l.fit.clone()),
                reason: Rejection::Inconsistent,
            }
        }));
        all
    }

    /// The keyframes so far.
    pub fn places(&self) -> &[Place] {
        &self.places
    }

    /// The keyframe poses with the loops applied (odometry frame), by keyframe index.
    pub fn poses(&self) -> &[Isometry3<f64>] {
        self.graph.poses()
    }

    /// How many optimisations have run: 0 while no loop is in the graph.
    pub fn revision(&self) -> u64 {
        self.graph.revision()
    }

    /// The pose of a scan registered at odometry pose `odometry_scan` after keyframe `k`, moved with
    /// that keyframe.
    pub fn follow(&self, k: usize, odometry_scan: &Isometry3<f64>) -> Isometry3<f64> {
        match (self.graph.poses().get(k), self.places.get(k)) {
            (Some(keyframe), Some(place)) => graph::follow(keyframe, &place.odometry, odometry_scan),
            _ => *odometry_scan,
        }
    }

    /// The keyframe pose graph as optimised (for `graph.g2o`): keyframe poses, odometry edges and
    /// the loops.
    pub fn graph(&self) -> Result<PoseGraph, PoseGraphError> {
        graph::build(self.graph.poses(), &self.odometry(), &self.loop_edges(), &self.config.graph)
    }

    /// The keyframes' odometry poses.
    fn odometry(&self) -> Vec<Isometry3<f64>> {
        self.places.iter().map(|p| p.odometry).collect()
    }

    /// The configuration in use.
    pub fn config(&self) -> &LoopConfig {
        &self.config
    }
}
