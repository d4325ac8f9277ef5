//! SE(3) helpers: exponential and logarithm maps, interpolation, error metrics and matrix forms.
//!
//! Tangent vectors are ordered `[ρ (translation part); φ (rotation part)]`, both in metres/radians.
//! A pose is perturbed on the right, in its own (body) frame: `T ← T · exp(δ)` ([`update`]). Every
//! solver of the workspace linearises and steps that way ([`crate::gauss_newton`]), and the
//! information matrices it reports live in that tangent space.

use nalgebra::{Isometry3, Matrix3, Matrix4, Matrix6, Rotation3, Translation3, UnitQuaternion, Vector3, Vector6};

/// The skew-symmetric matrix `[v]×`, so that `[v]× w = v × w`.
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The left Jacobian of SO(3), `V(φ)`, that couples rotation and translation in SE(3)'s exponential.
fn so3_left_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let k = skew(phi);
    if theta < 1e-6 {
        // Taylor expansion: the closed form divides by θ² and θ³.
        return Matrix3::identity() + 0.5 * k + k * k / 6.0;
    }
    let t2 = theta * theta;
    Matrix3::identity() + (1.0 - theta.cos()) / t2 * k + (theta - theta.sin()) / (t2 * theta) * k * k
}

/// SE(3) exponential: the rigid transform of tangent vector `ξ = [ρ; φ]`.
pub fn exp(xi: &Vector6<f64>) -> Isometry3<f64> {
    let rho = xi.fixed_rows::<3>(0).into_owned();
    let phi = xi.fixed_rows::<3>(3).into_owned();
    let rotation = UnitQuaternion::from_scaled_axis(phi);
    Isometry3::from_parts(Translation3::from(so3_left_jacobian(&phi) * rho), rotation)
}

/// The right-perturbation update `T · exp(δ)`: `δ` moves the pose in its own frame.
pub fn update(t: &Isometry3<f64>, delta: &Vector6<f64>) -> Isometry3<f64> {
    t * exp(delta)
}

/// SE(3) logarithm: the tangent vector `[ρ; φ]` with `exp(log(T)) = T` (rotation angle in [0, π]).
pub fn log(t: &Isometry3<f64>) -> Vector6<f64> {
    let phi = t.rotation.scaled_axis();
    let v = so3_left_jacobian(&phi);
    // V is invertible for |φ| < 2π; the angle is at most π here.
    let rho = v.try_inverse().unwrap_or_else(Matrix3::identity) * t.translation.vector;
    let mut xi = Vector6::zeros();
    xi.fixed_rows_mut::<3>(0).copy_from(&rho);
    xi.fixed_rows_mut::<3>(3).copy_from(&phi);
    xi
}

/// The adjoint of `T = (R, t)`, so that `T · exp(ξ) · T⁻¹ = exp(Ad(T) ξ)`: moves a right
/// perturbation of one frame into another. With `ξ = [ρ; φ]`,
///
/// ```text
/// Ad(T) = [ R   [t]× R ]
///         [ 0      R   ]                                                     (1)
/// ```
pub fn adjoint(t: &Isometry3<f64>) -> Matrix6<f64> {
    let r = t.rotation.to_rotation_matrix().into_inner();
    let mut ad = Matrix6::zeros();
    ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    ad.fixed_view_mut::<3, 3>(0, 3).copy_from(&(skew(&t.translation.vector) * r));
    ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    ad
}

/// The inverse right Jacobian of SE(3): `log(exp(ξ) · exp(δ)) ≈ ξ + Jr⁻¹(ξ) δ` for small `δ`, the
/// derivative of a logarithm under a right perturbation (a pose-graph edge's error).
///
/// `Jr(ξ) = Jl(−ξ)`, and the left Jacobian is block triangular (Barfoot, "State Estimation for
/// Robotics", eq. 7.85), so with `ψ = −φ`, `σ = −ρ`:
///
/// ```text
/// Jr⁻¹(ξ) = [ Jl⁻¹(ψ)   −Jl⁻¹(ψ) Q(σ, ψ) Jl⁻¹(ψ) ]
///           [    0              Jl⁻¹(ψ)         ]                            (2)
/// ```
pub fn right_jacobian_inverse(xi: &Vector6<f64>) -> Matrix6<f64> {
    let sigma = -xi.fixed_rows::<3>(0).into_owned();
    let psi = -xi.fixed_rows::<3>(3).into_owned();
    let jl_inv = so3_left_jacobian_inverse(&psi);
    let mut j = Matrix6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&jl_inv);
    j.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-jl_inv * se3_left_jacobian_q(&sigma, &psi) * jl_inv));
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(&jl_inv);
    j
}

