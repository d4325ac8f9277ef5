//! Trajectories: KITTI and TUM text formats, and the accuracy metrics ATE and RPE.

use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};

use crate::alignment::{AlignmentError, umeyama};
use crate::se3::{from_kitti_row, to_kitti_row};

/// A sequence of poses (sensor in the trajectory's world frame), with timestamps when known.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trajectory {
    /// Pose per frame.
    pub poses: Vec<Isometry3<f64>>,
    /// Seconds per frame (TUM files have them; KITTI pose files do not).
    pub stamps: Option<Vec<f64>>,
}

/// A trajectory file that could not be parsed or compared.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum TrajectoryError {
    /// A line with the wrong field count, a non-number or a non-rigid transform.
    #[error("line {line}: {reason}")]
    Line { line: usize, reason: String },
    /// Two trajectories that cannot be paired frame by frame.
    #[error("cannot pair trajectories: {0}")]
    Pairing(String),
    /// The alignment failed (e.g. all positions on a line).
    #[error("alignment failed: {0}")]
    Alignment(#[from] AlignmentError),
}

fn numbers(line: &str, n: usize, lineno: usize) -> Result<Vec<f64>, TrajectoryError> {
    let err = |reason: String| TrajectoryError::Line { line: lineno, reason };
    let v: Vec<f64> = line
        .split_whitespace()
        .map(|s| s.parse::<f64>().map_err(|_| err(format!("{s:?} is not a number"))))
        .collect::<Result<_, _>>()?;
    if v.len() != n {
        return Err(err(format!("{} fields, expected {n}", v.len())));
    }
    if v.iter().any(|x| !x.is_finite()) {
        return Err(err("non-finite value".into()));
    }
    Ok(v)
}

/// Lines that carry data: blank lines and `#` comments are skipped; numbering is 1-based.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())).filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

impl Trajectory {
    /// Parses KITTI pose lines: 12 numbers, the row-major 3x4 matrix `[R | t]`.
    pub fn parse_kitti(text: &str) -> Result<Self, TrajectoryError> {
        let mut poses = Vec::new();
        for (lineno, line) in data_lines(text) {
            let v: [f64; 12] = numbers(line, 12, lineno)?.try_into().expect("12 checked");
            let pose = from_kitti_row(&v)
                .ok_or(TrajectoryError::Line { line: lineno, reason: "rotation block is not a rotation".into() })?;
            poses.push(pose);
        }
        Ok(Trajectory { poses, stamps: None })
    }

    /// Parses TUM lines: `stamp tx ty tz qx qy qz qw`.
    pub fn parse_tum(text: &str) -> Result<Self, TrajectoryError> {
        let (mut poses, mut stamps) = (Vec::new(), Vec::new());
        for (lineno, line) in data_lines(text) {
            let v = numbers(line, 8, lineno)?;
            let q = Quaternion::new(v[7], v[4], v[5], v[6]);
            if (q.norm() - 1.0).abs() > 1e-3 {
                return Err(TrajectoryError::Line { line: lineno, reason: format!("quaternion norm {}", q.norm()) });
            }
            stamps.push(v[0]);
            poses.push(Isometry3::from_parts(Translation3::new(v[1], v[2], v[3]), UnitQuaternion::from_quaternion(q)));
        }
        Ok(Trajectory { poses, stamps: Some(stamps) })
    }

    /// Parses either format, told apart by the field count of the first data line (12 KITTI, 8 TUM).
    pub fn parse(text: &str) -> Result<Self, TrajectoryError> {
        match data_lines(text).next().map(|(n, l)| (n, l.split_whitespace().count())) {
            Some((_, 8)) => Self::parse_tum(text),
            Some((_, 12)) | None => Self::parse_kitti(text),
            Some((line, n)) => {
                Err(TrajectoryError::Line { line, reason: format!("{n} fields: neither KITTI (12) nor TUM (8)") })
            }
        }
    }

    /// KITTI text: one 12-number line per pose.
    pub fn to_kitti(&self) -> String {
        self.poses.iter().map(|p| join(&to_kitti_row(p)) + "\n").collect()
    }

    /// TUM text: `stamp tx ty tz qx qy qz qw` per pose (stamps = index × 0.1 s when unknown).
    pub fn to_tum(&self) -> String {
        let stamp = |i: usize| self.stamps.as_ref().map_or(i as f64 * 0.1, |s| s[i]);
        (0..self.poses.len())
            .map(|i| {
                let p = &self.poses[i];
                let (t, q) = (p.translation.vector, p.rotation.quaternion());
                join(&[stamp(i), t.x, t.y, t.z, q.i, q.j, q.k, q.w]) + "\n"
            })
            .collect()
    }

