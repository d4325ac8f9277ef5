//! What a source point is matched against: Gaussians found by nearest-neighbour search.

use nalgebra::{Isometry3, Matrix3, Point3, Vector3};

use super::covariance::estimate_covariances_with;
use crate::kdtree::{KdTree, gate_radius};
use crate::memory::{HeapSize, vec_bytes};

/// A set of Gaussians (mean, covariance) with a nearest-neighbour search: a point cloud with a k-d
/// tree (GICP) or a voxel map (VGICP).
pub trait Target: Sync {
    /// The Gaussian whose mean is nearest to `p`, if within `max_dist_sq` (m²).
    fn nearest(&self, p: &Vector3<f64>, max_dist_sq: f64) -> Option<u32>;
    /// Mean of Gaussian `i`.
    fn mean(&self, i: u32) -> &Vector3<f64>;
    /// Covariance of Gaussian `i`.
    fn covariance(&self, i: u32) -> &Matrix3<f64>;
}

/// Points with their regularised neighbourhood covariances and a k-d tree: a GICP source or target.
pub struct GaussianCloud {
    /// Positions in f64, the precision the cost is computed in.
    pub points: Vec<Vector3<f64>>,
    /// Regularised covariance of each point (see [`super::covariance::regularise`]).
    pub covariances: Vec<Matrix3<f64>>,
    tree: KdTree,
}

impl GaussianCloud {
    /// Estimates each point's covariance from its `neighbours` nearest points and keeps the tree.
    pub fn new(points: &[Point3<f32>], neighbours: usize) -> Self {
        let tree = KdTree::from_points(points);
        let covariances = estimate_covariances_with(&tree, points, neighbours);
        let points = points.iter().map(|p| p.coords.cast::<f64>()).collect();
        GaussianCloud { points, covariances, tree }
    }

    /// Points with covariances estimated elsewhere (e.g. each in its own cloud's frame and moved
    /// here, [`GaussianCloud::transformed`]); builds the tree. `covariances` is truncated or padded
    /// with identities to the points' length.
    pub fn from_parts(points: Vec<Vector3<f64>>, mut covariances: Vec<Matrix3<f64>>) -> Self {
        covariances.resize(points.len(), Matrix3::identity());
        let xyz: Vec<[f32; 3]> = points.iter().map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect();
        GaussianCloud { tree: KdTree::new(&xyz), points, covariances }
    }

    /// The points and covariances moved by `pose` (`p ↦ T p`, `C ↦ R C Rᵀ`), without a tree: parts
    /// for [`GaussianCloud::from_parts`].
    pub fn transformed(&self, pose: &Isometry3<f64>) -> (Vec<Vector3<f64>>, Vec<Matrix3<f64>>) {
        let r = pose.rotation.to_rotation_matrix().into_inner();
        let points = self.points.iter().map(|p| pose.rotation * p + pose.translation.vector).collect();
        let covariances = self.covariances.iter().map(|c| r * c * r.transpose()).collect();
        (points, covariances)
    }

    /// The points in single precision.
    pub fn points_f32(&self) -> Vec<Point3<f32>> {
        self.points.iter().map(|p| Point3::from(p.cast::<f32>())).collect()
    }

    /// Every `step`-th point with its covariance, as a registration source only: no tree is built,
    /// so it finds nothing when used as a target.
    pub(crate) fn strided_source(&self, step: usize) -> Self {
        let step = step.max(1);
        GaussianCloud {
            points: self.points.iter().step_by(step).copied().collect(),
            covariances: self.covariances.iter().step_by(step).copied().collect(),
            tree: KdTree::new(&[]),
        }
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// The k-d tree over the points (empty for a strided source).
    pub fn tree(&self) -> &KdTree {
        &self.tree
    }

    /// True when the cloud holds no point.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }
}

impl HeapSize for GaussianCloud {
    fn heap_bytes(&self) -> usize {
        vec_bytes(&self.points) + vec_bytes(&self.covariances) + self.tree.heap_bytes()
    }
}

impl Target for GaussianCloud {
    fn nearest(&self, p: &Vector3<f64>, max_dist_sq: f64) -> Option<u32> {
        let reach = gate_radius(max_dist_sq.sqrt() as f32);
        let n = self.tree.nearest_within(&[p.x as f32, p.y as f32, p.z as f32], reach)?;
        (f64::from(n.dist_sq) <= max_dist_sq).then_some(n.index as u32)
    }

    fn mean(&self, i: u32) -> &Vector3<f64> {
        &self.points[i as usize]
    }

    fn covariance(&self, i: u32) -> &Matrix3<f64> {
        &self.covariances[i as usize]
    }
}
