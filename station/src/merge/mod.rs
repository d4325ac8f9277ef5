//! Merging N robot maps into one global map (paper §4, after map_merge_3d).
//!
//! 1. **Per map, once** ([`map::PreparedMap`]): the pairwise features (finite points, voxel grid,
//!    outlier filter, normals, Harris keypoints, FPFH) and the Gaussians VGICP needs.
//! 2. **Per pair, in parallel** ([`estimate::estimate_pair`]): global registration
//!    ([`crate::pairwise::align`]); when it finds no reliable transform and
//!    [`MergeConfig::coarse`] is set (indoor), the same at 0.4 m, polished on the fine surfels;
//!    when that gives no edge and the maps' places show a candidate overlap ([`places`]: two
//!    keyframes that look alike), the same on the features within the descriptor's range of the
//!    two keyframes only ([`cloud::global::Around`]: a small shared part of two large maps, whose
//!    correct correspondences are a small share of all). Then VGICP refinement started from it
//!    ([`cloud::registration::align_gaussians`], VGICP). The refinement is kept
//!    only if it converged to a transform within [`MergeConfig::max_refine_translation`] /
//!    [`MergeConfig::max_refine_rotation_deg`] of the global one (VGICP that runs off locked onto
//!    a wrong structure) and does not leave a larger mean squared point-to-plane distance than the
//!    global transform, over the VGICP input points within [`MergeConfig::refine_voxel`] of the
//!    other map under both; otherwise the global transform stands (a tracked link keeps its
//!    previous transform the same way, [`estimate::Refinement`]). Outdoor, a last VGICP pass on
//!    finer input ([`MergeConfig::finish`]) takes the centimetre the 1 m voxels leave down to
//!    millimetres; it is kept if it moved less than [`FinishConfig::max_translation`] /
//!    [`FinishConfig::max_rotation_deg`] and leaves no larger truncated mean squared
//!    point-to-plane distance.
//! 3. **Confidence.** What is published per edge is the *overlap-aware score*
//!    `s = √(overlap · inlier_ratio)` of [`crate::pairwise::confidence`], recomputed at the final
//!    (refined) transform: `overlap` is the share of source surfels with a target surfel within
//!    1.5 voxels, `inlier_ratio` the RANSAC inlier share (of the correspondences around the
//!    shared place, for a link found there: the evidence where the maps overlap). map_merge_3d's
//!    fitness `1 / mean(d²)` is reported next to it ([`crate::pairwise::Confidence::fitness`]) but not used for decisions: unrelated maps whose
//!    floors coincide score a high fitness. An edge enters the match graph when the pairwise
//!    checks pass (inliers, overlap, score), `s ≥` [`MergeConfig::min_confidence`] — default
//!    **0.09 outdoor** and **0.12 indoor** (the pairwise default) — and the pair is not ambiguous
//!    ([`ambiguity`]: no distinct transform with more than half the inliers *and* more than half
//!    the upright support, the share of wall-like surfels landing on a parallel target surface).
//!    For maps that came with their keyframes' views ([`Merger::set_views`]: the station's), the
//!    placement must also not contradict what the robots saw: Birk & Carpin's acceptance index
//!    `ω = agr / (agr + dis)` of both maps' surfels against the other's range images
//!    ([`cloud::visibility`]) at least [`MergeConfig::min_acceptance`] (0.95). Look-alike streets
//!    pass every other check on young maps; they put walls where the other robot saw through.
//!    The scores of a transform found by the coarse fallback are measured on the coarse features.
//!    Both thresholds sit between what the true and the false pairs of the simulated scenarios
//!    measure; `station/tests/merge.rs` asserts those measurements.
//! 4. **Match graph** ([`graph`]): a maximum spanning forest on the scores (Kruskal); the reference
//!    component is the one holding [`MergeConfig::reference`] or else the largest one; its
//!    reference map is the configured one or else the tree centre (least maximum hop count, so no
//!    chain of estimates is longer than needed). Global transforms are chained along the tree.
//!    Maps outside the reference component are reported [`MapStatus::Unmerged`] with a reason and
//!    the identity: never forced in.
//! 5. **Global map** (paper eq. 11): the union of the merged maps, each moved by its global
//!    transform, voxelised at [`MergeConfig::output_voxel`] to fuse duplicates.
//!
//! A map's published confidence is the lowest edge score on its tree path to the reference (the
//! weakest link bounds the whole chain); the reference itself has 1. [`Merger`] keeps per-map
//! preparations and pairwise results by the preparations they were computed on, so updating one
//! map recomputes only its pairs; a map that only grows is prepared again once it has grown by
//! [`MergeConfig::refresh_growth`], a linked pair is then tracked from its last transform
//! ([`track_pair`]) instead of searched again, and a merge runs at most
//! [`MergeConfig::max_searches`] global registrations (see [`merger`]). That estimation is a
//! [`Round`] that can run on other threads while the merger composes global maps from the
//! placements found so far (the station does). Bad input (empty or tiny maps, NaN points) gives an unmerged map with
//! a reason, never a panic.

