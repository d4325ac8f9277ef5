//! Step 7 — a short point-to-plane polish of the RANSAC transform on the downsampled maps.
//!
//! RANSAC + Umeyama fits keypoints that are voxel centroids picked independently in each map, so a
//! pair can sit half a voxel apart and the fitted transform is good to a decimetre or two. A few
//! Gauss-Newton iterations of point-to-plane ICP (Chen & Medioni 1992) on a few thousand source
//! surfels against the target surfels and their normals bring it to centimetres for a millisecond
//! each. This is not fine registration: it runs on the downsampled maps, with a hard distance gate,
//! and the caller may still chain VGICP on full-resolution maps. It is skipped when
//! `iterations = 0`; the unpolished transform is kept next to the polished one.

use nalgebra::{Isometry3, Matrix6, Point3, Translation3, UnitQuaternion, Vector3, Vector6};
use rayon::prelude::*;

use super::FeatureError;
use super::normals::Surfels;

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
        let Some(step) = gauss_newton_step(&samples, target, &current, config.max_distance) else { break };
        current = step * current;
        // Converged: below a tenth of a millimetre and a thousandth of a degree.
        if step.translation.vector.norm() < 1e-4 && step.rotation.angle() < 2e-5 {
            break;
        }
    }
    current
}

/// One linearised least-squares step `δ = [t; ω]` minimising `Σ ((p + ω × p + t − q) · n)²`.
fn gauss_newton_step(
    samples: &[Point3<f64>],
    target: &Surfels,
    transform: &Isometry3<f64>,
    max_distance: f32,
) -> Option<Isometry3<f64>> {
    let gate = max_distance * max_distance;
    let (h, b, count) = samples
        .par_iter()
        .filter_map(|s| {
            let p = transform * s;
            let pf = p.cast::<f32>();
            let nn = target.tree.nearest(&[pf.x, pf.y, pf.z])?;
            if nn.dist_sq > gate || !target.has_normal(nn.index) {
                return None;
            }
            let n: Vector3<f64> = target.normals[nn.index].cast();
            let r = (p - target.points[nn.index].cast::<f64>()).dot(&n);
            let j = Vector6::new(n.x, n.y, n.z, 0.0, 0.0, 0.0) + {
                let c = p.coords.cross(&n);
                Vector6::new(0.0, 0.0, 0.0, c.x, c.y, c.z)
            };
            Some((j * j.transpose(), j * r, 1usize))
        })
        .reduce(|| (Matrix6::zeros(), Vector6::zeros(), 0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
    // Fewer pairs than unknowns, or a degenerate geometry (one plane): leave the transform alone.
    if count < 6 {
        return None;
    }
    // A little damping keeps unobservable directions (sliding along a lone plane) at zero.
    let damped = h + Matrix6::identity() * (1e-9 * h.trace()).max(1e-12);
    let delta = -damped.cholesky()?.solve(&b);
    delta.iter().all(|v| v.is_finite()).then(|| {
        let rotation = UnitQuaternion::from_scaled_axis(Vector3::new(delta[3], delta[4], delta[5]));
        Isometry3::from_parts(Translation3::new(delta[0], delta[1], delta[2]), rotation)
    })
}