    /// Total distance travelled, metres.
    pub fn length(&self) -> f64 {
        cumulative_distance(&self.poses).last().copied().unwrap_or(0.0)
    }
}

fn join(v: &[f64]) -> String {
    v.iter().map(|x| format!("{x:.9e}")).collect::<Vec<_>>().join(" ")
}

fn cumulative_distance(poses: &[Isometry3<f64>]) -> Vec<f64> {
    let mut d = Vec::with_capacity(poses.len());
    let mut acc = 0.0;
    for (i, p) in poses.iter().enumerate() {
        if i > 0 {
            acc += (p.translation.vector - poses[i - 1].translation.vector).norm();
        }
        d.push(acc);
    }
    d
}

/// Ground-truth and estimated poses paired frame by frame.
pub type PosePairs = (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>);

/// Pairs the frames of two trajectories: by timestamp (nearest within `max_dt` seconds) when both
/// have stamps, else by index (then the lengths must match).
pub fn pair(gt: &Trajectory, est: &Trajectory, max_dt: f64) -> Result<PosePairs, TrajectoryError> {
    match (&gt.stamps, &est.stamps) {
        (Some(gs), Some(es)) => {
            let (mut g, mut e) = (Vec::new(), Vec::new());
            for (i, t) in es.iter().enumerate() {
                let j = gs.partition_point(|s| s < t);
                let best = [j.wrapping_sub(1), j]
                    .into_iter()
                    .filter(|&k| k < gs.len())
                    .min_by(|&a, &b| (gs[a] - t).abs().total_cmp(&(gs[b] - t).abs()));
                if let Some(k) = best.filter(|&k| (gs[k] - t).abs() <= max_dt) {
                    g.push(gt.poses[k]);
                    e.push(est.poses[i]);
                }
            }
            if g.is_empty() {
                return Err(TrajectoryError::Pairing(format!("no timestamps within {max_dt} s of each other")));
            }
            Ok((g, e))
        }
        _ if gt.poses.len() != est.poses.len() => Err(TrajectoryError::Pairing(format!(
            "ground truth has {} poses, estimate {} (without timestamps they are paired by index)",
            gt.poses.len(),
            est.poses.len()
        ))),
        _ => Ok((gt.poses.clone(), est.poses.clone())),
    }
}

/// Absolute trajectory error over paired poses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ate {
    /// Root mean square of the position errors, metres.
    pub rmse: f64,
    /// Mean position error, metres.
    pub mean: f64,
    /// Largest position error, metres.
    pub max: f64,
    /// Number of paired poses.
    pub pairs: usize,
}

/// ATE: position errors of `est` against `gt` (paired), after the SE(3) alignment (Umeyama) of the
/// estimated positions onto the true ones when `align`, else as given (both start at identity).
pub fn ate(gt: &[Isometry3<f64>], est: &[Isometry3<f64>], align: bool) -> Result<Ate, TrajectoryError> {
    if gt.len() != est.len() || gt.is_empty() {
        return Err(TrajectoryError::Pairing(format!("{} vs {} poses", gt.len(), est.len())));
    }
    let position = |p: &Isometry3<f64>| Point3::from(p.translation.vector);
    let t = if align {
        umeyama(&est.iter().map(position).collect::<Vec<_>>(), &gt.iter().map(position).collect::<Vec<_>>())?
    } else {
        Isometry3::identity()
    };
    let errors: Vec<f64> = gt.iter().zip(est).map(|(g, e)| (position(g) - t * position(e)).norm()).collect();
    let n = errors.len() as f64;
    Ok(Ate {
        rmse: (errors.iter().map(|e| e * e).sum::<f64>() / n).sqrt(),
        mean: errors.iter().sum::<f64>() / n,
        max: errors.iter().copied().fold(0.0, f64::max),
        pairs: errors.len(),
    })
}

/// How far from a pose the points standing for its view lie, metres ([`map_fit`]): about where
/// a LiDAR's returns in a building fall, so that a rotation error weighs as it moves the map.
pub const VIEW_LEVER_M: f64 = 10.0;