pub mod ambiguity;
mod assembly;
pub mod estimate;
pub mod files;
pub mod graph;
pub mod map;
pub mod merger;
pub mod places;
mod round;

use std::time::Duration;

use cloud::registration::RegistrationConfig;
use cloud::visibility::VisibilityConfig;
use cloud::{PointCloud, Preset};
use nalgebra::Isometry3;

use crate::pairwise::{FeatureError, PairwiseConfig};
use places::PlaceConfig;

pub use estimate::{Edge, PairRejection, PairVerdict, estimate_pair, keep_link, track_pair};
pub use map::{PreparedMap, Reused};
pub use merger::{Merger, MergerStats, Round, RoundTiming};

/// Default edge threshold of [`MergeConfig::outdoor`].
pub const OUTDOOR_MIN_CONFIDENCE: f64 = 0.09;

/// Default edge threshold of [`MergeConfig::indoor`] (the pairwise default `min_score`).
pub const INDOOR_MIN_CONFIDENCE: f64 = 0.12;

/// Default [`MergeConfig::min_acceptance`].
pub const DEFAULT_MIN_ACCEPTANCE: f64 = 0.95;

/// The finishing VGICP pass: millimetres where the 0.25 m refinement leaves a centimetre.
///
/// The outdoor refinement needs large voxels and a wide reach to converge from a decimetre-level
/// global estimate, and its 1 m voxel means then bias the result by about a centimetre (5-11 mm on
/// warehouse-large). From there a pass on 0.2 m input with 0.3 m voxels converges in two or three
/// iterations to 0.1-0.3 mm, for a fifth of the cost of refining on 0.1 m input.
#[derive(Clone, Debug, PartialEq)]
pub struct FinishConfig {
    /// Voxel the maps are downsampled to for this pass, metres (default 0.2).
    pub voxel: f32,
    /// The VGICP settings (default: 0.3 m voxels and correspondences, 10 neighbours per
    /// covariance, no coarser level).
    pub registration: RegistrationConfig,
    /// The pass may move the refined transform by at most this much, metres (default 0.05: it
    /// starts within a centimetre or two; more is a slide along a weakly constrained direction).
    pub max_translation: f64,
    /// The pass may turn the refined transform by at most this much, degrees (default 0.5: it corrects hundredths of
    /// a degree; a turn about the map origin moves far points while the translation stays small).
    pub max_rotation_deg: f64,
}

impl FinishConfig {
    /// The outdoor finishing pass.
    pub fn outdoor() -> Self {
        Self {
            voxel: 0.2,
            registration: RegistrationConfig {
                voxel_resolution: 0.3,
                max_correspondence_distance: 0.3,
                neighbours: 10,
                coarse_levels: 0,
                ..RegistrationConfig::default()
            },
            max_translation: 0.05,
            max_rotation_deg: 0.5,
        }
    }
}

