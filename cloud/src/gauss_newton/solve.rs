//! Solving the normal equations for a step `δ`.

use nalgebra::{Matrix6, SymmetricEigen, Vector6};

use super::normal_equations::{LeverArm, NormalEquations};

/// Solves `(H + λI) δ = −b` (Levenberg-Marquardt damping); `None` when the damped `H` is not
/// positive definite or the step is not finite.
pub fn solve_damped<S>(eq: &NormalEquations<S>, lambda: f64) -> Option<Vector6<f64>> {
    let damped = eq.h + Matrix6::identity() * lambda;
    damped.cholesky().map(|c| c.solve(&-eq.b)).filter(|d| d.iter().all(|v| v.is_finite()))
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
/// Rotations are scaled by the RMS lever arm `L` first (`δ' = [ρ; L φ]`), so that both halves of
/// the problem are in metres and their eigenvalues compare.
pub fn solve_remapped(eq: &NormalEquations<LeverArm>, degeneracy_ratio: f64) -> Remapped {
    let sum = eq.sums.weight_sum.max(1e-12);
    let lever = (eq.sums.lever_sum / sum).sqrt().max(1e-3);
    let scale = Vector6::new(1.0, 1.0, 1.0, 1.0 / lever, 1.0 / lever, 1.0 / lever);
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
