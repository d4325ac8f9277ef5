//! Cost factors: how a residual between a transformed source point and a target Gaussian is weighed,
//! and the per-thread accumulation of the Gauss-Newton system.

use nalgebra::{Isometry3, Matrix3, Matrix6, Vector3, Vector6};
use rayon::prelude::*;

use super::covariance::PLANE_EPSILON;
use super::target::{GaussianCloud, Target};
use crate::se3::skew;

/// A cost term `eᵀ W e` on the residual `e = μ_target − T p_source`; the factor chooses `W`.
pub trait Factor: Sync {
    /// The weight of one correspondence, given both covariances and the rotation of `T`; `None`
    /// drops it (e.g. a singular matrix).
    fn weight(
        &self,
        target_cov: &Matrix3<f64>,
        source_cov: &Matrix3<f64>,
        rotation: &Matrix3<f64>,
    ) -> Option<Matrix3<f64>>;
}

/// Generalized ICP: the Mahalanobis distance under the fused covariance `(C_t + R C_s Rᵀ)⁻¹`.
#[derive(Clone, Copy, Debug, Default)]
pub struct GicpFactor;

impl Factor for GicpFactor {
    fn weight(&self, target_cov: &Matrix3<f64>, source_cov: &Matrix3<f64>, r: &Matrix3<f64>) -> Option<Matrix3<f64>> {
        (target_cov + r * source_cov * r.transpose()).try_inverse()
    }
}

/// Point-to-plane ICP: `W = n nᵀ` with `n` the target normal.
///
/// The normal comes from the regularised target covariance `C = I − (1 − ε) n nᵀ`, so
/// `n nᵀ = (I − C) / (1 − ε)` needs no eigen-decomposition; shapeless points (identity) weigh zero.
#[derive(Clone, Copy, Debug, Default)]
pub struct PointToPlaneFactor;

impl Factor for PointToPlaneFactor {
    fn weight(&self, target_cov: &Matrix3<f64>, _: &Matrix3<f64>, _: &Matrix3<f64>) -> Option<Matrix3<f64>> {
        Some((Matrix3::identity() - target_cov) / (1.0 - PLANE_EPSILON))
    }
}

/// The Gauss-Newton system of all correspondences at one pose, with update `T ← T · exp(δ)` and
/// `δ = [ρ; φ]` (translation first, as in [`crate::se3`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinearSystem {
    /// `Σ Jᵀ W J`: the information matrix of the pose (right-perturbation tangent space).
    pub h: Matrix6<f64>,
    /// `Σ Jᵀ W e`: the gradient of half the cost.
    pub b: Vector6<f64>,
    /// `Σ eᵀ W e`: the cost (squared Mahalanobis distances for GICP).
    pub error: f64,
    /// `Σ |e|²`, m²: the plain squared distances, for a unit-bearing fitness.
    pub sum_sq_distance: f64,
    /// Number of source points that found a target within the correspondence distance.
    pub inliers: usize,
}

impl LinearSystem {
    /// The empty sum.
    pub fn zero() -> Self {
        LinearSystem { h: Matrix6::zeros(), b: Vector6::zeros(), error: 0.0, sum_sq_distance: 0.0, inliers: 0 }
    }

    /// The sum of two partial systems (the rayon reduction).
    fn merge(mut self, other: Self) -> Self {
        self.h += other.h;
        self.b += other.b;
        self.error += other.error;
        self.sum_sq_distance += other.sum_sq_distance;
        self.inliers += other.inliers;
        self
    }
}

/// Source points per rayon work item: large enough to amortise task overhead, small enough to balance.
const CHUNK: usize = 256;

/// Marks a source point without correspondence.
pub(crate) const NO_MATCH: u32 = u32::MAX;

