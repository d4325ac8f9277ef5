//! How far to trust the constant-velocity prediction: KISS-ICP's adaptive threshold (Vizzo et al.,
//! RA-L 2023, section III-C), kept as a running estimate of the prediction's error.
//!
//! After each scan the deviation between the predicted and the estimated pose is turned into the
//! largest displacement it causes on a point at the sensor's range (eq. 9), and σ is the root mean
//! square of these over the scans that moved (eq. 10). A fit is expected within 3σ of the
//! prediction. Until a scan has moved there is no evidence: σ is the initial value, large, and the
//! odometry aligns coarse to fine rather than from a prediction it cannot trust.

use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

/// Settings of the prediction-error model.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct MotionModelConfig {
    /// σ before any scan has moved, and after a gap in the stamps (m). Default 2 m (KISS-ICP's
    /// `initial_threshold`): a car at 15 m/s moves 1.5 m between 10 Hz sweeps.
    pub initial_sigma: f64,
    /// Scans that moved less than this (m, and the rotation's displacement at `range`) do not
    /// update σ: standing still says nothing about how well motion is predicted. Default 0.1 m
    /// (KISS-ICP's `min_motion_th`).
    pub min_motion: f64,
    /// Range at which a rotation's displacement is measured (m). Default 50 m: half the features'
    /// usual range crop, where most matched structure lies.
    pub range: f64,
    /// Above this many seconds between two sweeps' stamps the prediction is distrusted again
    /// (σ back to its initial value). Default 1.5 s: a dropped sweep or two at 1 Hz is not a gap.
    pub gap_s: f64,
}

impl Default for MotionModelConfig {
    fn default() -> Self {
        MotionModelConfig { initial_sigma: 2.0, min_motion: 0.1, range: 50.0, gap_s: 1.5 }
    }
}

/// Eq. 9: the largest displacement `deviation` causes on a point within `range` of the sensor,
/// `‖t‖ + 2 r sin(θ / 2)`.
pub fn displacement(deviation: &Isometry3<f64>, range: f64) -> f64 {
    deviation.translation.vector.norm() + 2.0 * range * (deviation.rotation.angle() / 2.0).sin()
}

/// How far the last motion is carried forward to predict the next scan's pose.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Extrapolation {
    /// Over the sweeps that passed since the last scan, by the stamps: right for a sensor read at
    /// its own rate, whatever scans were dropped.
    Time,
    /// By the last scan-to-scan motion, whatever the time between: right for scans kept by
    /// distance travelled (a recording of keyframes), where the stamps' gaps follow the speed.
    Scan,
}

/// Scans over which the two extrapolations' errors are compared.
const EXTRAPOLATION_WINDOW: usize = 20;

/// The running σ of the prediction's error, and which extrapolation has predicted better.
#[derive(Clone, Debug)]
pub struct MotionModel {
    config: MotionModelConfig,
    sum_sq: f64,
    count: usize,
    /// Recent squared errors of the two extrapolations, by time and by scan.
    recent: std::collections::VecDeque<(f64, f64)>,
}

impl MotionModel {
    /// No evidence yet: σ is [`MotionModelConfig::initial_sigma`].
    pub fn new(config: MotionModelConfig) -> Self {
        MotionModel { config, sum_sq: 0.0, count: 0, recent: std::collections::VecDeque::new() }
    }

    /// Eq. 10: σ = sqrt(Σ e² / n) over the scans that moved, or the initial σ before any did.
    pub fn sigma(&self) -> f64 {
        if self.count == 0 { self.config.initial_sigma } else { (self.sum_sq / self.count as f64).sqrt() }
    }

    /// Records one scan: its `predicted` and `estimated` poses and the `motion` since the last scan.
    pub fn observe(&mut self, predicted: &Isometry3<f64>, estimated: &Isometry3<f64>, motion: &Isometry3<f64>) {
        if displacement(motion, self.config.range) < self.config.min_motion {
            return;
        }
        let error = displacement(&(predicted.inverse() * estimated), self.config.range);
        self.sum_sq += error * error;
        self.count += 1;
    }

    /// Forgets the evidence (after a gap in the stamps or a lost scan).
    pub fn reset(&mut self) {
        self.sum_sq = 0.0;
        self.count = 0;
        self.recent.clear();
    }

    /// Records how far each extrapolation's prediction (`by_time`, `by_scan`) was from the
    /// `estimated` pose. Where the stamps are regular the two are one and the same.
    pub fn compare(&mut self, by_time: &Isometry3<f64>, by_scan: &Isometry3<f64>, estimated: &Isometry3<f64>) {
        let error = |predicted: &Isometry3<f64>| displacement(&(predicted.inverse() * estimated), self.config.range);
        if self.recent.len() == EXTRAPOLATION_WINDOW {
            self.recent.pop_front();
        }
        self.recent.push_back((error(by_time).powi(2), error(by_scan).powi(2)));
    }

    /// The extrapolation with the smaller recent error; by time until the scans say otherwise.
    pub fn extrapolation(&self) -> Extrapolation {
        let (time, scan) = self.recent.iter().fold((0.0, 0.0), |(t, s), (a, b)| (t + a, s + b));
        if scan < time { Extrapolation::Scan } else { Extrapolation::Time }
    }

    /// True when two sweep stamps are far enough apart to distrust the prediction.
    pub fn is_gap(&self, previous: f64, stamp: f64) -> bool {
        (stamp - previous).abs() > self.config.gap_s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn sigma_is_the_rms_displacement_of_the_moving_scans() {
        let mut model = MotionModel::new(MotionModelConfig::default());
        assert_eq!(model.sigma(), 2.0);
        let moved = Isometry3::translation(1.0, 0.0, 0.0);
        // Predictions 0.3 m and 0.4 m off: σ = sqrt((0.09 + 0.16) / 2).
        model.observe(&Isometry3::identity(), &Isometry3::translation(0.3, 0.0, 0.0), &moved);
        model.observe(&Isometry3::identity(), &Isometry3::translation(0.0, 0.4, 0.0), &moved);
        // Standing still: no evidence either way.
        model.observe(&Isometry3::identity(), &Isometry3::translation(5.0, 0.0, 0.0), &Isometry3::identity());
        assert!((model.sigma() - (0.125f64).sqrt()).abs() < 1e-12);
        model.reset();
        assert_eq!(model.sigma(), 2.0);
    }

    #[test]
    fn the_extrapolation_that_predicted_better_is_chosen() {
        let mut model = MotionModel::new(MotionModelConfig::default());
        assert_eq!(model.extrapolation(), Extrapolation::Time);
        let truth = Isometry3::translation(1.0, 0.0, 0.0);
        // Regular stamps: both predict alike, time is kept.
        model.compare(&truth, &truth, &truth);
        assert_eq!(model.extrapolation(), Extrapolation::Time);
        // Keyframes kept by distance: the scan's motion predicts, the time gap overshoots.
        for _ in 0..3 {
            model.compare(&Isometry3::translation(2.5, 0.0, 0.0), &Isometry3::translation(1.1, 0.0, 0.0), &truth);
        }
        assert_eq!(model.extrapolation(), Extrapolation::Scan);
        model.reset();
        assert_eq!(model.extrapolation(), Extrapolation::Time);
    }

    #[test]
    fn a_rotation_displaces_a_point_at_range_by_its_chord() {
        let turn = Isometry3::new(Vector3::zeros(), Vector3::new(0.0, 0.0, 60f64.to_radians()));
        // A 60° turn moves a point 50 m away along a chord as long as the radius.
        assert!((displacement(&turn, 50.0) - 50.0).abs() < 1e-9);
    }
}
