//! Conversions between the wire `Pose` and nalgebra's `Isometry3`.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::v1::Pose;

/// How far from unit length a received quaternion may be before it is rejected rather than
/// renormalised. Senders write normalised f64 quaternions; anything further off is corrupt.
const UNIT_TOLERANCE: f64 = 1e-6;

/// A wire pose that is not a rigid transform.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum InvalidPose {
    /// A component is NaN or infinite.
    #[error("pose has a non-finite component")]
    NonFinite,
    /// The quaternion's norm is not 1.
    #[error("pose quaternion has norm {0}, expected 1")]
    NotUnit(f64),
}

impl From<&Isometry3<f64>> for Pose {
    fn from(iso: &Isometry3<f64>) -> Self {
        let t = &iso.translation.vector;
        let q = iso.rotation.quaternion();
        Pose { tx: t.x, ty: t.y, tz: t.z, qx: q.i, qy: q.j, qz: q.k, qw: q.w }
    }
}

impl From<Isometry3<f64>> for Pose {
    fn from(iso: Isometry3<f64>) -> Self {
        Pose::from(&iso)
    }
}

impl From<&Isometry3<f32>> for Pose {
    fn from(iso: &Isometry3<f32>) -> Self {
        Pose::from(&iso.cast::<f64>())
    }
}

impl TryFrom<&Pose> for Isometry3<f64> {
    type Error = InvalidPose;

    fn try_from(p: &Pose) -> Result<Self, InvalidPose> {
        let all = [p.tx, p.ty, p.tz, p.qx, p.qy, p.qz, p.qw];
        if !all.iter().all(|v| v.is_finite()) {
            return Err(InvalidPose::NonFinite);
        }
        let q = Quaternion::new(p.qw, p.qx, p.qy, p.qz);
        let norm = q.norm();
        if (norm - 1.0).abs() > UNIT_TOLERANCE {
            return Err(InvalidPose::NotUnit(norm));
        }
        // Renormalising an already-unit quaternion changes its last bits; skip it so that
        // Isometry3 -> Pose -> Isometry3 is exact. Rotations composed over thousands of scans
        // drift from unit norm by a few ulps (seen: 1.4e-15), so "already unit" is 1e-12.
        let rotation = if (norm - 1.0).abs() <= 1e-12 {
            UnitQuaternion::new_unchecked(q)
        } else {
            UnitQuaternion::new_normalize(q)
        };
        Ok(Isometry3::from_parts(Translation3::new(p.tx, p.ty, p.tz), rotation))
    }
}

impl TryFrom<Pose> for Isometry3<f64> {
    type Error = InvalidPose;

    fn try_from(p: Pose) -> Result<Self, InvalidPose> {
        Isometry3::try_from(&p)
    }
}

impl Pose {
    /// The identity transform.
    pub fn identity() -> Self {
        Pose::from(&Isometry3::<f64>::identity())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn round_trip_is_exact() {
        let iso = Isometry3::new(Vector3::new(1.5, -2.25, 1e5), Vector3::new(0.3, -1.2, 2.9));
        let back = Isometry3::try_from(&Pose::from(&iso)).unwrap();
        assert_eq!(back, iso);
    }

    #[test]
    fn rejects_non_unit_and_non_finite() {
        let mut p = Pose::identity();
        p.qw = 2.0;
        assert_eq!(Isometry3::try_from(&p), Err(InvalidPose::NotUnit(2.0)));
        p.qw = 1.0;
        p.tx = f64::NAN;
        assert_eq!(Isometry3::try_from(&p), Err(InvalidPose::NonFinite));
    }

    #[test]
    fn default_pose_is_not_a_transform() {
        // proto3 zero-fills a missing pose: all-zero quaternion must be caught, not turned into NaNs.
        assert_eq!(Isometry3::try_from(&Pose::default()), Err(InvalidPose::NotUnit(0.0)));
    }
}