/// Finds each source point's correspondence at `pose` (stored in `matches`) and sums the system.
///
/// Each rayon task folds into its own system, and the per-task systems are summed once at the end:
/// no locks and no per-point allocation.
pub(crate) fn linearize<T: Target, F: Factor>(
    source: &GaussianCloud,
    target: &T,
    factor: &F,
    pose: &Isometry3<f64>,
    max_dist_sq: f64,
    matches: &mut [u32],
) -> LinearSystem {
    let r = pose.rotation.to_rotation_matrix().into_inner();
    let t = pose.translation.vector;
    matches
        .par_chunks_mut(CHUNK)
        .zip(source.points.par_chunks(CHUNK).zip(source.covariances.par_chunks(CHUNK)))
        // The accumulator is a 300-byte struct: folding whole chunks moves it once per chunk, not per point.
        .fold(LinearSystem::zero, |mut sys, (matches, (points, covariances))| {
            for ((m, p), cs) in matches.iter_mut().zip(points).zip(covariances) {
                let q = r * p + t;
                *m = target.nearest(&q, max_dist_sq).unwrap_or(NO_MATCH);
                if *m != NO_MATCH {
                    add_term(&mut sys, target, factor, *m, p, &q, cs, &r);
                }
            }
            sys
        })
        .reduce(LinearSystem::zero, LinearSystem::merge)
}

/// Adds one correspondence's `Jᵀ W J`, `Jᵀ W e` and `eᵀ W e`.
#[allow(clippy::too_many_arguments)] // the hot loop: passing parts avoids rebuilding a struct per point
#[inline(always)]
fn add_term<T: Target, F: Factor>(
    sys: &mut LinearSystem,
    target: &T,
    factor: &F,
    m: u32,
    p: &Vector3<f64>,
    q: &Vector3<f64>,
    source_cov: &Matrix3<f64>,
    r: &Matrix3<f64>,
) {
    let Some(w) = factor.weight(target.covariance(m), source_cov, r) else { return };
    let e = target.mean(m) - q;
    // d(T exp(δ) p)/dδ = R [I, −[p]×] and e = μ − T p, so J = −R [I, −[p]×]. In the source frame
    // (A = Rᵀ W R, g = Rᵀ W e) the blocks are H = [A, −A[p]×; [p]×A, −[p]×A[p]×] and
    // b = [−g; g × p]: fewer products than forming the 3x6 Jacobian.
    let we = w * e;
    let a = r.transpose() * w * r;
    let g = r.transpose() * we;
    let s = skew(p);
    let a_s = a * s;
    let mut h = Matrix6::zeros();
    h.fixed_view_mut::<3, 3>(0, 0).copy_from(&a);
    h.fixed_view_mut::<3, 3>(0, 3).copy_from(&-a_s);
    h.fixed_view_mut::<3, 3>(3, 0).copy_from(&-a_s.transpose());
    h.fixed_view_mut::<3, 3>(3, 3).copy_from(&-(s * a_s));
    sys.h += h;
    let mut b = Vector6::zeros();
    b.fixed_rows_mut::<3>(0).copy_from(&-g);
    b.fixed_rows_mut::<3>(3).copy_from(&g.cross(p));
    sys.b += b;
    sys.error += e.dot(&we);
    sys.sum_sq_distance += e.norm_squared();
    sys.inliers += 1;
}

/// The cost `Σ eᵀ W e` at `pose` over the correspondences fixed by the last [`linearize`].
pub(crate) fn evaluate<T: Target, F: Factor>(
    source: &GaussianCloud,
    target: &T,
    factor: &F,
    pose: &Isometry3<f64>,
    matches: &[u32],
) -> f64 {
    let r = pose.rotation.to_rotation_matrix().into_inner();
    let t = pose.translation.vector;
    matches
        .par_chunks(CHUNK)
        .zip(source.points.par_chunks(CHUNK).zip(source.covariances.par_chunks(CHUNK)))
        .map(|(matches, (points, covariances))| {
            let mut cost = 0.0;
            for ((&m, p), cs) in matches.iter().zip(points).zip(covariances) {
                if m == NO_MATCH {
                    continue;
                }
                let Some(w) = factor.weight(target.covariance(m), cs, &r) else { continue };
                let e = target.mean(m) - (r * p + t);
                cost += e.dot(&(w * e));
            }
            cost
        })
        .sum()
}