/// The rigid transform that best carries a robot's estimated map onto the truth: each pose stands
/// for what it sees by its position and the points [`VIEW_LEVER_M`] along its six axis directions,
/// and the estimated ones are fitted onto the true ones (Umeyama). Unlike [`ate`]'s alignment of
/// positions alone, it sees rotation errors about the path (a tilt along a straight run). It is the
/// best any rigid placement of the map can do; what is left is the map's own shape error.
pub fn map_fit(gt: &[Isometry3<f64>], est: &[Isometry3<f64>]) -> Result<Isometry3<f64>, TrajectoryError> {
    if gt.len() != est.len() || gt.is_empty() {
        return Err(TrajectoryError::Pairing(format!("{} vs {} poses", gt.len(), est.len())));
    }
    let view = |poses: &[Isometry3<f64>]| -> Vec<Point3<f64>> {
        let levers =
            [Vector3::zeros(), Vector3::x(), -Vector3::x(), Vector3::y(), -Vector3::y(), Vector3::z(), -Vector3::z()];
        poses.iter().flat_map(|p| levers.map(|l| p * Point3::from(l * VIEW_LEVER_M))).collect()
    };
    Ok(umeyama(&view(est), &view(gt))?)
}

/// Relative pose error, KITTI style.
#[derive(Clone, Debug, PartialEq)]
pub struct Rpe {
    /// Mean translational drift, percent of the segment length.
    pub translation_percent: f64,
    /// Mean rotational drift, degrees per 100 m.
    pub rotation_deg_per_100m: f64,
    /// Segment lengths used, metres.
    pub lengths: Vec<f64>,
    /// Number of segments averaged.
    pub segments: usize,
}

/// KITTI's segment lengths (100..800 m) that fit in a path of `total` metres; for shorter paths,
/// 1/5 .. 4/5 of the path, so that short sequences still get a drift figure.
pub fn segment_lengths(total: f64) -> Vec<f64> {
    let kitti: Vec<f64> = (1..=8).map(|i| 100.0 * i as f64).filter(|l| *l <= total).collect();
    if kitti.is_empty() { (1..=4).map(|i| total * i as f64 / 5.0).collect() } else { kitti }
}