/// Every setting of the merge.
#[derive(Clone, Debug, PartialEq)]
pub struct MergeConfig {
    /// Global registration of each pair (default [`PairwiseConfig::outdoor`]).
    pub pairwise: PairwiseConfig,
    /// A second, coarser global registration tried when `pairwise` finds no reliable transform
    /// (outdoor `None`; indoor [`PairwiseConfig::outdoor`]'s 0.4 m features with the indoor
    /// `min_score`). Its transform is polished on `pairwise`'s surfels before refinement.
    pub coarse: Option<PairwiseConfig>,
    /// VGICP refinement (outdoor: 1 m voxels, 1 m correspondences; indoor 0.3 m / 0.3 m).
    pub refine: RegistrationConfig,
    /// Voxel the maps are downsampled to for VGICP, metres (outdoor 0.25, indoor 0.1).
    pub refine_voxel: f32,
    /// A last, finer VGICP pass from the refined transform (outdoor: see [`FinishConfig::outdoor`];
    /// indoor `None`, its refinement already runs on 0.1 m input).
    pub finish: Option<FinishConfig>,
    /// VGICP may move the global transform by at most this much, metres (outdoor 1.0, indoor 0.3).
    pub max_refine_translation: f64,
    /// VGICP may turn the global transform by at most this much, degrees (default 5).
    pub max_refine_rotation_deg: f64,
    /// Edges scoring below this are dropped from the match graph (outdoor 0.09, indoor 0.12; the
    /// pairwise `min_score` of the preset is set to the same value).
    pub min_confidence: f64,
    /// A pair is refused as ambiguous when a distinct alternative transform has more than this
    /// share of the chosen one's RANSAC inliers and of its upright support (default 0.5).
    pub max_ambiguity: f64,
    /// Alternatives closer than this to the chosen transform (mean keypoint displacement) are the
    /// same answer, not an alternative, metres (outdoor 4, indoor 1: four RANSAC inlier distances).
    pub ambiguity_distance: f64,
    /// Index of the map whose frame is the global frame (default `None`: the tree centre).
    pub reference: Option<usize>,
    /// Voxel of the merged global map, metres (outdoor 0.2, indoor 0.1).
    pub output_voxel: f32,
    /// Growing maps (see [`Merger::grow`]): a map is prepared again, and its pairs estimated
    /// again, once it has this share more points than when it was last prepared (default 0.25).
    /// In between, the global map takes its newest points at the placement estimated on the last
    /// preparation: the transform between two robots' frames does not change as they drive on.
    pub refresh_growth: f64,
    /// The same for a map that the last merge placed in the global map, once every usable map is
    /// placed (default 1.0: at every doubling). Its placement does not change as it grows, so
    /// preparing it again then serves only to re-examine its links on more evidence; preparing
    /// every growing map at `refresh_growth` kept a 16-robot station preparing two maps in every
    /// merge. While a usable map is unplaced, its searches need the others' newest parts (an
    /// overlap is often in what a robot mapped last), so every map is prepared at
    /// `refresh_growth`, unplaced ones first.
    pub merged_refresh_growth: f64,
    /// A linked pair is tracked from its last transform when its maps change; the global
    /// registration runs again, with every check, once either map has this share more points than
    /// when the link was last found that way (default 1.0: at every doubling), so that a link made
    /// on small maps is re-examined on the larger evidence.
    pub reverify_growth: f64,
    /// Most global registrations per round of estimation (default 8); the other pairs waiting
    /// for one keep their last verdict (or [`PairRejection::Pending`]) and the round reports them
    /// as pending, so another round follows. Bounds a round's time however large the fleet.
    pub max_searches: usize,
    /// Most grown maps prepared again per round, the most grown first (default 2, a map per core
    /// of a small station: preparing is the costliest step of a round); new maps and
    /// maps whose shape changed are always prepared.
    pub max_refreshes: usize,
    /// How the free space the robots saw is checked ([`cloud::visibility`]; outdoor
    /// [`VisibilityConfig::outdoor`], indoor [`VisibilityConfig::indoor`]). Used only for maps given
    /// their views ([`Merger::set_views`]): maps from files have none and skip the check.
    pub visibility: VisibilityConfig,
    /// An edge is refused when the acceptance index `ω = agr / (agr + dis)` of its placement, both
    /// maps' surfels judged against the other's views, is below this (default 0.95, see
    /// [`cloud::visibility`]). True placements measure 0.98-1.0 (KITTI 00 and 08's reverse
    /// revisit at their reference poses, moving cars included; the simulated campus and
    /// warehouses, the door of `warehouse-small`), wrong ones 0.40-0.79 (the same scans shifted
    /// 5-10 m or turned 90-180°; look-alike campus streets), 0.73-0.85 (the other hall of
    /// `warehouse-small`) and 0.86-0.91 (the identical halls of `aisles`, whose first robot's map
    /// is a metre off: 0.9 let one through).
    pub min_acceptance: f64,
    /// Surfels of each map judged against the other's views (default 5,000).
    pub acceptance_samples: usize,
    /// A global registration short only of RANSAC inliers (at least this many, fewer than the
    /// pairwise `min_inliers`; its overlap and score pass) is judged on what the robots saw
    /// instead, when both maps have views (default 10; 0 turns it off). Two maps that share only
    /// what each saw through a door give the true placement 10-15 inliers, some draws 14, and
    /// the fixed count cannot tell it from look-alikes (wrong placements drew 10-14 there);
    /// the free space can: the door's 1.00 against 0.74-0.84.
    pub near_miss_inliers: usize,
    /// Such a near miss (see `near_miss_inliers`) is kept only when its acceptance is at least
    /// this (default 0.97, stricter than
    /// `min_acceptance`: weaker feature evidence asks for cleaner geometry; true placements
    /// measure 0.98-1.0).
    pub near_miss_acceptance: f64,
    /// When the free space contradicts a pair's best placement, the next distinct placements
    /// (RANSAC again on the correspondences that disagree with those refused) are judged in turn,
    /// up to this many (default 2; 0 turns it off). Only for maps with views. Each costs a RANSAC,
    /// a refinement and the checks, a fraction of the maps' features.
    pub max_alternatives: usize,
    /// Largest tilt of a placement, degrees: the angle between one map's vertical and the
    /// other's (default 30; 180 turns the check off). The robots' frames are their sensors' at
    /// their first sweeps, upright on ground robots to within the slope they started on and
    /// the mount: a placement that turns one map on its side or upside down is a look-alike.
    /// The free space cannot refute one: a map turned upside down about the ground lies below
    /// the other's ground, where no ray went. Measured: two young campus streets matched so
    /// (roll 180 deg about the ground, 20 inliers, every sampled surfel agreeing) and the
    /// station published a robot 153 m / 180 deg off; with the check the 16- and 32-robot campus
    /// loads (rolling ground) and every demo still place all the robots they placed before.
    /// Set it to 180 for fleets whose sensors are not mounted upright (handheld, aerial).
    pub max_tilt_deg: f64,
    /// How the maps' place descriptors are compared for candidate overlaps (default
    /// [`PlaceConfig::default`]). Used only for maps given their places ([`Merger::set_places`]).
    pub places: PlaceConfig,
}

