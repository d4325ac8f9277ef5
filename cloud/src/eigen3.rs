//! Closed-form eigen-decomposition of symmetric 3x3 matrices (covariances of point neighbourhoods).
//!
//! nalgebra's general iterative solver costs several times more; registration and normal
//! estimation call this once per point per iteration. The method is Eberly's (2014, "A robust
//! eigensolver for 3x3 symmetric matrices"): eigenvalues by the trigonometric formula, the eigenvector
//! of the best-separated eigenvalue from cross products of the rows of A − λI, the second one from a
//! 2x2 problem in the plane orthogonal to the first, the third as their cross product.

use nalgebra::{Matrix3, Vector3};

/// Eigenvalues in ascending order and the matching unit eigenvectors (columns).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SymmetricEigen3 {
    /// λ₀ ≤ λ₁ ≤ λ₂.
    pub values: Vector3<f64>,
    /// Column i is the unit eigenvector of `values[i]`; the columns form a rotation.
    pub vectors: Matrix3<f64>,
}

/// Decomposes a symmetric matrix (only the upper triangle is read).
pub fn symmetric_eigen3(a: &Matrix3<f64>) -> SymmetricEigen3 {
    let scale = a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if scale == 0.0 || !scale.is_finite() {
        return SymmetricEigen3 {
            values: Vector3::repeat(if scale.is_finite() { 0.0 } else { f64::NAN }),
            vectors: Matrix3::identity(),
        };
    }
    // Scaled, shifted by the mean eigenvalue: B = (A/s − q I) has trace 0.
    let m =
        Matrix3::new(a[(0, 0)], a[(0, 1)], a[(0, 2)], a[(0, 1)], a[(1, 1)], a[(1, 2)], a[(0, 2)], a[(1, 2)], a[(2, 2)])
            / scale;
    let q = m.trace() / 3.0;
    let b = m - Matrix3::identity() * q;
    let p = (b.norm_squared() / 6.0).sqrt();
    if p < 1e-14 {
        return SymmetricEigen3 { values: Vector3::repeat(q * scale), vectors: Matrix3::identity() };
    }
    let half_det = (b / p).determinant() / 2.0;
    let phi = half_det.clamp(-1.0, 1.0).acos() / 3.0;
    let third = 2.0 * std::f64::consts::PI / 3.0;
    // β₂ ≥ β₁ ≥ β₀ (cos is decreasing on [0, π]).
    let b2 = 2.0 * phi.cos();
    let b0 = 2.0 * (phi + third).cos();
    let b1 = -(b0 + b2);
    let values = Vector3::new(b0, b1, b2) * p;
    // Start from the eigenvalue farthest from the middle one: its eigenvector is best conditioned.
    let (first, second) = if half_det >= 0.0 { (2, 1) } else { (0, 1) };
    let v_first = nullspace_vector(&(m - Matrix3::identity() * (values[first] + q)));
    let v_second = second_vector(&m, &v_first, values[second] + q);
    let v_third = v_first.cross(&v_second);
    let mut vectors = Matrix3::zeros();
    vectors.set_column(first, &v_first);
    vectors.set_column(second, &v_second);
    vectors.set_column(3 - first - second, &v_third);
    // Keep a right-handed frame.
    if vectors.determinant() < 0.0 {
        vectors.set_column(3 - first - second, &-v_third);
    }
    SymmetricEigen3 { values: (values + Vector3::repeat(q)) * scale, vectors }
}

/// A unit vector in the null space of a rank-2 symmetric matrix: the largest cross product of its rows.
fn nullspace_vector(m: &Matrix3<f64>) -> Vector3<f64> {
    let (r0, r1, r2) = (m.row(0).transpose(), m.row(1).transpose(), m.row(2).transpose());
    let candidates = [r0.cross(&r1), r0.cross(&r2), r1.cross(&r2)];
    let best =
        candidates.iter().max_by(|a, b| a.norm_squared().total_cmp(&b.norm_squared())).copied().unwrap_or(Vector3::x());
    let n = best.norm();
    if n > 0.0 { best / n } else { Vector3::x() }
}