/// RPE as the KITTI devkit computes it: for every first frame and segment length, the error of the
/// relative motion to the first frame at least that far along the true path, divided by the length.
/// Two departures from the devkit, both immaterial at 10 Hz but not on coarse test trajectories:
/// `>=` where it has `>` (so a segment ending exactly on a frame is not stretched by one frame), and
/// every frame starts a segment (it steps by 10 for speed).
pub fn rpe(gt: &[Isometry3<f64>], est: &[Isometry3<f64>], lengths: &[f64]) -> Result<Rpe, TrajectoryError> {
    if gt.len() != est.len() {
        return Err(TrajectoryError::Pairing(format!("{} vs {} poses", gt.len(), est.len())));
    }
    let dist = cumulative_distance(gt);
    let (mut t_sum, mut r_sum, mut n) = (0.0, 0.0, 0usize);
    for first in 0..gt.len() {
        for &len in lengths {
            let Some(last) = (first..gt.len()).find(|&j| dist[j] >= dist[first] + len) else { continue };
            let d_gt = gt[first].inverse() * gt[last];
            let d_est = est[first].inverse() * est[last];
            let e = d_gt.inverse() * d_est;
            t_sum += e.translation.vector.norm() / len;
            r_sum += e.rotation.angle().to_degrees() / len;
            n += 1;
        }
    }
    if n == 0 {
        return Err(TrajectoryError::Pairing("no segment fits the trajectory".into()));
    }
    Ok(Rpe {
        translation_percent: 100.0 * t_sum / n as f64,
        rotation_deg_per_100m: 100.0 * r_sum / n as f64,
        lengths: lengths.to_vec(),
        segments: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn straight(n: usize, step: f64) -> Vec<Isometry3<f64>> {
        (0..n).map(|i| Isometry3::translation(i as f64 * step, 0.0, 0.0)).collect()
    }

    #[test]
    fn ate_by_hand() {
        // Errors 0, 0.3 (in y) and 0.4 (in z): RMSE = sqrt((0 + 0.09 + 0.16) / 3) = sqrt(0.25/3).
        let gt = straight(3, 1.0);
        let est = vec![gt[0], Isometry3::translation(1.0, 0.3, 0.0), Isometry3::translation(2.0, 0.0, 0.4)];
        let a = ate(&gt, &est, false).unwrap();
        assert!((a.rmse - (0.25f64 / 3.0).sqrt()).abs() < 1e-12);
        assert!((a.mean - 0.7 / 3.0).abs() < 1e-12);
        assert!((a.max - 0.4).abs() < 1e-12);
    }

    #[test]
    fn the_map_fit_finds_a_tilt_along_a_straight_run_that_positions_alone_cannot() {
        // A straight run whose map is rolled 0.3 deg about the path and shifted: positions alone
        // are collinear (no rotation about their line), the views are not.
        let gt = straight(50, 0.5);
        let error = Isometry3::new(Vector3::new(0.02, -0.05, 0.03), Vector3::new(0.3f64.to_radians(), 0.0, 0.0));
        let est: Vec<_> = gt.iter().map(|p| error * p).collect();
        assert!(matches!(ate(&gt, &est, true), Err(TrajectoryError::Alignment(_))));
        let fit = map_fit(&gt, &est).unwrap();
        let left = fit * error;
        assert!(left.translation.vector.norm() < 1e-9, "{left:?}");
        assert!(left.rotation.angle() < 1e-9, "{left:?}");
        assert!(map_fit(&gt, &est[1..]).is_err());
    }

    #[test]
    fn alignment_removes_a_rigid_offset_but_not_shape_error() {
        let gt: Vec<_> = (0..10)
            .map(|i| Isometry3::translation((i as f64).cos() * 5.0, (i as f64).sin() * 5.0, 0.1 * i as f64))
            .collect();
        let offset = Isometry3::new(Vector3::new(10.0, -4.0, 1.0), Vector3::new(0.0, 0.0, 0.8));
        let est: Vec<_> = gt.iter().map(|p| offset * p).collect();
        assert!(ate(&gt, &est, true).unwrap().rmse < 1e-9);
        assert!(ate(&gt, &est, false).unwrap().rmse > 5.0);
    }

    #[test]
    fn rpe_by_hand() {
        // Truth moves 1 m per frame along x; the estimate 1.1 m per frame: over any segment of
        // length L the translational error is 0.1 L, i.e. 10 %, and there is no rotation.
        let gt = straight(11, 1.0);
        let est = straight(11, 1.1);
        let r = rpe(&gt, &est, &[2.0, 5.0]).unwrap();
        assert!((r.translation_percent - 10.0).abs() < 1e-9, "{r:?}");
        assert!(r.rotation_deg_per_100m.abs() < 1e-9);
        // Segments of 2 m start at frames 0..=8 (9), of 5 m at 0..=5 (6).
        assert_eq!(r.segments, 15);
    }

    #[test]
    fn rpe_rotation_by_hand() {
        // The estimate turns by 1 degree per frame where the truth goes straight (1 m per frame):
        // a 4 m segment accumulates 4 degrees, 1 deg/m = 100 deg/100 m.
        let gt = straight(6, 1.0);
        let est: Vec<_> = (0..6)
            .map(|i| Isometry3::new(Vector3::new(i as f64, 0.0, 0.0), Vector3::new(0.0, 0.0, (i as f64).to_radians())))
            .collect();
        let r = rpe(&gt, &est, &[4.0]).unwrap();
        assert!((r.rotation_deg_per_100m - 100.0).abs() < 1e-6, "{r:?}");
    }

    #[test]
    fn formats_round_trip_and_report_lines() {
        let t = Trajectory {
            poses: (0..4)
                .map(|i| Isometry3::new(Vector3::new(i as f64, 2.0, -1.0), Vector3::new(0.0, 0.1 * i as f64, 0.0)))
                .collect(),
            stamps: Some(vec![0.0, 0.1, 0.2, 0.3]),
        };
        let k = Trajectory::parse(&t.to_kitti()).unwrap();
        let m = Trajectory::parse(&t.to_tum()).unwrap();
        assert!(ate(&t.poses, &k.poses, false).unwrap().max < 1e-8);
        assert!(ate(&t.poses, &m.poses, false).unwrap().max < 1e-8);
        assert_eq!(m.stamps, t.stamps);
        let err = Trajectory::parse("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 x 0 1 0 0 0 0 1 0\n").unwrap_err();
        assert_eq!(err, TrajectoryError::Line { line: 2, reason: "\"x\" is not a number".into() });
    }

    #[test]
    fn pairing_by_stamp_and_by_index() {
        let gt = Trajectory { poses: straight(5, 1.0), stamps: Some(vec![0.0, 0.1, 0.2, 0.3, 0.4]) };
        let est = Trajectory { poses: straight(2, 1.0), stamps: Some(vec![0.101, 0.399]) };
        let (g, e) = pair(&gt, &est, 0.01).unwrap();
        assert_eq!(g, vec![gt.poses[1], gt.poses[4]]);
        assert_eq!(e.len(), 2);
        let no_stamps = Trajectory { poses: straight(4, 1.0), stamps: None };
        assert!(pair(&gt, &no_stamps, 0.01).is_err());
    }
}
