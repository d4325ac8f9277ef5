//! One edge's error and its analytic Jacobians (GTSAM's `BetweenFactor<Pose3>`, in the
//! workspace's tangent order `[ρ; φ]` and right perturbations, [`crate::se3`]).
//!
//! An edge measures `Z`, the pose of `j` in the frame of `i`. Its error is the tangent vector that
//! takes the measurement to the prediction `Tᵢ⁻¹ Tⱼ`:
//!
//! ```text
//! e = log(Z⁻¹ · Tᵢ⁻¹ · Tⱼ)                                                      (1)
//! ```
//!
//! Perturbing both poses on the right, `Tᵢ ← Tᵢ exp(δᵢ)`, `Tⱼ ← Tⱼ exp(δⱼ)`, and moving `exp(−δᵢ)`
//! past `Tᵢ⁻¹ Tⱼ` with the adjoint (`exp(−δᵢ) X = X exp(−Ad(X⁻¹) δᵢ)`):
//!
//! ```text
//! e(δᵢ, δⱼ) = log(Z⁻¹ Tᵢ⁻¹ Tⱼ · exp(−Ad(Tⱼ⁻¹ Tᵢ) δᵢ) · exp(δⱼ))                     (2)
//! ∂e/∂δⱼ =  Jr⁻¹(e)                                                             (3)
//! ∂e/∂δᵢ = −Jr⁻¹(e) · Ad(Tⱼ⁻¹ Tᵢ)                                               (4)
//! ```
//!
//! `Jr⁻¹` is exact ([`crate::se3::right_jacobian_inverse`]), as GTSAM's `Pose3::Logmap`
//! derivative is, so both optimisers take the same Gauss-Newton steps.

use crate::se3;
use nalgebra::{Isometry3, Matrix6, Vector6};

/// An edge's error and Jacobians at one linearisation point.
#[derive(Clone, Copy, Debug)]
pub struct Linearised {
    /// `e`, eq. (1).
    pub error: Vector6<f64>,
    /// `∂e/∂δᵢ`, eq. (4).
    pub d_from: Matrix6<f64>,
    /// `∂e/∂δⱼ`, eq. (3).
    pub d_to: Matrix6<f64>,
}

/// `e`, eq. (1).
pub fn error(measurement: &Isometry3<f64>, from: &Isometry3<f64>, to: &Isometry3<f64>) -> Vector6<f64> {
    se3::log(&(measurement.inverse() * from.inverse() * to))
}

/// `e` and its Jacobians, eqs. (1), (3), (4).
pub fn linearise(measurement: &Isometry3<f64>, from: &Isometry3<f64>, to: &Isometry3<f64>) -> Linearised {
    let error = error(measurement, from, to);
    let d_to = se3::right_jacobian_inverse(&error);
    let d_from = -d_to * se3::adjoint(&(to.inverse() * from));
    Linearised { error, d_from, d_to }
}

#[cfg(test)]
mod tests {
    use super::*;
    use testkit::Rng;

    /// A random pose: translation within ±10 m, rotation of any axis and an angle up to `max_deg`.
    fn random_pose(rng: &mut Rng, max_deg: f64) -> Isometry3<f64> {
        let axis = nalgebra::Vector3::new(rng.gaussian(1.0), rng.gaussian(1.0), rng.gaussian(1.0)).normalize();
        let angle = rng.uniform(0.0, max_deg).to_radians();
        let t = [rng.uniform(-10.0, 10.0), rng.uniform(-10.0, 10.0), rng.uniform(-10.0, 10.0)];
        testkit::pose_from_axis_angle(t, (axis * angle).into())
    }

    /// `∂e/∂δ` of one side by central differences of eq. (1) under right perturbations.
    fn numeric(z: &Isometry3<f64>, from: &Isometry3<f64>, to: &Isometry3<f64>, perturb_from: bool) -> Matrix6<f64> {
        let h = 1e-6;
        let mut j = Matrix6::zeros();
        for k in 0..6 {
            let at = |d: Vector6<f64>| {
                if perturb_from { error(z, &se3::update(from, &d), to) } else { error(z, from, &se3::update(to, &d)) }
            };
            j.set_column(k, &((at(Vector6::ith(k, h)) - at(Vector6::ith(k, -h))) / (2.0 * h)));
        }
        j
    }

    #[test]
    fn jacobians_match_numerical_differentiation() {
        let mut rng = Rng::xorshift64_star(Rng::spread(14));
        for case in 0..60 {
            // Half the cases put the error near a half turn (up to 170 deg), where Jr⁻¹ is large.
            let (from, to) = (random_pose(&mut rng, 180.0), random_pose(&mut rng, 180.0));
            let max_error_deg = if case % 2 == 0 { 170.0 } else { 20.0 };
            let off = random_pose(&mut rng, max_error_deg);
            let z = from.inverse() * to * off.inverse();
            let lin = linearise(&z, &from, &to);
            assert!((lin.error - se3::log(&off)).norm() < 1e-9, "case {case}: the error is log(off)");
            for (analytic, numeric) in
                [(lin.d_from, numeric(&z, &from, &to, true)), (lin.d_to, numeric(&z, &from, &to, false))]
            {
                let scale = 1.0 + numeric.norm();
                assert!((analytic - numeric).norm() < 1e-6 * scale, "case {case}:\n{analytic}\nvs\n{numeric}");
            }
        }
    }

    #[test]
    fn an_exact_measurement_has_zero_error_and_opposite_jacobians_at_identity() {
        let pose = testkit::pose_from_yaw_deg(30.0, [1.0, 2.0, 3.0]);
        let lin = linearise(&Isometry3::identity(), &pose, &pose);
        assert!(lin.error.norm() < 1e-12);
        assert!((lin.d_to - Matrix6::identity()).norm() < 1e-12 && (lin.d_from + Matrix6::identity()).norm() < 1e-12);
    }
}