impl Default for MergeConfig {
    fn default() -> Self {
        Self::outdoor()
    }
}

impl MergeConfig {
    /// The settings of a named preset: [`Self::indoor`] or [`Self::outdoor`].
    pub fn preset(preset: Preset) -> Self {
        match preset {
            Preset::Indoor => Self::indoor(),
            Preset::Outdoor => Self::outdoor(),
        }
    }

    /// Streets, campuses: 0.4 m features, 0.25 m VGICP input, 0.2 m output, confidence ≥ 0.09.
    pub fn outdoor() -> Self {
        let mut pairwise = PairwiseConfig::outdoor();
        // Lowered from the pairwise 0.12: the true pairs of the simulated campus score 0.097-0.23
        // (rolling ground, sparse maps), an unrelated look-alike street 0.06-0.08; the ambiguity
        // test is the second guard against aliasing.
        pairwise.confidence.min_score = OUTDOOR_MIN_CONFIDENCE;
        Self {
            pairwise,
            coarse: None,
            refine: RegistrationConfig::default(),
            refine_voxel: 0.25,
            finish: Some(FinishConfig::outdoor()),
            max_refine_translation: 1.0,
            max_refine_rotation_deg: 5.0,
            min_confidence: OUTDOOR_MIN_CONFIDENCE,
            max_ambiguity: 0.5,
            ambiguity_distance: 4.0,
            reference: None,
            output_voxel: 0.2,
            refresh_growth: 0.25,
            merged_refresh_growth: 1.0,
            reverify_growth: 1.0,
            max_searches: 8,
            max_refreshes: 2,
            visibility: VisibilityConfig::outdoor(),
            min_acceptance: DEFAULT_MIN_ACCEPTANCE,
            acceptance_samples: 5_000,
            near_miss_inliers: 10,
            near_miss_acceptance: 0.97,
            max_alternatives: 2,
            max_tilt_deg: 30.0,
            places: PlaceConfig::default(),
        }
    }

