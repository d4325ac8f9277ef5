//! Per-point times for clouds recorded without them, derived from azimuth.
//!
//! A spinning LiDAR measures azimuths in order, so a point's time within the sweep is the angle
//! swept since the first point divided by a full turn, times the rotation period. This assumes
//! one revolution per scan that starts at the cloud's first point (the order drivers and KITTI
//! store points in); a point measured just before the first one by jitter gets a time near the
//! full period.

use nalgebra::Point3;

/// How to fill the time channel of a scan that has none.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum TimeModel {
    /// Leave the time channel absent (the default: nothing is invented).
    #[default]
    None,
    /// Times from azimuth, see the module doc.
    Azimuth {
        /// Seconds per revolution (0.1 at 10 Hz).
        period_s: f32,
        /// Rotation direction seen from above (+z).
        spin: Spin,
    },
}

/// Rotation direction of the sensor head, seen from above (looking down the -z axis).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Spin {
    /// Azimuth `atan2(y, x)` decreases with time (Velodyne VLP-16/32 in the ROS x-forward frame).
    Clockwise,
    /// Azimuth `atan2(y, x)` increases with time (the point order of KITTI's HDL-64 scans).
    CounterClockwise,
    /// Told from the point order of each scan: the direction most consecutive points turn.
    Detect,
}

impl Spin {
    /// +1 when azimuth increases with time, −1 when it decreases ([`Spin::Detect`] counts as +1;
    /// resolve it with [`detect_spin`] first).
    pub fn sign(self) -> f64 {
        if self == Spin::Clockwise { -1.0 } else { 1.0 }
    }
}

/// The spin direction of a cloud stored in firing order: consecutive points mostly step a small
/// angle in the direction of rotation (the large steps at ring changes and gaps are ignored).
pub fn detect_spin(points: &[Point3<f32>]) -> Spin {
    let (mut up, mut down) = (0usize, 0usize);
    for w in points.windows(2) {
        let d = (azimuth(&w[1]) - azimuth(&w[0]) + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
            - std::f64::consts::PI;
        if d.abs() < 0.1 {
            if d > 0.0 {
                up += 1;
            } else if d < 0.0 {
                down += 1;
            }
        }
    }
    if down > up { Spin::Clockwise } else { Spin::CounterClockwise }
}

/// Seconds since the sweep start for each point, from its azimuth relative to the first point.
pub fn times_from_azimuth(points: &[Point3<f32>], period_s: f32, spin: Spin) -> Vec<f32> {
    let Some(first) = points.first() else {
        return Vec::new();
    };
    let start = azimuth(first);
    let spin = if spin == Spin::Detect { detect_spin(points) } else { spin };
    let sign = spin.sign();
    let turn = std::f64::consts::TAU;
    points
        .iter()
        .map(|p| {
            let swept = (sign * (azimuth(p) - start)).rem_euclid(turn);
            (swept / turn * f64::from(period_s)) as f32
        })
        .collect()
}

/// `atan2(y, x)` in radians.
fn azimuth(p: &Point3<f32>) -> f64 {
    f64::from(p.y).atan2(f64::from(p.x))
}

/// One-degree bins of azimuth: a spinning head's scan returns in nearly all of them.
const AZIMUTH_BINS: usize = 360;

/// The share of the azimuth circle (in one-degree bins) where `points` have a return.
pub fn azimuth_coverage(points: &[Point3<f32>]) -> f64 {
    let mut seen = [false; AZIMUTH_BINS];
    for p in points.iter().filter(|p| p.x != 0.0 || p.y != 0.0) {
        let bin = ((azimuth(p) + std::f64::consts::PI) / std::f64::consts::TAU * AZIMUTH_BINS as f64) as usize;
        seen[bin.min(AZIMUTH_BINS - 1)] = true;
    }
    seen.iter().filter(|s| **s).count() as f64 / AZIMUTH_BINS as f64
}

/// True when a scan looks taken by a spinning head: it has returns around more than half the
/// circle. Scan lines and a sweep through azimuth, what rings and times are derived from, exist
/// only there; a solid-state sensor's view (70-120 deg) covers a fifth to a third of it, while a
/// spinning head sees around itself even with its back to a wall or its rear half masked.
pub fn is_spinning(points: &[Point3<f32>]) -> bool {
    azimuth_coverage(points) > 0.5
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ring of points measured at `times` by a sensor starting at `start` rad and spinning `spin`.
    fn ring(times: &[f64], start: f64, spin: Spin, period: f64) -> Vec<Point3<f32>> {
        let sign = if spin == Spin::Clockwise { -1.0 } else { 1.0 };
        times
            .iter()
            .map(|t| {
                let az = start + sign * t / period * std::f64::consts::TAU;
                Point3::new((10.0 * az.cos()) as f32, (10.0 * az.sin()) as f32, -1.0)
            })
            .collect()
    }

    #[test]
    fn recovers_times_on_a_synthetic_ring_both_ways() {
        let period = 0.1;
        let times: Vec<f64> = (0..1000).map(|i| f64::from(i) * period / 1000.0).collect();
        for spin in [Spin::Clockwise, Spin::CounterClockwise] {
            for start in [0.0, 3.0, -2.5] {
                let points = ring(&times, start, spin, period);
                let derived = times_from_azimuth(&points, period as f32, spin);
                for (d, t) in derived.iter().zip(&times) {
                    assert!((f64::from(*d) - t).abs() < 1e-6, "{spin:?} start {start}: {d} vs {t}");
                }
            }
        }
    }

    #[test]
    fn a_full_turn_is_spinning_and_a_forward_view_is_not() {
        let around = ring(&(0..3600).map(|i| f64::from(i) / 36_000.0).collect::<Vec<_>>(), 0.0, Spin::Clockwise, 0.1);
        assert!((azimuth_coverage(&around) - 1.0).abs() < 1e-9);
        assert!(is_spinning(&around));
        // The rear half masked: still a spinning head.
        let front: Vec<Point3<f32>> = around.iter().filter(|p| p.x > -0.5).copied().collect();
        assert!(is_spinning(&front));
        // A 70 deg forward view (a Livox Avia's).
        let narrow: Vec<Point3<f32>> =
            around.iter().filter(|p| p.y.atan2(p.x).abs() < 35f32.to_radians()).copied().collect();
        assert!((azimuth_coverage(&narrow) - 70.0 / 360.0).abs() < 0.01, "{}", azimuth_coverage(&narrow));
        assert!(!is_spinning(&narrow));
        assert!(!is_spinning(&[]));
    }

    #[test]
    fn the_wrong_direction_mirrors_the_sweep() {
        let times = [0.0, 0.025, 0.05];
        let points = ring(&times, 1.0, Spin::Clockwise, 0.1);
        let derived = times_from_azimuth(&points, 0.1, Spin::CounterClockwise);
        assert!((derived[1] - 0.075).abs() < 1e-6 && (derived[2] - 0.05).abs() < 1e-6, "{derived:?}");
    }
}
