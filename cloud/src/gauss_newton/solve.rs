//! Solving the normal equations for a step `δ`.

use nalgebra::{Matrix6, SymmetricEigen, Vector3, Vector6};

use super::normal_equations::{LeverArm, NormalEquations};

/// Solves `(H + λI) δ = −b` (Levenberg-Marquardt damping); `None` when the damped `H` is not
/// positive definite or the step is not finite.
pub fn solve_damped<S>(eq: &NormalEquations<S>, lambda: f64) -> Option<Vector6<f64>> {
    let damped = eq.h + Matrix6::identity() * lambda;
    damped.cholesky().map(|c| c.solve(&-eq.b)).filter(|d| d.iter().all(|v| v.is_finite()))
}

/// How [`solve_remapped`] puts rotations in metres before it compares the eigenvalues.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RotationScale {
    /// One lever arm for all three rotations: the points' RMS distance from the origin.
    #[default]
    Common,
    /// Each rotation by its own lever arm: the points' RMS distance from its axis.
    PerAxis,
}

/// A step that leaves the unconstrained directions alone.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Remapped {
    /// The step `δ = [ρ; φ]`.
    pub delta: Vector6<f64>,
    /// Eigen-directions kept at zero.
    pub degenerate: usize,
    /// Smallest eigenvalue of the scaled `H` over `Σ w` (the conditioning).
    pub min_eigen_ratio: f64,
}

/// Solves `H δ = −b`, keeping `δ` at zero along eigen-directions whose eigenvalue is below
/// `degeneracy_ratio · Σ w` (Zhang, Kaess & Singh 2016, "solution remapping"): there the terms do
/// not constrain the pose, so the prior the solver started from is kept instead of drifting.
///
/// Rotations are scaled to metres first (`δ' = [ρ; L∘φ]`), so that both halves of the problem are
/// in metres of point motion and their eigenvalues compare: by one lever arm, the points' RMS
/// distance from the origin ([`RotationScale::Common`]), or each by its own, their RMS distance
/// from its axis ([`RotationScale::PerAxis`]). The common one is set by the far points: looking
/// down a 3 m wide aisle it is ~10 m, while a roll moves the points by their ~1 m offsets from
/// the aisle's axis, so a well-measured roll looks degenerate and is left to the prior.
pub fn solve_remapped(eq: &NormalEquations<LeverArm>, degeneracy_ratio: f64, rotations: RotationScale) -> Remapped {
    let sum = eq.sums.weight_sum.max(1e-12);
    let lever = match rotations {
        RotationScale::Common => Vector3::repeat(eq.sums.from_origin()),
        RotationScale::PerAxis => eq.sums.about_axes(),
    }
    .map(|l| l.max(1e-3));
    let scale = Vector6::new(1.0, 1.0, 1.0, 1.0 / lever.x, 1.0 / lever.y, 1.0 / lever.z);
    let s = Matrix6::from_diagonal(&scale);
    let eig = SymmetricEigen::new(s * eq.h * s);
    let threshold = degeneracy_ratio * sum;
    let projected_b = eig.eigenvectors.transpose() * (s * eq.b);
    let mut delta_eig = Vector6::zeros();
    let mut degenerate = 0;
    for i in 0..6 {
        let lambda = eig.eigenvalues[i];
        if lambda > threshold {
            delta_eig[i] = -projected_b[i] / lambda;
        } else {
            degenerate += 1;
        }
    }
    let min_eigen_ratio = eig.eigenvalues.min() / sum;
    Remapped { delta: s * (eig.eigenvectors * delta_eig), degenerate, min_eigen_ratio }
}