/// The eigenvector of `lambda` orthogonal to `v0`: the null vector of the 2x2 restriction of
/// `m − λI` to the plane orthogonal to `v0`.
fn second_vector(m: &Matrix3<f64>, v0: &Vector3<f64>, lambda: f64) -> Vector3<f64> {
    let u = if v0.x.abs() > v0.y.abs() {
        Vector3::new(-v0.z, 0.0, v0.x).normalize()
    } else {
        Vector3::new(0.0, v0.z, -v0.y).normalize()
    };
    let v = v0.cross(&u);
    let a = m - Matrix3::identity() * lambda;
    let (auu, auv, avv) = ((a * u).dot(&u), (a * u).dot(&v), (a * v).dot(&v));
    // Null vector of [[auu, auv], [auv, avv]]: orthogonal to its larger row.
    let w = if auu.abs() >= avv.abs() {
        if auu.abs().max(auv.abs()) > 0.0 { (-auv, auu) } else { (1.0, 0.0) }
    } else {
        (avv, -auv)
    };
    let r = (u * w.0 + v * w.1).normalize();
    if r.iter().all(|x| x.is_finite()) { r } else { u }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, SymmetricEigen};

    fn check(a: &Matrix3<f64>) {
        let e = symmetric_eigen3(a);
        let reference = SymmetricEigen::new(*a);
        let mut want: Vec<f64> = reference.eigenvalues.iter().copied().collect();
        want.sort_by(f64::total_cmp);
        let tol = 1e-9 * a.norm().max(1e-300);
        for i in 0..3 {
            assert!((e.values[i] - want[i]).abs() <= tol, "{a}: {} vs {want:?}", e.values);
            let v = e.vectors.column(i);
            assert!((v.norm() - 1.0).abs() < 1e-9);
            assert!((a * v - v * e.values[i]).norm() <= 1e-8 * a.norm().max(1e-300), "{a} column {i}");
        }
        assert!((e.vectors.determinant() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn matches_the_iterative_solver() {
        let mut rng = testkit::Rng::new(0x1234_5678_9abc_def0);
        let mut rand = move || rng.f64() * 2.0 - 1.0;
        for _ in 0..2000 {
            let r = Rotation3::new(Vector3::new(rand(), rand(), rand()) * 3.0);
            let d = Matrix3::from_diagonal(&Vector3::new(rand(), rand() * 10.0, rand() * 1e-3));
            check(&(r * d * r.transpose()));
        }
    }

    #[test]
    fn repeated_and_degenerate_spectra() {
        let r = Rotation3::new(Vector3::new(0.3, -1.1, 0.7));
        for d in
            [[1.0, 1.0, 5.0], [2.0, 7.0, 7.0], [3.0, 3.0, 3.0], [0.0, 0.0, 1.0], [0.0, 1e-12, 1.0], [1e-6, 2e-6, 1e-3]]
        {
            check(&(r * Matrix3::from_diagonal(&Vector3::from(d)) * r.transpose()));
        }
        let zero = symmetric_eigen3(&Matrix3::zeros());
        assert_eq!(zero.values, Vector3::zeros());
    }

    #[test]
    fn planar_neighbourhood_normal() {
        // Points on the plane z = 0.5 x: the smallest eigenvector is the plane normal.
        let pts: Vec<Vector3<f64>> =
            (0..25).map(|i| Vector3::new((i % 5) as f64, (i / 5) as f64, 0.5 * (i % 5) as f64)).collect();
        let mean = pts.iter().sum::<Vector3<f64>>() / 25.0;
        let cov = pts.iter().map(|p| (p - mean) * (p - mean).transpose()).sum::<Matrix3<f64>>() / 25.0;
        let e = symmetric_eigen3(&cov);
        let n = e.vectors.column(0);
        let want = Vector3::new(-0.5, 0.0, 1.0).normalize();
        assert!(n.dot(&want).abs() > 1.0 - 1e-12);
        assert!(e.values[0].abs() < 1e-12);
    }
}
