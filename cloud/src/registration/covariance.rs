//! Per-point covariances of local neighbourhoods, regularised to plane-like Gaussians.

use nalgebra::{Matrix3, Point3};
use rayon::prelude::*;

use crate::eigen3::symmetric_eigen3;
use crate::kdtree::KdTree;
use crate::moments::mean_covariance;

/// Smallest eigenvalue given to every covariance: the plane's thickness relative to its extent
/// (Segal et al., "Generalized-ICP", 2009: eigenvalues replaced by (ε, 1, 1)).
pub const PLANE_EPSILON: f64 = 1e-3;

/// Fewer neighbours than this (the point included) give no shape: the covariance is the identity.
pub const MIN_NEIGHBOURS: usize = 5;

/// Regularised covariance of each point's `k` nearest neighbours (the point itself included).
///
/// Builds a k-d tree over `points`; use [`estimate_covariances_with`] when one exists already.
pub fn estimate_covariances(points: &[Point3<f32>], k: usize) -> Vec<Matrix3<f64>> {
    estimate_covariances_with(&KdTree::from_points(points), points, k)
}

/// [`estimate_covariances`] with a tree built over exactly `points`.
pub fn estimate_covariances_with(tree: &KdTree, points: &[Point3<f32>], k: usize) -> Vec<Matrix3<f64>> {
    let xyz: &[[f32; 3]] = bytemuck::cast_slice(points);
    xyz.par_iter().map(|q| covariance_at(tree, points, q, k).0).collect()
}

/// The covariance of the `k` points nearest `q` (through `tree`, built over `points`) and the
/// squared distance to the farthest of them, as the tree gave it (infinite when the tree holds
/// fewer: any point added anywhere would join them).
pub(crate) fn covariance_at(tree: &KdTree, points: &[Point3<f32>], q: &[f32; 3], k: usize) -> (Matrix3<f64>, f32) {
    let neighbours = tree.knn(q, k);
    let radius_sq = match neighbours.last() {
        Some(far) if neighbours.len() == k => far.dist_sq,
        _ => f32::INFINITY,
    };
    (neighbourhood_covariance(neighbours.iter().map(|n| &points[n.index])), radius_sq)
}

/// The plane-regularised covariance of a set of points, or the identity when they are too few.
fn neighbourhood_covariance<'a>(points: impl ExactSizeIterator<Item = &'a Point3<f32>> + Clone) -> Matrix3<f64> {
    let n = points.len();
    if n < MIN_NEIGHBOURS {
        return Matrix3::identity();
    }
    let (_, cov) = mean_covariance(points.map(|p| p.coords.cast::<f64>()));
    regularise(&cov)
}

/// Replaces the eigenvalues of a covariance by (ε, 1, 1), keeping its axes: every neighbourhood
/// becomes a unit disc, so the cost weighs surface orientation and not sampling density.
pub fn regularise(cov: &Matrix3<f64>) -> Matrix3<f64> {
    let e = symmetric_eigen3(cov);
    let v = e.vectors;
    // V diag(ε, 1, 1) Vᵀ = I − (1 − ε) v₀ v₀ᵀ, with v₀ the normal (eigenvalues ascending).
    let normal = v.column(0);
    if !normal.iter().all(|x| x.is_finite()) {
        return Matrix3::identity();
    }
    Matrix3::identity() - (1.0 - PLANE_EPSILON) * normal * normal.transpose()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn plane_gets_its_normal_as_thin_axis() {
        // A grid on the plane z = 0.2 x: the covariance is thin along the plane normal.
        let pts: Vec<Point3<f32>> = (0..400)
            .map(|i| Point3::new((i % 20) as f32 * 0.1, (i / 20) as f32 * 0.1, 0.02 * (i % 20) as f32))
            .collect();
        let covs = estimate_covariances(&pts, 20);
        let n = Vector3::new(-0.2, 0.0, 1.0).normalize();
        for c in &covs {
            assert!((n.dot(&(c * n)) - PLANE_EPSILON).abs() < 1e-6, "{c}");
            let t = Vector3::y();
            assert!((t.dot(&(c * t)) - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn too_few_neighbours_give_identity() {
        let pts = vec![Point3::new(0.0f32, 0.0, 0.0), Point3::new(1.0, 0.0, 0.0)];
        assert_eq!(estimate_covariances(&pts, 20), vec![Matrix3::identity(); 2]);
    }
}
