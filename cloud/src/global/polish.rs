//! Step 7 — a short point-to-plane polish of the RANSAC transform on the downsampled maps.
//!
//! RANSAC + Umeyama fits keypoints that are voxel centroids picked independently in each map, so a
//! pair can sit half a voxel apart and the fitted transform is good to a decimetre or two. A few
//! Gauss-Newton iterations of point-to-plane ICP (Chen & Medioni 1992) on a few thousand source
//! surfels against the target surfels and their normals bring it to centimetres for a millisecond
//! each, in the workspace's right perturbation `T ← T · exp(δ)` ([`crate::gauss_newton`]). This is not fine registration: it runs on the downsampled maps, with a hard distance gate,
//! and the caller may still chain VGICP on full-resolution maps. It is skipped when
//! `iterations = 0`; the unpolished transform is kept next to the polished one.

use nalgebra::{Isometry3, Point3, Vector6};
use rayon::prelude::*;

use super::error::FeatureError;
use super::normals::Surfels;
use crate::gauss_newton::{
    BLOCK, Factor, NormalEquations, SignedDistance, SignedDistanceFactor, solve_damped, sum_blocks,
};
use crate::kdtree::gate_radius;
use crate::se3;

/// Settings of step 7.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PolishConfig {
    /// Gauss-Newton iterations (default 10; 0 disables the step).
    pub iterations: usize,
    /// Source surfels used, evenly spread over the map (default 4000).
    pub samples: usize,
    /// Pairs farther apart than this are ignored, metres (default 0.8 = 2 × voxel).
    pub max_distance: f32,
}

impl Default for PolishConfig {
    fn default() -> Self {
        Self { iterations: 10, samples: 4000, max_distance: 0.8 }
    }
}

impl PolishConfig {
    /// Checks the distance gate.
    pub fn validate(&self) -> Result<(), FeatureError> {
        if !(self.max_distance > 0.0 && self.max_distance.is_finite()) {
            return Err(FeatureError::InvalidConfig("polish.max_distance must be positive and finite"));
        }
        Ok(())
    }
}

/// Step 7: `transform` (source → target) refined by point-to-plane Gauss-Newton steps.
pub fn polish(source: &Surfels, target: &Surfels, transform: &Isometry3<f64>, config: &PolishConfig) -> Isometry3<f64> {
    let with_normal: Vec<usize> = (0..source.len()).filter(|&i| source.has_normal(i)).collect();
    let stride = (with_normal.len() / config.samples.max(1)).max(1);
    let samples: Vec<Point3<f64>> = with_normal.iter().step_by(stride).map(|&i| source.points[i].cast()).collect();
    let mut current = *transform;
    for _ in 0..config.iterations {
        let Some(delta) = gauss_newton_step(&samples, target, &current, config.max_distance) else { break };
        let step = se3::exp(&delta);
        current *= step;
        // Converged: below a tenth of a millimetre and a thousandth of a degree.
        if step.translation.vector.norm() < 1e-4 && step.rotation.angle() < 2e-5 {
            break;
        }
    }
    current
}

/// One Gauss-Newton step `δ = [ρ; φ]` for `T ← T · exp(δ)` minimising `Σ (n · (T exp(δ) p − q))²`
/// over the source samples `p` and their nearest target surfels `q` (normal `n`).
fn gauss_newton_step(
    samples: &[Point3<f64>],
    target: &Surfels,
    transform: &Isometry3<f64>,
    max_distance: f32,
) -> Option<Vector6<f64>> {
    let gate = max_distance * max_distance;
    // Plain least squares: the distance gate already keeps outliers out.
    let factor = SignedDistanceFactor::new(transform, f64::INFINITY);
    let eq = sum_blocks(samples.par_chunks(BLOCK), |block| {
        let mut eq = NormalEquations::zero();
        for source in block {
            let pf = (transform * source).cast::<f32>();
            let Some(nn) = target.tree.nearest_within(&[pf.x, pf.y, pf.z], gate_radius(max_distance)) else { continue };
            if nn.dist_sq > gate || !target.has_normal(nn.index) {
                continue;
            }
            let term = SignedDistance {
                source: *source,
                anchor: target.points[nn.index].cast(),
                normal: target.normals[nn.index].cast(),
                weight: 1.0,
            };
            factor.add(&term, &mut eq);
        }
        eq
    });
    // Fewer pairs than unknowns, or a degenerate geometry (one plane): leave the transform alone.
    if eq.count < 6 {
        return None;
    }
    // A little damping keeps unobservable directions (sliding along a lone plane) at zero.
    solve_damped(&eq, (1e-9 * eq.h.trace()).max(1e-12))
}
