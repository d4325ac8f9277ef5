//! Cost factors: how a residual between a transformed source point and a target Gaussian is weighed,
//! and the normal equations of all correspondences at one pose (summed as [`crate::gauss_newton`]
//! sums every system: per block, blocks in order).

use nalgebra::{Isometry3, Matrix3, Matrix6, Point3, Vector3, Vector6};
use rayon::prelude::*;

use super::covariance::PLANE_EPSILON;
use super::target::{GaussianCloud, PackedCovariance, Target};
use crate::gauss_newton::{self, BLOCK, NormalEquations, Sums, reduce_in_order, sum_blocks};

/// A cost term `eᵀ W e` on the residual `e = μ_target − T p_source`; the factor chooses `W`.
pub trait Factor: Sync {
    /// The weight of one correspondence, given both covariances and the rotation of `T`; `None`
    /// drops it (e.g. a singular matrix).
    fn weight(
        &self,
        target_cov: &Matrix3<f64>,
        source_cov: &PackedCovariance,
        rotation: &Matrix3<f64>,
    ) -> Option<Matrix3<f64>>;
}

/// Generalized ICP: the Mahalanobis distance under the fused covariance `(C_t + R C_s Rᵀ)⁻¹`.
#[derive(Clone, Copy, Debug, Default)]
pub struct GicpFactor;

impl Factor for GicpFactor {
    fn weight(
        &self,
        target_cov: &Matrix3<f64>,
        source_cov: &PackedCovariance,
        r: &Matrix3<f64>,
    ) -> Option<Matrix3<f64>> {
        (target_cov + source_cov.rotated(r)).try_inverse()
    }
}

/// Point-to-plane ICP: `W = n nᵀ` with `n` the target normal.
///
/// The normal comes from the regularised target covariance `C = I − (1 − ε) n nᵀ`, so
/// `n nᵀ = (I − C) / (1 − ε)` needs no eigen-decomposition; shapeless points (identity) weigh zero.
#[derive(Clone, Copy, Debug, Default)]
pub struct PointToPlaneFactor;

impl Factor for PointToPlaneFactor {
    fn weight(&self, target_cov: &Matrix3<f64>, _: &PackedCovariance, _: &Matrix3<f64>) -> Option<Matrix3<f64>> {
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
        NormalEquations::<SquaredDistance>::zero().into()
    }
}

impl From<NormalEquations<SquaredDistance>> for LinearSystem {
    fn from(eq: NormalEquations<SquaredDistance>) -> Self {
        LinearSystem { h: eq.h, b: eq.b, error: eq.cost, sum_sq_distance: eq.sums.0, inliers: eq.count }
    }
}

/// `Σ |e|²` beside the normal equations: the registration's fitness is in m², not in `W` units.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct SquaredDistance(pub(crate) f64);

impl Sums for SquaredDistance {
    fn zero() -> Self {
        SquaredDistance(0.0)
    }

    fn merge(self, other: Self) -> Self {
        SquaredDistance(self.0 + other.0)
    }
}

/// A source point matched to a target Gaussian.
pub(crate) struct Match<'a> {
    /// Index of the target Gaussian.
    target: u32,
    /// The source point `p`.
    point: Vector3<f64>,
    /// `T p`.
    placed: Vector3<f64>,
    /// The source point's covariance.
    covariance: &'a PackedCovariance,
}

/// The residual `e = μ_target − T p` at a fixed pose, weighed by a [`Factor`]: GICP, VGICP (the same
/// factor against voxels) and point-to-plane as one plug-in of [`crate::gauss_newton`].
pub(crate) struct PointToGaussian<'a, T, F> {
    target: &'a T,
    factor: &'a F,
    rotation: Matrix3<f64>,
    translation: Vector3<f64>,
}

impl<'a, T: Target, F: Factor> PointToGaussian<'a, T, F> {
    fn new(target: &'a T, factor: &'a F, pose: &Isometry3<f64>) -> Self {
        let rotation = pose.rotation.to_rotation_matrix().into_inner();
        PointToGaussian { target, factor, rotation, translation: pose.translation.vector }
    }

    fn place(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }

    /// The weight and residual of a correspondence; `None` when the factor drops it.
    #[inline(always)]
    fn weighed(&self, m: &Match<'a>) -> Option<(Matrix3<f64>, Vector3<f64>)> {
        let w = self.factor.weight(&self.target.covariance(m.target), m.covariance, &self.rotation)?;
        Some((w, self.target.mean(m.target) - m.placed))
    }
}

impl<'a, T: Target, F: Factor> gauss_newton::Factor for PointToGaussian<'a, T, F> {
    type Term = Match<'a>;
    type Sums = SquaredDistance;

    #[inline(always)]
    fn add(&self, m: &Match<'a>, eq: &mut NormalEquations<SquaredDistance>) {
        let Some((w, e)) = self.weighed(m) else { return };
        eq.add_point(&m.point, &e, &w, &self.rotation);
        eq.sums.0 += e.norm_squared();
    }
}

/// Marks a source point without correspondence.
pub(crate) const NO_MATCH: u32 = u32::MAX;

/// Finds each source point's correspondence at `pose` (stored in `matches`) and sums the system.
pub(crate) fn linearize<T: Target, F: Factor>(
    source: &GaussianCloud,
    target: &T,
    factor: &F,
    pose: &Isometry3<f64>,
    max_dist_sq: f64,
    matches: &mut [u32],
) -> NormalEquations<SquaredDistance> {
    let gaussians = PointToGaussian::new(target, factor, pose);
    let (points, covariances) = source.parts();
    let blocks = matches.par_chunks_mut(BLOCK).zip(points.par_chunks(BLOCK).zip(covariances.par_chunks(BLOCK)));
    sum_blocks(blocks, |(matches, (points, covariances))| {
        let mut eq = NormalEquations::zero();
        for ((m, point), covariance) in matches.iter_mut().zip(points).zip(covariances) {
            let point = point.coords.cast::<f64>();
            let placed = gaussians.place(&point);
            *m = target.nearest(&placed, max_dist_sq).unwrap_or(NO_MATCH);
            if *m != NO_MATCH {
                gauss_newton::Factor::add(&gaussians, &Match { target: *m, point, placed, covariance }, &mut eq);
            }
        }
        eq
    })
}

/// One block of [`evaluate`]: correspondences, source points and their covariances.
type SourceBlock<'a> = (&'a [u32], (&'a [Point3<f32>], &'a [PackedCovariance]));

/// The cost `Σ eᵀ W e` at `pose` over the correspondences fixed by the last [`linearize`].
pub(crate) fn evaluate<T: Target, F: Factor>(
    source: &GaussianCloud,
    target: &T,
    factor: &F,
    pose: &Isometry3<f64>,
    matches: &[u32],
) -> f64 {
    let gaussians = PointToGaussian::new(target, factor, pose);
    let (points, covariances) = source.parts();
    let blocks = matches.par_chunks(BLOCK).zip(points.par_chunks(BLOCK).zip(covariances.par_chunks(BLOCK)));
    let block_cost = |(matches, (points, covariances)): SourceBlock| {
        let mut cost = 0.0;
        for ((&target, point), covariance) in matches.iter().zip(points).zip(covariances) {
            if target == NO_MATCH {
                continue;
            }
            let point = point.coords.cast::<f64>();
            let m = Match { target, point, placed: gaussians.place(&point), covariance };
            if let Some((w, e)) = gaussians.weighed(&m) {
                cost += e.dot(&(w * e));
            }
        }
        cost
    };
    reduce_in_order(blocks, block_cost, 0.0, |a, b| a + b)
}