    /// Rooms, warehouses: 0.1 m features (0.4 m when they fail), VGICP input and output,
    /// confidence ≥ 0.12.
    pub fn indoor() -> Self {
        // Fine features need both robots to have sampled the common part alike; where one saw it
        // only from afar (through a door) its 0.1 m voxels hold LiDAR rings, not surfaces, and
        // only the 0.4 m grid, which fills the gaps between rings, describes it as the other map.
        let mut coarse = PairwiseConfig::outdoor();
        coarse.confidence.min_score = INDOOR_MIN_CONFIDENCE;
        Self {
            pairwise: PairwiseConfig::indoor(),
            coarse: Some(coarse),
            min_confidence: INDOOR_MIN_CONFIDENCE,
            refine: RegistrationConfig {
                voxel_resolution: 0.3,
                max_correspondence_distance: 0.3,
                ..RegistrationConfig::default()
            },
            refine_voxel: 0.1,
            finish: None,
            max_refine_translation: 0.3,
            ambiguity_distance: 1.0,
            output_voxel: 0.1,
            visibility: VisibilityConfig::indoor(),
            ..Self::outdoor()
        }
    }

    /// Checks every setting.
    pub fn validate(&self) -> Result<(), MergeError> {
        self.pairwise.validate().map_err(MergeError::Config)?;
        self.visibility.validate().map_err(|e| MergeError::Config(FeatureError::InvalidConfig(e)))?;
        if let Some(c) = &self.coarse {
            c.validate().map_err(MergeError::Config)?;
        }
        let positive = |v: f64| v > 0.0 && v.is_finite();
        let finish_ok = self.finish.as_ref().is_none_or(|f| {
            positive(f64::from(f.voxel)) && positive(f.max_translation) && positive(f.max_rotation_deg)
        });
        let ok = finish_ok
            && positive(f64::from(self.refine_voxel))
            && positive(f64::from(self.output_voxel))
            && positive(self.max_refine_translation)
            && positive(self.max_refine_rotation_deg)
            && self.min_confidence.is_finite()
            && self.max_ambiguity.is_finite()
            && positive(self.ambiguity_distance)
            && positive(self.refresh_growth)
            && positive(self.merged_refresh_growth)
            && positive(self.reverify_growth)
            && self.max_searches > 0
            && (0.0..=1.0).contains(&self.min_acceptance)
            && (0.0..=1.0).contains(&self.near_miss_acceptance)
            && self.acceptance_samples > 0
            && positive(self.max_tilt_deg)
            && self.places.candidates > 0
            && (0.0..=1.0).contains(&self.places.max_distance)
            && positive(self.refine.voxel_resolution)
            && positive(self.refine.max_correspondence_distance);
        if !ok {
            return Err(MergeError::Config(FeatureError::InvalidConfig(
                "merge voxels, refinement limits, growth shares, max_searches, max_tilt_deg, place candidates and min_confidence must be positive and finite, min_acceptance, near_miss_acceptance and the place max_distance within [0, 1]",
            )));
        }
        Ok(())
    }
}

/// Why a merge could not run at all (per-map problems are [`Unmerged`] reasons instead).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum MergeError {
    /// A setting is out of range.
    #[error("invalid merge configuration: {0}")]
    Config(FeatureError),
    /// The configured reference map does not exist.
    #[error("reference map {reference} does not exist ({maps} maps)")]
    NoSuchReference {
        /// The index asked for.
        reference: usize,
        /// Maps available.
        maps: usize,
    },
    /// The configured reference map cannot be registered at all.
    #[error("reference map {reference} is unusable: {reason}")]
    UnusableReference {
        /// The index asked for.
        reference: usize,
        /// Why its features failed.
        reason: FeatureError,
    },
    /// The threads that run rounds of estimation could not be started.
    #[error("cannot start the estimation threads: {0}")]
    Threads(String),
}

/// Why a map was left out of the global map.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum Unmerged {
    /// The map itself cannot be registered (empty, tiny, all NaN, no keypoints).
    #[error("unusable map: {0}")]
    Unusable(FeatureError),
    /// No pair with this map passed the reliability checks.
    #[error("no reliable overlap with any other map")]
    NoOverlap,
    /// It aligns with other maps, but none connected to the reference map.
    #[error("aligned only with maps outside the reference component")]
    OtherComponent,
    /// It has not been prepared yet: a round of estimation is still to take it.
    #[error("waiting for its first preparation")]
    Waiting,
}

/// Where a map ended up.
#[derive(Clone, Debug, PartialEq)]
pub enum MapStatus {
    /// In the global map.
    Merged {
        /// Maps this map's points into the global (reference) frame.
        transform: Isometry3<f64>,
        /// Lowest edge score on the tree path to the reference (1 for the reference).
        confidence: f64,
        /// Tree hops to the reference.
        hops: usize,
    },
    /// Left out, with the reason.
    Unmerged(Unmerged),
}

