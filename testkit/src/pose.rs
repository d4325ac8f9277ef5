//! Poses as the tests write them, and how far an estimate is from the truth.

use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// A pose turned by `yaw_deg` about z, then moved to `t`.
pub fn pose_from_yaw_deg(yaw_deg: f64, t: [f64; 3]) -> Isometry3<f64> {
    pose_from_axis_angle(t, [0.0, 0.0, yaw_deg.to_radians()])
}

/// A pose at `t` rotated by `axis_angle` (the axis scaled by the angle in radians).
pub fn pose_from_axis_angle(t: [f64; 3], axis_angle: [f64; 3]) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), UnitQuaternion::from_scaled_axis(axis_angle.into()))
}

/// The translation and rotation of `truth⁻¹ · estimate`: the definition of `cloud::se3::pose_error`,
/// restated because this crate must not depend on `cloud`.
#[derive(Clone, Copy, Debug, PartialEq)]
struct PoseError {
    translation_m: f64,
    rotation_deg: f64,
}

fn pose_error(estimate: &Isometry3<f64>, truth: &Isometry3<f64>) -> PoseError {
    let d = truth.inverse() * estimate;
    PoseError { translation_m: d.translation.vector.norm(), rotation_deg: d.rotation.angle().to_degrees() }
}

/// Panics unless `actual` is strictly within `max_translation_m` and `max_rotation_deg` of
/// `expected`, naming both errors and both bounds, after an optional `format!`-style context
/// (which method, which case) as `assert!` takes one.
///
/// ```
/// let truth = testkit::pose_from_yaw_deg(30.0, [1.0, 2.0, 3.0]);
/// testkit::assert_pose_close!(&truth, &truth, 1e-9, 1e-9);
/// testkit::assert_pose_close!(&truth, &truth, 1e-9, 1e-9, "case {}", 1);
/// ```
#[macro_export]
macro_rules! assert_pose_close {
    ($actual:expr, $expected:expr, $max_translation_m:expr, $max_rotation_deg:expr $(,)?) => {
        $crate::check_pose_close($actual, $expected, $max_translation_m, $max_rotation_deg, ::std::format_args!(""))
    };
    ($actual:expr, $expected:expr, $max_translation_m:expr, $max_rotation_deg:expr, $($context:tt)+) => {
        $crate::check_pose_close(
            $actual,
            $expected,
            $max_translation_m,
            $max_rotation_deg,
            ::std::format_args!("{}: ", ::std::format_args!($($context)+)),
        )
    };
}

/// What [`assert_pose_close!`] expands to; `context` prefixes the message.
#[doc(hidden)]
#[track_caller]
pub fn check_pose_close(
    actual: &Isometry3<f64>,
    expected: &Isometry3<f64>,
    max_translation_m: f64,
    max_rotation_deg: f64,
    context: std::fmt::Arguments,
) {
    let e = pose_error(actual, expected);
    assert!(
        e.translation_m < max_translation_m && e.rotation_deg < max_rotation_deg,
        "{context}pose off by {:.6} m and {:.6} deg (allowed below {max_translation_m} m and {max_rotation_deg} deg)",
        e.translation_m,
        e.rotation_deg
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn yaw_builder_turns_about_z() {
        for yaw in [-179.0, -90.0, -33.3, 0.0, 1e-9, 12.5, 45.0, 90.0, 135.0, 180.0] {
            let t = [1.5, -2.0, 0.25];
            let euler = UnitQuaternion::from_euler_angles(0.0, 0.0, f64::to_radians(yaw));
            let e = pose_error(&pose_from_yaw_deg(yaw, t), &Isometry3::from_parts(Vector3::from(t).into(), euler));
            assert!(e.translation_m == 0.0 && e.rotation_deg < 1e-12, "{yaw}: {e:?}");
        }
    }

    #[test]
    fn errors_of_a_known_offset() {
        let truth = pose_from_yaw_deg(30.0, [1.0, 2.0, 3.0]);
        let estimate = truth * pose_from_axis_angle([0.3, 0.4, 0.0], [0.0, 0.0, 2f64.to_radians()]);
        let e = pose_error(&estimate, &truth);
        assert!((e.translation_m - 0.5).abs() < 1e-12 && (e.rotation_deg - 2.0).abs() < 1e-9, "{e:?}");
        crate::assert_pose_close!(&estimate, &truth, 0.51, 2.01);
    }

    #[test]
    #[should_panic(expected = "case 7: pose off by 0.500000 m")]
    fn a_wrong_translation_fails() {
        let truth = pose_from_yaw_deg(30.0, [1.0, 2.0, 3.0]);
        let off = truth * pose_from_axis_angle([0.3, 0.4, 0.0], [0.0; 3]);
        crate::assert_pose_close!(&off, &truth, 0.1, 1.0, "case {}", 7);
    }

    #[test]
    #[should_panic(expected = "and 2.000000 deg")]
    fn a_wrong_rotation_fails() {
        let truth = pose_from_yaw_deg(30.0, [1.0, 2.0, 3.0]);
        crate::assert_pose_close!(&(truth * pose_from_yaw_deg(2.0, [0.0; 3])), &truth, 0.1, 1.0);
    }
}
