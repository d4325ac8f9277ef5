//! The accumulator of the 6x6 normal equations.

use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};

use crate::se3::skew;

/// Sums a factor keeps beside the normal equations; `()` when it needs none.
pub trait Sums: Copy + Send {
    /// The empty sum.
    fn zero() -> Self;
    /// The sum of two partial sums.
    fn merge(self, other: Self) -> Self;
}

impl Sums for () {
    fn zero() -> Self {}
    fn merge(self, _: Self) -> Self {}
}

/// `Σ Jᵀ W J`, `Σ Jᵀ W e` and `Σ eᵀ W e` over the terms added, in the right-perturbation tangent
/// `T · exp([ρ; φ])`, with the number of terms and the factor's extra sums `S`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NormalEquations<S = ()> {
    /// `Σ Jᵀ W J`: the information matrix of the pose.
    pub h: Matrix6<f64>,
    /// `Σ Jᵀ W e`: the gradient of half the cost.
    pub b: Vector6<f64>,
    /// `Σ eᵀ W e`.
    pub cost: f64,
    /// Terms added.
    pub count: usize,
    /// The factor's own sums.
    pub sums: S,
}

impl<S: Sums> NormalEquations<S> {
    /// The empty sum.
    pub fn zero() -> Self {
        NormalEquations { h: Matrix6::zeros(), b: Vector6::zeros(), cost: 0.0, count: 0, sums: S::zero() }
    }

    /// The sum of two partial systems.
    pub fn merge(mut self, other: Self) -> Self {
        self.h += other.h;
        self.b += other.b;
        self.cost += other.cost;
        self.count += other.count;
        self.sums = self.sums.merge(other.sums);
        self
    }

    /// A scalar residual `e` with Jacobian row `j` and weight `k`.
    #[inline(always)]
    pub fn add_row(&mut self, j: Vector6<f64>, k: f64, e: f64) {
        self.h += k * j * j.transpose();
        self.b += k * e * j;
        self.cost += k * e * e;
        self.count += 1;
    }

    /// A point residual `e = μ − T p` with weight `W`, for `T` of rotation `R`.
    ///
    /// `d(T exp(δ) p)/dδ = R [I, −[p]×]`, so `J = −R [I, −[p]×]`. In the body frame
    /// (`A = Rᵀ W R`, `g = Rᵀ W e`) the blocks are `H = [A, −A[p]×; [p]×A, −[p]×A[p]×]` and
    /// `b = [−g; g × p]`: fewer products than forming the 3x6 Jacobian.
    #[inline(always)]
    pub fn add_point(&mut self, p: &Vector3<f64>, e: &Vector3<f64>, w: &Matrix3<f64>, r: &Matrix3<f64>) {
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
        self.h += h;
        let mut b = Vector6::zeros();
        b.fixed_rows_mut::<3>(0).copy_from(&-g);
        b.fixed_rows_mut::<3>(3).copy_from(&g.cross(p));
        self.b += b;
        self.cost += e.dot(&we);
        self.count += 1;
    }
}

/// The weights and lever arms of scalar residuals on body-frame points, which put rotations in
/// metres for [`super::solve_remapped`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LeverArm {
    /// `Σ w` (the terms' own weights, before any robust kernel).
    pub weight_sum: f64,
    /// `Σ w p∘p` over the body-frame points: `(Σ w x², Σ w y², Σ w z²)`.
    pub squares: Vector3<f64>,
}

impl LeverArm {
    /// The RMS distance of the points from the body origin (m): one lever arm for every rotation.
    pub fn from_origin(&self) -> f64 {
        (self.squares.sum() / self.weight_sum.max(1e-12)).sqrt()
    }

    /// The RMS distance of the points from each body axis (m): how far a rotation about that axis
    /// moves them per radian.
    pub fn about_axes(&self) -> Vector3<f64> {
        let sum = self.weight_sum.max(1e-12);
        let total = self.squares.sum();
        self.squares.map(|axis| ((total - axis) / sum).max(0.0).sqrt())
    }
}

impl Sums for LeverArm {
    fn zero() -> Self {
        LeverArm::default()
    }

    fn merge(self, o: Self) -> Self {
        LeverArm { weight_sum: self.weight_sum + o.weight_sum, squares: self.squares + o.squares }
    }
}
