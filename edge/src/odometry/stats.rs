//! Figures of an odometry run: timing, features, degeneracy (what `stats.json` holds).

use serde::Serialize;

/// Median, 95th percentile and maximum of a series.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Spread {
    /// Median.
    pub median: f64,
    /// 95th percentile (nearest rank).
    pub p95: f64,
    /// Maximum.
    pub max: f64,
}

impl Spread {
    /// The spread of `values` (all zero when empty).
    pub fn of(values: &[f64]) -> Self {
        if values.is_empty() {
            return Spread::default();
        }
        let mut v = values.to_vec();
        v.sort_by(f64::total_cmp);
        let rank = |q: f64| v[((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1];
        Spread { median: rank(0.5), p95: rank(0.95), max: v[v.len() - 1] }
    }
}

/// Accumulates per-frame figures during a run.
#[derive(Clone, Debug, Default)]
pub struct RunStats {
    ms: Vec<f64>,
    stages: [Vec<f64>; 3],
    edges: Vec<f64>,
    planes: Vec<f64>,
    degenerate: usize,
    keyframes: usize,
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
    /// Keyframes made.
    pub keyframes: usize,
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
        self.keyframes += usize::from(frame.keyframe.is_some());
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
            keyframes: self.keyframes,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_by_hand() {
        let v: Vec<f64> = (1..=20).map(f64::from).collect();
        // Nearest rank: median = 10th of 20, p95 = 19th.
        assert_eq!(Spread::of(&v), Spread { median: 10.0, p95: 19.0, max: 20.0 });
        assert_eq!(Spread::of(&[]), Spread::default());
        assert_eq!(Spread::of(&[3.0]), Spread { median: 3.0, p95: 3.0, max: 3.0 });
    }
}