/// The inverse of [`so3_left_jacobian`] (Barfoot eq. 7.77), for angles up to π:
/// `Jl⁻¹(φ) = I − ½[φ]× + (1/θ² − cot(θ/2) / 2θ) [φ]×²`.
fn so3_left_jacobian_inverse(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let k = skew(phi);
    // The closed form cancels to 1/12 as θ → 0; its Taylor series is exact to rounding below 1e-3.
    let c = if theta < 1e-3 {
        1.0 / 12.0 + theta * theta / 720.0
    } else {
        1.0 / (theta * theta) - 1.0 / (2.0 * theta * (theta / 2.0).tan())
    };
    Matrix3::identity() - 0.5 * k + c * k * k
}

/// The coupling block `Q(ρ, φ)` of SE(3)'s left Jacobian (Barfoot eq. 7.86).
fn se3_left_jacobian_q(rho: &Vector3<f64>, phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let (p, r) = (skew(phi), skew(rho));
    let t2 = theta * theta;
    // The closed forms cancel catastrophically for small θ (the last divides by θ⁵): below 1e-3
    // their Taylor series, whose next terms are below 1e-12 of the first.
    let (c1, c2, c3) = if theta < 1e-3 {
        (1.0 / 6.0 - t2 / 120.0, 1.0 / 24.0 - t2 / 720.0, 1.0 / 120.0 - t2 / 2520.0)
    } else {
        let (s, c) = theta.sin_cos();
        (
            (theta - s) / (t2 * theta),
            (t2 + 2.0 * c - 2.0) / (2.0 * t2 * t2),
            (2.0 * theta - 3.0 * s + theta * c) / (2.0 * t2 * t2 * theta),
        )
    };
    0.5 * r
        + c1 * (p * r + r * p + p * r * p)
        + c2 * (p * p * r + r * p * p - 3.0 * p * r * p)
        + c3 * (p * r * p * p + p * p * r * p)
}

/// Geodesic interpolation between `a` (s = 0) and `b` (s = 1): `a · exp(s · log(a⁻¹ b))`.
pub fn interpolate(a: &Isometry3<f64>, b: &Isometry3<f64>, s: f64) -> Isometry3<f64> {
    a * exp(&(s * log(&(a.inverse() * b))))
}

/// Translation and rotation size of a transform: metres, and degrees of rotation angle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseError {
    /// Length of the translation, metres.
    pub translation_m: f64,
    /// Rotation angle, degrees.
    pub rotation_deg: f64,
}

/// How far `estimate` is from `truth`: the size of `truth⁻¹ · estimate`.
pub fn pose_error(estimate: &Isometry3<f64>, truth: &Isometry3<f64>) -> PoseError {
    let d = truth.inverse() * estimate;
    PoseError { translation_m: d.translation.vector.norm(), rotation_deg: d.rotation.angle().to_degrees() }
}

/// The homogeneous 4x4 matrix of a transform.
pub fn to_matrix(t: &Isometry3<f64>) -> Matrix4<f64> {
    t.to_homogeneous()
}

/// A rigid transform from a 4x4 matrix whose rotation block may carry rounding noise (e.g. read from
/// a text file): the rotation is projected onto SO(3). `None` if non-finite or not a rotation.
pub fn from_matrix(m: &Matrix4<f64>) -> Option<Isometry3<f64>> {
    if !m.iter().all(|v| v.is_finite()) {
        return None;
    }
    let r = m.fixed_view::<3, 3>(0, 0).into_owned();
    // A proper rotation has det 1 and orthonormal columns; allow text-file rounding only.
    if (r.determinant() - 1.0).abs() > 1e-3 || (r.transpose() * r - Matrix3::identity()).norm() > 1e-3 {
        return None;
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&r));
    Some(Isometry3::from_parts(Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]), rotation))
}

/// The 12 numbers of a KITTI pose line: the row-major 3x4 matrix `[R | t]`.
pub fn to_kitti_row(t: &Isometry3<f64>) -> [f64; 12] {
    let m = t.to_homogeneous();
    std::array::from_fn(|i| m[(i / 4, i % 4)])
}

