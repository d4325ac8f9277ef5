//! Closed-form rigid alignment of paired points (Umeyama 1991, without scale).

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion};

/// Why a rigid fit could not be computed.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum AlignmentError {
    /// Source and target have different lengths.
    #[error("{source_len} source points for {target_len} target points")]
    LengthMismatch { source_len: usize, target_len: usize },
    /// Fewer than three pairs: the rotation is undetermined.
    #[error("{0} point pairs, need at least 3")]
    TooFewPoints(usize),
    /// All points collinear (or coincident): the rotation about their line is undetermined.
    #[error("the points are degenerate (collinear or coincident)")]
    Degenerate,
}

/// The rigid transform `T` minimising `Σ |target_i - T source_i|²` (Umeyama, eqs. 40-42, scale 1).
pub fn umeyama(source: &[Point3<f64>], target: &[Point3<f64>]) -> Result<Isometry3<f64>, AlignmentError> {
    if source.len() != target.len() {
        return Err(AlignmentError::LengthMismatch { source_len: source.len(), target_len: target.len() });
    }
    let n = source.len();
    if n < 3 {
        return Err(AlignmentError::TooFewPoints(n));
    }
    let mean = |pts: &[Point3<f64>]| pts.iter().fold(Point3::origin(), |acc, p| acc + p.coords) / n as f64;
    let (mu_s, mu_t) = (mean(source), mean(target));
    // Cross-covariance Σ_ts (eq. 38).
    let sigma =
        source.iter().zip(target).fold(Matrix3::zeros(), |acc, (s, t)| acc + (t - mu_t) * (s - mu_s).transpose())
            / n as f64;
    let svd = sigma.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else { return Err(AlignmentError::Degenerate) };
    // Rank < 2 means the points span at most a line.
    let mut sv = svd.singular_values.as_slice().to_vec();
    sv.sort_by(|a, b| b.total_cmp(a));
    if sv[1] <= 1e-12 * sv[0].max(1e-300) {
        return Err(AlignmentError::Degenerate);
    }
    // S flips the last axis when U V^T is a reflection (eq. 39).
    let mut s = Matrix3::identity();
    if u.determinant() * v_t.determinant() < 0.0 {
        s[(2, 2)] = -1.0;
    }
    let r = u * s * v_t;
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    let t = mu_t.coords - rotation * mu_s.coords;
    Ok(Isometry3::from_parts(Translation3::from(t), rotation))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::se3::pose_error;
    use nalgebra::Vector3;

    #[test]
    fn recovers_a_known_transform() {
        let truth = Isometry3::new(Vector3::new(3.0, -1.0, 0.5), Vector3::new(0.2, -0.4, 2.5));
        let src: Vec<Point3<f64>> = (0..30)
            .map(|i| {
                let f = i as f64;
                Point3::new((f * 1.3).sin() * 5.0, (f * 0.7).cos() * 3.0, f * 0.1)
            })
            .collect();
        let dst: Vec<_> = src.iter().map(|p| truth * p).collect();
        let est = umeyama(&src, &dst).unwrap();
        testkit::assert_pose_close!(&est, &truth, 1e-9, 1e-7);
    }

    #[test]
    fn planar_points_give_a_rotation_not_a_reflection() {
        // Coplanar points: Σ has a zero singular value and U V^T may be a reflection without the S fix.
        let src = [
            Point3::new(0.0, 0.0, 0.0),
            Point3::new(1.0, 0.0, 0.0),
            Point3::new(0.0, 2.0, 0.0),
            Point3::new(1.0, 1.0, 0.0),
        ];
        let truth = Isometry3::new(Vector3::new(0.0, 1.0, 2.0), Vector3::new(0.0, 0.0, 0.7));
        let dst: Vec<_> = src.iter().map(|p| truth * p).collect();
        let est = umeyama(&src, &dst).unwrap();
        assert!(pose_error(&est, &truth).rotation_deg < 1e-7);
    }

    #[test]
    fn rejects_degenerate_input() {
        let line: Vec<_> = (0..5).map(|i| Point3::new(i as f64, 0.0, 0.0)).collect();
        assert_eq!(umeyama(&line, &line), Err(AlignmentError::Degenerate));
        assert_eq!(umeyama(&line[..2], &line[..2]), Err(AlignmentError::TooFewPoints(2)));
        assert!(matches!(umeyama(&line, &line[..4]), Err(AlignmentError::LengthMismatch { .. })));
    }
}