/// One input map in the result.
#[derive(Clone, Debug, PartialEq)]
pub struct MapReport {
    /// The map's id (its index for [`merge`]).
    pub id: usize,
    /// The revision that was merged.
    pub revision: u64,
    /// Finite points of the map as given.
    pub points: usize,
    /// Points dropped because a coordinate was NaN or infinite.
    pub dropped_non_finite: usize,
    /// Merged or not, and why.
    pub status: MapStatus,
}

impl MapReport {
    /// The global transform, the identity for an unmerged map.
    pub fn transform(&self) -> Isometry3<f64> {
        match &self.status {
            MapStatus::Merged { transform, .. } => *transform,
            MapStatus::Unmerged(_) => Isometry3::identity(),
        }
    }

    /// The published confidence, 0 for an unmerged map.
    pub fn confidence(&self) -> f64 {
        match &self.status {
            MapStatus::Merged { confidence, .. } => *confidence,
            MapStatus::Unmerged(_) => 0.0,
        }
    }

    /// True when the map is in the global map.
    pub fn is_merged(&self) -> bool {
        matches!(self.status, MapStatus::Merged { .. })
    }
}

/// One evaluated pair (`a < b` by position in [`MergeReport::maps`]).
#[derive(Clone, Debug, PartialEq)]
pub struct PairReport {
    /// Position of the first map.
    pub a: usize,
    /// Position of the second map.
    pub b: usize,
    /// The verdict.
    pub verdict: PairVerdict,
    /// True when the verdict came from the cache.
    pub cached: bool,
}

impl PairReport {
    /// True when the pair was never estimated: it waits for a global registration a later round
    /// will run.
    pub fn pending(&self) -> bool {
        matches!(self.verdict, PairVerdict::Rejected { reason: PairRejection::Pending, .. })
    }
}

/// Wall time of each stage of one merge.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MergeTiming {
    /// Per-map preparation (features, Gaussians) of the maps that changed.
    pub features: Duration,
    /// Pairwise estimates of the pairs that changed.
    pub pairs: Duration,
    /// Of `pairs`: comparing the places of the pairs waiting for a search.
    pub places: Duration,
    /// Spanning tree, reference and chaining.
    pub graph: Duration,
    /// Union and voxel grid of the global map.
    pub assemble: Duration,
    /// End to end.
    pub total: Duration,
}

/// The outcome of a merge.
#[derive(Clone, Debug)]
pub struct MergeReport {
    /// Every input map, in id order.
    pub maps: Vec<MapReport>,
    /// Every pair of usable maps with its verdict.
    pub pairs: Vec<PairReport>,
    /// Position in `maps` of the reference map, if any map is usable.
    pub reference: Option<usize>,
    /// Pairs (positions in `maps`) of the spanning tree that the transforms were chained along.
    pub tree: Vec<(usize, usize)>,
    /// The global map (paper eq. 11), in the reference frame.
    pub global_map: PointCloud,
    /// Per point of `global_map`, the id of the map it came from (of a voxel's first point when
    /// several maps met in it): what a viewer colours by.
    pub origins: Vec<usize>,
    /// Time per stage.
    pub timing: MergeTiming,
    /// Work the last round left for the next one (pairs over [`MergeConfig::max_searches`], grown
    /// maps over [`MergeConfig::max_refreshes`]): merge again even if nothing changes.
    pub pending: usize,
    /// The last round settled ([`Merger::settle`]), left nothing pending, and no map changed since:
    /// what a merge from scratch of the current maps gives (but for links kept, see
    /// [`Merger::settle`]).
    pub settled: bool,
}

impl MergeReport {
    /// The accepted edges of the match graph.
    pub fn edges(&self) -> impl Iterator<Item = &Edge> {
        self.pairs.iter().filter_map(|p| p.verdict.edge())
    }

    /// How many maps were merged.
    pub fn merged(&self) -> usize {
        self.maps.iter().filter(|m| m.is_merged()).count()
    }
}

/// Merges `maps` (map `i` gets id `i`, revision 0) in one go.
pub fn merge(maps: &[PointCloud], config: &MergeConfig) -> Result<MergeReport, MergeError> {
    let mut merger = Merger::new(config.clone())?;
    for (i, m) in maps.iter().enumerate() {
        merger.update(i, 0, m.clone());
    }
    merger.merge()
}