/// A transform from the 12 numbers of a KITTI pose line (see [`from_matrix`] for the checks).
pub fn from_kitti_row(v: &[f64; 12]) -> Option<Isometry3<f64>> {
    let mut m = Matrix4::identity();
    for (i, x) in v.iter().enumerate() {
        m[(i / 4, i % 4)] = *x;
    }
    from_matrix(&m)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(i: usize) -> Vector6<f64> {
        let f = i as f64;
        Vector6::new(
            (f * 0.7).sin() * 5.0,
            f * 0.1 - 2.0,
            (f * 1.9).cos(),
            (f * 0.3).sin(),
            (f * 0.5).cos() * 0.8,
            f * 0.013,
        )
    }

    #[test]
    fn log_inverts_exp() {
        for i in 0..100 {
            let xi = sample(i);
            assert!((log(&exp(&xi)) - xi).norm() < 1e-9, "{i}");
        }
        assert!(
            (log(&exp(&Vector6::new(1.0, 2.0, 3.0, 1e-9, 0.0, 0.0))) - Vector6::new(1.0, 2.0, 3.0, 1e-9, 0.0, 0.0))
                .norm()
                < 1e-12
        );
    }

    #[test]
    fn exp_matches_its_derivative_definition() {
        // A constant twist applied in N small steps integrates to exp of the whole twist.
        let xi = Vector6::new(1.0, 0.2, -0.3, 0.1, -0.4, 0.9);
        let n = 20_000;
        let step = exp(&(xi / n as f64));
        let mut t = Isometry3::identity();
        for _ in 0..n {
            t = step * t;
        }
        let e = pose_error(&t, &exp(&xi));
        assert!(e.translation_m < 1e-6 && e.rotation_deg < 1e-6, "{e:?}");
    }

    #[test]
    fn interpolation_hits_ends_and_middle() {
        let a = exp(&sample(3));
        let b = exp(&sample(8));
        assert!(pose_error(&interpolate(&a, &b, 0.0), &a).translation_m < 1e-12);
        let e = pose_error(&interpolate(&a, &b, 1.0), &b);
        assert!(e.translation_m < 1e-9 && e.rotation_deg < 1e-9);
        let m = interpolate(&a, &b, 0.5);
        let e = pose_error(&(m * (a.inverse() * m)), &b);
        assert!(e.translation_m < 1e-9 && e.rotation_deg < 1e-9, "two half steps make the whole");
    }

    #[test]
    fn adjoint_moves_a_perturbation_between_frames() {
        for i in 0..20 {
            let t = exp(&sample(i));
            let xi = sample(i + 31) * 0.3;
            let moved = t * exp(&xi) * t.inverse();
            let e = pose_error(&moved, &exp(&(adjoint(&t) * xi)));
            assert!(e.translation_m < 1e-9 && e.rotation_deg < 1e-9, "{i}: {e:?}");
        }
    }

    #[test]
    fn right_jacobian_inverse_matches_numerical_differentiation() {
        // Small, ordinary and nearly half-turn rotations (170 deg), and the exact identity.
        let mut cases: Vec<Vector6<f64>> = (0..30).map(sample).collect();
        cases.push(Vector6::zeros());
        cases.push(Vector6::new(0.5, -1.0, 2.0, 1e-5, -2e-5, 1e-5));
        let axis = Vector3::new(0.3, -0.5, 0.8).normalize() * 170f64.to_radians();
        cases.push(Vector6::new(1.0, 2.0, -0.5, axis.x, axis.y, axis.z));
        for xi in cases {
            let t = exp(&xi);
            let h = 1e-6;
            let mut numeric = Matrix6::zeros();
            for k in 0..6 {
                let d = Vector6::ith(k, h);
                numeric.set_column(k, &((log(&(t * exp(&d))) - log(&(t * exp(&-d)))) / (2.0 * h)));
            }
            let analytic = right_jacobian_inverse(&xi);
            assert!((analytic - numeric).norm() < 1e-6 * (1.0 + numeric.norm()), "{xi}: {analytic} vs {numeric}");
        }
    }

    #[test]
    fn kitti_rows_round_trip_and_reject_non_rotations() {
        let t = exp(&sample(5));
        let back = from_kitti_row(&to_kitti_row(&t)).unwrap();
        let e = pose_error(&back, &t);
        assert!(e.translation_m < 1e-12 && e.rotation_deg < 1e-6);
        let mut bad = to_kitti_row(&t);
        bad[0] *= 2.0;
        assert!(from_kitti_row(&bad).is_none());
        bad[0] = f64::NAN;
        assert!(from_kitti_row(&bad).is_none());
    }
}
