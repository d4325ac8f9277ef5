//! Motion distortion compensation (F-LOAM eqs. 2-3): constant velocity over the sweep.

use nalgebra::{Isometry3, Point3, Vector6};

use super::features::Feature;

/// The sensor's motion over one sweep, as a twist: `log(T_{k-1}⁻¹ T_k)` (eq. 2, constant velocity).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SweepMotion(pub Vector6<f64>);

impl SweepMotion {
    /// No motion: compensation leaves points unchanged.
    pub fn zero() -> Self {
        SweepMotion(Vector6::zeros())
    }

    /// The motion between two consecutive scan-end poses.
    pub fn between(previous: &Isometry3<f64>, current: &Isometry3<f64>) -> Self {
        SweepMotion(cloud::se3::log(&(previous.inverse() * current)))
    }

    /// The motion over one sweep when `sweeps` sweeps passed between two scan-end poses (more than
    /// one where scans were dropped): the constant velocity spreads it evenly.
    pub fn per_sweep(previous: &Isometry3<f64>, current: &Isometry3<f64>, sweeps: f64) -> Self {
        SweepMotion(Self::between(previous, current).0 / sweeps)
    }

    /// Eq. 3: the transform from the sensor frame at sweep phase `s` to the frame at the sweep end,
    /// `exp((s − 1) ξ)`.
    pub fn to_end(&self, phase: f32) -> Isometry3<f64> {
        cloud::se3::exp(&((f64::from(phase) - 1.0) * self.0))
    }

    /// A point measured at phase `s`, expressed in the sweep-end frame.
    pub fn compensate(&self, point: &Point3<f32>, phase: f32) -> Point3<f32> {
        (self.to_end(phase) * point.cast::<f64>()).cast::<f32>()
    }
}

/// Phase bins of [`SweepMotion::table`]: the nearest bin is at most half a bin off, 49 µs of a
/// 10 Hz sweep: 0.1 mm at 2 m/s, 2 mm at 50 m while turning at 0.8 rad/s.
const TABLE_BINS: usize = 1024;

/// Sweep-end transforms precomputed per phase bin, for compensating whole clouds (one `exp` per
/// bin instead of per point).
pub struct CompensationTable {
    to_end: Vec<Isometry3<f32>>,
}

impl CompensationTable {
    /// A point measured at phase `s`, in the sweep-end frame (nearest phase bin).
    pub fn compensate(&self, point: &Point3<f32>, phase: f32) -> Point3<f32> {
        let bin = (phase.clamp(0.0, 1.0) * TABLE_BINS as f32).round() as usize;
        self.to_end[bin] * point
    }
}

impl SweepMotion {
    /// The per-bin table of [`SweepMotion::to_end`].
    pub fn table(&self) -> CompensationTable {
        let to_end = (0..=TABLE_BINS).map(|b| self.to_end(b as f32 / TABLE_BINS as f32).cast::<f32>()).collect();
        CompensationTable { to_end }
    }

    /// An upper bound on how far apart the two motions place a point `range` metres away, at
    /// the sweep start (where they differ most).
    pub fn difference_at(&self, other: &SweepMotion, range: f64) -> f64 {
        let d = self.0 - other.0;
        d.fixed_rows::<3>(0).norm() + range * d.fixed_rows::<3>(3).norm()
    }

    /// True when there is no motion to compensate.
    pub fn is_zero(&self) -> bool {
        self.0 == Vector6::zeros()
    }
}

/// Moves every feature to the sweep-end frame (phase becomes 1).
pub fn compensate(features: &[Feature], motion: &SweepMotion) -> Vec<Feature> {
    features.iter().map(|f| Feature { point: motion.compensate(&f.point, f.phase), phase: 1.0, ..*f }).collect()
}

/// A whole scan moved to the sweep-end frame by its per-point times (`period` seconds a sweep); a
/// scan without times, or no motion, is returned as it is.
pub fn cloud(scan: &cloud::PointCloud, motion: &SweepMotion, period: f32) -> cloud::PointCloud {
    let mut deskewed = scan.clone();
    if let (false, Some(times)) = (motion.is_zero(), scan.time.as_deref()) {
        let table = motion.table();
        for (p, t) in deskewed.points.iter_mut().zip(times) {
            *p = table.compensate(p, t / period);
        }
    }
    deskewed
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn a_point_measured_mid_sweep_moves_by_half_the_motion() {
        // Driving 1 m forward (x) over the sweep: a static point seen at phase 0.5 is 0.5 m closer
        // at the end of the sweep.
        let motion = SweepMotion::between(&Isometry3::identity(), &Isometry3::translation(1.0, 0.0, 0.0));
        let p = motion.compensate(&Point3::new(10.0, 2.0, 0.0), 0.5);
        assert!((p - Point3::new(9.5, 2.0, 0.0)).norm() < 1e-5, "{p}");
        assert_eq!(motion.compensate(&Point3::new(3.0, 4.0, 5.0), 1.0), Point3::new(3.0, 4.0, 5.0));
    }

    #[test]
    fn the_table_agrees_with_exact_compensation() {
        // 1.5 m/s and 0.8 rad/s over a 0.1 s sweep; a point 50 m away.
        let motion = SweepMotion(Vector6::new(0.15, 0.0, 0.0, 0.0, 0.0, 0.08));
        let table = motion.table();
        let p = Point3::new(30.0, -40.0, 2.0);
        for i in 0..=997 {
            let s = i as f32 / 997.0;
            let d = (table.compensate(&p, s) - motion.compensate(&p, s)).norm();
            assert!(d < 2.5e-3, "phase {s}: {d} m");
        }
    }

    #[test]
    fn compensation_matches_the_true_pose_at_each_phase() {
        // Under constant twist ξ the sensor at phase s is T(s) = T_end exp((s-1)ξ); a world point w
        // measured at s reads T(s)⁻¹ w; compensation must give T_end⁻¹ w.
        let xi = Vector6::new(1.2, 0.1, 0.0, 0.0, 0.02, 0.3);
        let end = Isometry3::new(Vector3::new(5.0, 1.0, 0.0), Vector3::new(0.0, 0.0, 0.4));
        let motion = SweepMotion(xi);
        let w = Point3::new(12.0, -3.0, 1.5);
        for s in [0.0f32, 0.25, 0.7, 1.0] {
            let pose_s = end * cloud::se3::exp(&((f64::from(s) - 1.0) * xi));
            let measured = (pose_s.inverse() * w).cast::<f32>();
            let got = motion.compensate(&measured, s).cast::<f64>();
            assert!((got - end.inverse() * w).norm() < 1e-4, "phase {s}");
        }
    }
}
