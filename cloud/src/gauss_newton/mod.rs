//! Gauss-Newton on one SE(3) pose: the normal equations, how they are summed, and how they are solved.
//!
//! Every solver here minimises `Σ eᵢᵀ Wᵢ eᵢ` over a pose `T` by linearising each residual in the
//! right perturbation `T ← T · exp(δ)`, `δ = [ρ; φ]` translation first ([`crate::se3::update`]):
//! `eᵢ(T exp(δ)) ≈ eᵢ + Jᵢ δ`, so that the step solves the 6x6 normal equations
//!
//! ```text
//! H δ = −b,   H = Σ Jᵢᵀ Wᵢ Jᵢ,   b = Σ Jᵢᵀ Wᵢ eᵢ.
//! ```
//!
//! The perturbation is taken in the body frame so that `H` does not depend on how far the pose is
//! from the origin (in world coordinates a rotation's eigenvalues grow with the lever arm to it).
//!
//! A [`Factor`] adds one residual's rows to [`NormalEquations`]; the factors are plug-ins, the sum
//! is one policy ([`sum_blocks`]): fixed blocks of [`BLOCK`] terms are summed by one rayon task
//! each, then the block sums are added in index order. The result does not depend on the number
//! of threads, bit for bit: a sum in another order differs in the last bits, and over a few hundred
//! scans an odometry grows such bits into millimetres.
//!
//! Two solvers close the step: [`solve_damped`] (`(H + λI) δ = −b`, Levenberg-Marquardt's damping)
//! and [`solve_remapped`] (degenerate directions kept at zero, Zhang, Kaess & Singh 2016).

mod factors;
mod normal_equations;
mod solve;
#[cfg(test)]
mod tests;

pub use factors::{SignedDistance, SignedDistanceFactor};
pub use normal_equations::{LeverArm, NormalEquations, Sums};
pub use solve::{Remapped, RotationScale, solve_damped, solve_remapped};

use rayon::prelude::*;

/// One kind of residual at a fixed linearisation point: how a term adds its Jacobian rows.
pub trait Factor: Sync {
    /// What one residual is made of (a correspondence).
    type Term;
    /// The extra sums beyond `H`, `b`, the cost and the count that this factor's solver needs.
    type Sums: Sums;

    /// Adds `Jᵀ W J`, `Jᵀ W e` and `eᵀ W e` of `term`, or nothing when the term is unusable.
    fn add(&self, term: &Self::Term, eq: &mut NormalEquations<Self::Sums>);
}

/// Terms per block: large enough to amortise a rayon task, small enough to balance two cores.
pub const BLOCK: usize = 256;

/// The normal equations of all `terms` (see [`sum_blocks`] for the order).
pub fn sum_terms<F>(factor: &F, terms: &[F::Term]) -> NormalEquations<F::Sums>
where
    F: Factor,
    F::Term: Sync,
{
    sum_blocks(terms.par_chunks(BLOCK), |block| sum_block(factor, block))
}

/// The normal equations of one block of terms, added in order.
pub fn sum_block<F: Factor>(factor: &F, terms: &[F::Term]) -> NormalEquations<F::Sums> {
    let mut eq = NormalEquations::zero();
    for term in terms {
        factor.add(term, &mut eq);
    }
    eq
}

/// Sums blocks of terms, one rayon task per block, and then the block sums in index order.
///
/// The blocks are the caller's (e.g. `par_chunks(BLOCK)` of several slices chained, or zipped with
/// an output), so that a block can also search correspondences or record them.
pub fn sum_blocks<I, S>(
    blocks: I,
    sum_block: impl Fn(I::Item) -> NormalEquations<S> + Sync + Send,
) -> NormalEquations<S>
where
    I: IndexedParallelIterator,
    S: Sums,
{
    reduce_in_order(blocks, sum_block, NormalEquations::zero(), NormalEquations::merge)
}

/// The same policy for any partial result, e.g. a cost evaluated without linearising.
pub fn reduce_in_order<I, A>(
    blocks: I,
    sum_block: impl Fn(I::Item) -> A + Sync + Send,
    zero: A,
    merge: impl Fn(A, A) -> A,
) -> A
where
    I: IndexedParallelIterator,
    A: Send,
{
    let partial: Vec<A> = blocks.map(sum_block).collect();
    partial.into_iter().fold(zero, merge)
}
