//! Scalar distance factors: a body-frame point against a line or a plane of the map.

use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3, Vector6};

use super::Factor;
use super::normal_equations::{LeverArm, NormalEquations};

/// A residual `e = n · (T p − q)`: the signed distance of the placed point `p` from a line (through
/// `q`, `n` ⟂ the line toward the point) or a plane (through `q`, normal `n`).
#[derive(Clone, Copy, Debug)]
pub struct SignedDistance {
    /// The point in the body frame.
    pub source: Point3<f64>,
    /// A point of the line or plane.
    pub anchor: Point3<f64>,
    /// Unit direction of the distance.
    pub normal: Vector3<f64>,
    /// The term's weight `w`.
    pub weight: f64,
}

impl SignedDistance {
    /// The residual `e` with the point placed by `pose`.
    #[inline(always)]
    pub fn at(&self, pose: &Isometry3<f64>) -> f64 {
        self.normal.dot(&(pose * self.source - self.anchor))
    }
}

/// [`SignedDistance`] terms at `pose` under a Huber kernel: weight `w · min(1, δ_H / |e|)`.
#[derive(Clone, Copy, Debug)]
pub struct SignedDistanceFactor {
    pose: Isometry3<f64>,
    inverse_rotation: UnitQuaternion<f64>,
    huber: f64,
}

impl SignedDistanceFactor {
    /// Linearises at `pose`; `huber = ∞` gives plain least squares.
    pub fn new(pose: &Isometry3<f64>, huber: f64) -> Self {
        SignedDistanceFactor { pose: *pose, inverse_rotation: pose.rotation.inverse(), huber }
    }
}

impl Factor for SignedDistanceFactor {
    type Term = SignedDistance;
    type Sums = LeverArm;

    /// `∂(T exp(δ) p)/∂δ = R [I, −[p]×]`, so with `m = Rᵀ n` the row is `J = [mᵀ, (p × m)ᵀ]`.
    #[inline(always)]
    fn add(&self, r: &SignedDistance, eq: &mut NormalEquations<LeverArm>) {
        let e = r.at(&self.pose);
        let robust = if e.abs() <= self.huber { 1.0 } else { self.huber / e.abs() };
        let m = self.inverse_rotation * r.normal;
        let rot = r.source.coords.cross(&m);
        eq.add_row(Vector6::new(m.x, m.y, m.z, rot.x, rot.y, rot.z), r.weight * robust, e);
        eq.sums.weight_sum += r.weight;
        eq.sums.squares += r.weight * r.source.coords.component_mul(&r.source.coords);
    }
}
