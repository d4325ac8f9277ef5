//! Step 1 — everything about one map that does not depend on the others, computed once per revision.

use std::sync::Arc;

use cloud::PointCloud;
use cloud::memory::HeapSize;
use cloud::registration::{GaussianCloud, MIN_POINTS};
use cloud::visibility::Views;
use cloud::voxel::downsample;

use super::MergeConfig;
use crate::pairwise::{FeatureError, Features};

/// One map ready for pairwise estimates: its finite points, features and VGICP Gaussians.
pub struct PreparedMap {
    /// Finite points of the map it was prepared from (the cloud itself is not kept: the merger
    /// holds the newest one, from which the global map is built).
    pub points: usize,
    /// Points dropped because a coordinate was NaN or infinite.
    pub dropped_non_finite: usize,
    /// Pairwise features, or why the map cannot be registered.
    pub features: Result<Features, FeatureError>,
    /// Features at [`MergeConfig::coarse`], when configured and computable.
    pub coarse: Option<Features>,
    /// The map at [`MergeConfig::refine_voxel`] with covariances; `None` when too small to refine.
    pub fine: Option<GaussianCloud>,
    /// The map at [`super::FinishConfig::voxel`] with covariances, when a finishing pass is configured.
    pub finish: Option<GaussianCloud>,
    /// What the robot's sensor saw, keyframe by keyframe, when the map came with it
    /// ([`super::Merger::set_views`]): the free space another map placed here must respect.
    pub views: Option<Arc<Views>>,
    /// Points whose results were taken over from the preparation it grew from
    /// ([`PreparedMap::grown`]).
    pub reused: Reused,
}

/// Points of a preparation taken over from an earlier one, per product.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Reused {
    /// Covariances of [`PreparedMap::fine`].
    pub fine: usize,
    /// Covariances of [`PreparedMap::finish`].
    pub finish: usize,
}

impl HeapSize for PreparedMap {
    /// Features and Gaussians; the views are the station's, shared, and counted there.
    fn heap_bytes(&self) -> usize {
        self.features.as_ref().map_or(0, HeapSize::heap_bytes)
            + self.coarse.as_ref().map_or(0, HeapSize::heap_bytes)
            + self.fine.as_ref().map_or(0, HeapSize::heap_bytes)
            + self.finish.as_ref().map_or(0, HeapSize::heap_bytes)
    }
}

impl PreparedMap {
    /// Drops non-finite points, then computes the features and the VGICP Gaussians concurrently;
    /// `views` are the map's keyframe views, if known.
    pub fn new(cloud: PointCloud, views: Option<Arc<Views>>, config: &MergeConfig) -> Self {
        Self::prepare(cloud, views, config, None)
    }

    /// The preparation of `cloud`, a later revision of the map `earlier` was prepared from: the
    /// same as [`PreparedMap::new`] gives, with every result whose neighbourhood did not change
    /// taken over from `earlier` (a map grown by keyframes is estimated again around them only).
    pub fn grown(cloud: PointCloud, views: Option<Arc<Views>>, config: &MergeConfig, earlier: &PreparedMap) -> Self {
        Self::prepare(cloud, views, config, Some(earlier))
    }

    fn prepare(
        mut cloud: PointCloud,
        views: Option<Arc<Views>>,
        config: &MergeConfig,
        earlier: Option<&PreparedMap>,
    ) -> Self {
        let dropped_non_finite = cloud.retain_finite();
        let ((features, coarse), (fine, finish)) = rayon::join(
            || {
                rayon::join(
                    || Features::compute(&cloud, &config.pairwise.global),
                    || config.coarse.as_ref().and_then(|c| Features::compute(&cloud, &c.global).ok()),
                )
            },
            || {
                rayon::join(
                    || {
                        let earlier = earlier.and_then(|e| e.fine.as_ref());
                        gaussians(&cloud, config.refine_voxel, config.refine.neighbours, earlier)
                    },
                    || {
                        let earlier = earlier.and_then(|e| e.finish.as_ref());
                        let f = config.finish.as_ref()?;
                        gaussians(&cloud, f.voxel, f.registration.neighbours, earlier)
                    },
                )
            },
        );
        let reused = Reused { fine: fine.as_ref().map_or(0, |g| g.1), finish: finish.as_ref().map_or(0, |g| g.1) };
        let (fine, finish) = (fine.map(|g| g.0), finish.map(|g| g.0));
        Self { points: cloud.len(), dropped_non_finite, features, coarse, fine, finish, views, reused }
    }

    /// The features if the map is usable.
    pub fn usable(&self) -> Option<&Features> {
        self.features.as_ref().ok()
    }

    /// The coarse features if the map is usable at both scales.
    pub fn usable_coarse(&self) -> Option<&Features> {
        self.usable().and(self.coarse.as_ref())
    }
}

/// The map downsampled to `voxel` with covariances over `neighbours` points, if enough points
/// remain to fix a pose, and how many covariances were taken over from `earlier`.
fn gaussians(
    cloud: &PointCloud,
    voxel: f32,
    neighbours: usize,
    earlier: Option<&GaussianCloud>,
) -> Option<(GaussianCloud, usize)> {
    let down = downsample(cloud, voxel).ok()?;
    // Covariances need a neighbourhood; fewer points than neighbours gives no usable shape.
    (down.len() >= MIN_POINTS.max(neighbours)).then(|| {
        let grown = GaussianCloud::regrown(earlier, &down.points, neighbours);
        (grown.cloud, grown.reused)
    })
}
