//! Figures of an odometry run: timing, features, degeneracy (what `stats.json` holds).

pub use cloud::stats::{Low, Spread};
use serde::Serialize;

/// Accumulates per-frame figures during a run.
#[derive(Clone, Debug, Default)]
pub struct RunStats {
    ms: Vec<f64>,
    stages: [Vec<f64>; 3],
    edges: Vec<f64>,
    planes: Vec<f64>,
    degenerate: usize,
    unfitted: usize,
    keyframes: usize,
    conditioning: Vec<f64>,
    recoveries: Recoveries,
    voxel_shape_scans: usize,
    dense: usize,
}

/// How often the prediction's fit was not the one kept, and how often no fit could be trusted.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Recoveries {
    /// Scans whose pose came from a coarse alignment (the second scan, after gaps, suspect fits).
    pub coarse: usize,
    /// Scans whose pose came from a global re-localisation.
    pub global: usize,
    /// Scans judged lost: even the best fit matched too few features; kept out of the map.
    pub lost: usize,
}

/// The summary written as `stats.json`.
#[derive(Clone, Debug, Serialize)]
pub struct RunSummary {
    /// Scans registered.
    pub frames: usize,
    /// Wall time per scan, milliseconds (feature extraction, registration, map update).
    pub ms_per_frame: Spread,
    /// The same split by stage: features, registration (deskew + pose), map update.
    pub ms_features: Spread,
    /// Registration time per scan, milliseconds.
    pub ms_registration: Spread,
    /// Map update time per scan, milliseconds.
    pub ms_map: Spread,
    /// Edge features per scan.
    pub edge_features: Spread,
    /// Plane features per scan (after thinning).
    pub plane_features: Spread,
    /// Scans whose pose problem was ill-conditioned (the motion prior was kept along some direction).
    pub degenerate_frames: usize,
    /// Scans after the first whose fit found fewer matches than it needs (the feature fit's
    /// `solver.min_matches`, the dense fit's 30 points): nothing measured their pose, which is the
    /// motion model's extrapolation. Any is a warning; many mean the odometry is not tracking.
    pub unfitted_scans: usize,
    /// Conditioning of the pose problem (smallest eigenvalue over the sum of weights): the lowest
    /// value, the 5th percentile and the median over the scans after the first.
    pub conditioning: Low,
    /// Keyframes made.
    pub keyframes: usize,
    /// Scans located from another start than the prediction, and scans judged lost.
    pub recoveries: Recoveries,
    /// Scans without a ring channel, whose features came from voxel shapes instead of rings.
    pub voxel_shape_scans: usize,
    /// Scans whose pose came from the dense fit of the whole scan against the local map of points:
    /// their features were too few for the feature fit to measure the pose.
    pub dense_scans: usize,
}

impl RunStats {
    /// Records one frame.
    pub fn add(&mut self, frame: &super::Frame, ms: f64) {
        self.ms.push(ms);
        let t = &frame.timings;
        for (stage, v) in self.stages.iter_mut().zip([t.features, t.registration, t.map]) {
            stage.push(v);
        }
        self.edges.push(frame.edges as f64);
        self.planes.push(frame.planes as f64);
        self.degenerate += usize::from(frame.degenerate);
        self.unfitted += usize::from(self.ms.len() > 1 && frame.iterations == 0);
        self.keyframes += usize::from(frame.keyframe.is_some());
        self.recoveries.coarse += usize::from(frame.start == super::Start::Coarse);
        self.recoveries.global += usize::from(frame.start == super::Start::Global);
        self.recoveries.lost += usize::from(frame.lost);
        self.voxel_shape_scans += usize::from(frame.feature_kind == super::features::FeatureKind::VoxelShape);
        self.dense += usize::from(frame.fit == super::Fit::Dense);
        if self.ms.len() > 1 {
            self.conditioning.push(frame.conditioning);
        }
    }

    /// Wall time per scan so far, milliseconds, in scan order.
    pub fn ms(&self) -> &[f64] {
        &self.ms
    }

    /// Time per scan of each stage (features, registration, map), milliseconds, in scan order.
    pub fn stages(&self) -> &[Vec<f64>; 3] {
        &self.stages
    }

    /// The summary so far.
    pub fn summary(&self) -> RunSummary {
        RunSummary {
            frames: self.ms.len(),
            ms_per_frame: Spread::of(&self.ms),
            ms_features: Spread::of(&self.stages[0]),
            ms_registration: Spread::of(&self.stages[1]),
            ms_map: Spread::of(&self.stages[2]),
            edge_features: Spread::of(&self.edges),
            plane_features: Spread::of(&self.planes),
            degenerate_frames: self.degenerate,
            unfitted_scans: self.unfitted,
            conditioning: Low::of(&self.conditioning),
            keyframes: self.keyframes,
            recoveries: self.recoveries,
            voxel_shape_scans: self.voxel_shape_scans,
            dense_scans: self.dense,
        }
    }
}
