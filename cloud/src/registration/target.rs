//! What a source point is matched against: Gaussians found by nearest-neighbour search.

use nalgebra::{Isometry3, Matrix3, Point3, Vector3};
use rayon::prelude::*;

use super::covariance::{PLANE_EPSILON, covariance_at, estimate_covariances_with};
use crate::changed::ChangedPoints;
use crate::kdtree::{KdTree, gate_radius};
use crate::memory::{HeapSize, vec_bytes};

/// A set of Gaussians (mean, covariance) with a nearest-neighbour search: a point cloud with a k-d
/// tree (GICP) or a voxel map (VGICP).
pub trait Target: Sync {
    /// The Gaussian whose mean is nearest to `p`, if within `max_dist_sq` (m²).
    fn nearest(&self, p: &Vector3<f64>, max_dist_sq: f64) -> Option<u32>;
    /// Mean of Gaussian `i`.
    fn mean(&self, i: u32) -> Vector3<f64>;
    /// Covariance of Gaussian `i`.
    fn covariance(&self, i: u32) -> Matrix3<f64>;
}

/// A plane-regularised covariance `C = I − (1 − ε) n nᵀ` kept as its normal `n` in single
/// precision (zero for a shapeless point, `C = I`): 12 bytes where the f64 matrix takes 72.
///
/// Every covariance a [`GaussianCloud`] holds has that form ([`super::covariance::regularise`]),
/// and a rotated one keeps it, so the normal is all there is to keep. A map's Gaussians live as
/// long as the map: the station keeps two sets per robot, and in f64 they were half of all it held
/// for a robot. The matrix rebuilt in f64 from the f32 normal is exactly of the regularised form
/// (rounding turns the plane by 1e-7 rad), where rounding the matrix's entries would move its ε
/// eigenvalue, which the GICP weight inverts.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PackedCovariance([f32; 3]);

impl PackedCovariance {
    /// The normal of `c`, a plane-regularised covariance or the identity (anything else is
    /// outside what a [`GaussianCloud`] holds).
    pub fn pack(c: &Matrix3<f64>) -> Self {
        // n nᵀ = (I − C) / (1 − ε); its largest diagonal entry picks a column that is n scaled.
        let outer = (Matrix3::identity() - c) / (1.0 - PLANE_EPSILON);
        let (j, largest) = (0..3).map(|j| (j, outer[(j, j)])).fold((0, f64::MIN), |m, x| if x.1 > m.1 { x } else { m });
        if largest < 0.25 {
            return Self::default();
        }
        let n = outer.column(j) / largest.sqrt();
        debug_assert!((Self::plane(&n) - c).norm() < 1e-9, "not a plane-regularised covariance: {c}");
        Self([n.x as f32, n.y as f32, n.z as f32])
    }

    /// The covariance in f64.
    #[inline]
    pub fn unpack(&self) -> Matrix3<f64> {
        Self::plane(&self.normal())
    }

    /// `R C Rᵀ`: the plane turned, formed from the turned normal (a sixth of the products).
    #[inline]
    pub fn rotated(&self, r: &Matrix3<f64>) -> Matrix3<f64> {
        Self::plane(&(r * self.normal()))
    }

    /// The same plane turned by `r`, packed.
    pub fn turned(&self, r: &Matrix3<f64>) -> Self {
        let n = r * self.normal();
        Self([n.x as f32, n.y as f32, n.z as f32])
    }

    /// The plane's unit normal; `None` for a shapeless point (`C = I`).
    pub fn unit_normal(&self) -> Option<Vector3<f64>> {
        let n = self.normal();
        (n != Vector3::zeros()).then(|| n.normalize())
    }

    fn normal(&self) -> Vector3<f64> {
        Vector3::new(f64::from(self.0[0]), f64::from(self.0[1]), f64::from(self.0[2]))
    }

    /// `I − (1 − ε) n nᵀ / |n|²`: the projector onto `n` keeps the form exact for an f32 normal of
    /// not quite unit length; the identity for `n = 0`.
    #[inline]
    fn plane(n: &Vector3<f64>) -> Matrix3<f64> {
        let squared = n.norm_squared();
        if squared == 0.0 {
            return Matrix3::identity();
        }
        Matrix3::identity() - ((1.0 - PLANE_EPSILON) / squared) * n * n.transpose()
    }
}

/// Points with their regularised neighbourhood covariances and a k-d tree: a GICP source or target.
///
/// Stored in single precision (points as the scans give them, covariances packed): 24 bytes a
/// point instead of 96; every product of the cost is formed in f64 from them.
pub struct GaussianCloud {
    points: Vec<Point3<f32>>,
    covariances: Vec<PackedCovariance>,
    tree: KdTree,
    /// How each covariance was estimated, when it may be estimated again for a grown cloud
    /// ([`GaussianCloud::growable`]).
    radii: Option<NeighbourhoodRadii>,
}

/// Each point's neighbourhood radius (the squared distance to the farthest of the `neighbours`
/// nearest points its covariance was estimated from, as the tree gave it; infinite when the cloud
/// had fewer): a change farther than that from a point leaves its covariance as it was.
struct NeighbourhoodRadii {
    neighbours: usize,
    radii_sq: Vec<f32>,
}

/// A [`GaussianCloud`] estimated again for a cloud that changed: [`GaussianCloud::regrown`].
pub struct Regrown {
    /// The cloud, as [`GaussianCloud::growable`] would give it.
    pub cloud: GaussianCloud,
    /// Covariances taken over unchanged from the earlier cloud.
    pub reused: usize,
}

impl GaussianCloud {
    /// Estimates each point's covariance from its `neighbours` nearest points and keeps the tree.
    pub fn new(points: &[Point3<f32>], neighbours: usize) -> Self {
        let tree = KdTree::from_points(points);
        let covariances =
            estimate_covariances_with(&tree, points, neighbours).iter().map(PackedCovariance::pack).collect();
        GaussianCloud { points: points.to_vec(), covariances, tree, radii: None }
    }

    /// [`GaussianCloud::new`] that also keeps each point's neighbourhood radius (4 bytes a point),
    /// so that once the cloud has grown [`GaussianCloud::regrown`] re-estimates only the
    /// covariances a change can reach.
    pub fn growable(points: &[Point3<f32>], neighbours: usize) -> Self {
        Self::regrown(None, points, neighbours).cloud
    }

    /// The growable cloud of `points`, the same covariances as [`GaussianCloud::new`] gives, taking
    /// over from `previous` (growable, of the same `neighbours`) every covariance whose
    /// neighbourhood holds no added, moved or removed point: a robot's map grown by a keyframe
    /// costs the keyframe's surroundings, not the whole map.
    pub fn regrown(previous: Option<&GaussianCloud>, points: &[Point3<f32>], neighbours: usize) -> Regrown {
        let tree = KdTree::from_points(points);
        let earlier = previous.and_then(|p| {
            let radii = p.radii.as_ref().filter(|r| r.neighbours == neighbours)?;
            Some((p, radii, ChangedPoints::between(&p.points, points)))
        });
        let estimated: Vec<(PackedCovariance, f32, bool)> = points
            .par_iter()
            .enumerate()
            .map(|(i, p)| {
                let kept = earlier.as_ref().and_then(|(cloud, radii, changed)| {
                    let radius_sq = radii.radii_sq[changed.twin(i)?];
                    let twin = changed.unchanged_within(i, p, radius_sq)?;
                    Some((cloud.covariances[twin], radius_sq, true))
                });
                kept.unwrap_or_else(|| {
                    let (covariance, radius_sq) = covariance_at(&tree, points, &[p.x, p.y, p.z], neighbours);
                    (PackedCovariance::pack(&covariance), radius_sq, false)
                })
            })
            .collect();
        let reused = estimated.iter().filter(|e| e.2).count();
        let (covariances, radii_sq) = estimated.into_iter().map(|(c, r, _)| (c, r)).unzip();
        let radii = Some(NeighbourhoodRadii { neighbours, radii_sq });
        Regrown { cloud: GaussianCloud { points: points.to_vec(), covariances, tree, radii }, reused }
    }

    /// Points with covariances estimated elsewhere (e.g. each in its own cloud's frame and moved
    /// here, [`GaussianCloud::transformed`]); builds the tree. `covariances` is truncated or padded
    /// with identities to the points' length.
    pub fn from_parts(points: Vec<Vector3<f64>>, mut covariances: Vec<PackedCovariance>) -> Self {
        covariances.resize(points.len(), PackedCovariance::default());
        let points: Vec<Point3<f32>> = points.iter().map(|p| Point3::from(p.cast::<f32>())).collect();
        GaussianCloud { tree: KdTree::from_points(&points), points, covariances, radii: None }
    }

    /// The points and covariances moved by `pose` (`p ↦ T p`, `C ↦ R C Rᵀ`), without a tree: parts
    /// for [`GaussianCloud::from_parts`].
    pub fn transformed(&self, pose: &Isometry3<f64>) -> (Vec<Vector3<f64>>, Vec<PackedCovariance>) {
        let r = pose.rotation.to_rotation_matrix().into_inner();
        let points = (0..self.len()).map(|i| pose.rotation * self.point(i) + pose.translation.vector).collect();
        let covariances = self.covariances.iter().map(|c| c.turned(&r)).collect();
        (points, covariances)
    }

    /// The points in single precision.
    pub fn points_f32(&self) -> Vec<Point3<f32>> {
        self.points.clone()
    }

    /// Point `i` in f64.
    pub fn point(&self, i: usize) -> Vector3<f64> {
        self.points[i].coords.cast()
    }

    /// The unit normal of the plane point `i` lies on; `None` for a shapeless point.
    pub fn plane_normal(&self, i: usize) -> Option<Vector3<f64>> {
        self.covariances[i].unit_normal()
    }

    /// Covariance of point `i` in f64.
    pub fn covariance_of(&self, i: usize) -> Matrix3<f64> {
        self.covariances[i].unpack()
    }

    /// The points (single precision) and their packed covariances, in step: a registration
    /// source's blocks.
    pub(crate) fn parts(&self) -> (&[Point3<f32>], &[PackedCovariance]) {
        (&self.points, &self.covariances)
    }

    /// Every `step`-th point with its covariance, as a registration source only: no tree is built,
    /// so it finds nothing when used as a target.
    pub(crate) fn strided_source(&self, step: usize) -> Self {
        let step = step.max(1);
        GaussianCloud {
            points: self.points.iter().step_by(step).copied().collect(),
            covariances: self.covariances.iter().step_by(step).copied().collect(),
            tree: KdTree::new(&[]),
            radii: None,
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
        vec_bytes(&self.points)
            + vec_bytes(&self.covariances)
            + self.tree.heap_bytes()
            + self.radii.as_ref().map_or(0, |r| vec_bytes(&r.radii_sq))
    }
}

impl Target for GaussianCloud {
    fn nearest(&self, p: &Vector3<f64>, max_dist_sq: f64) -> Option<u32> {
        let reach = gate_radius(max_dist_sq.sqrt() as f32);
        let n = self.tree.nearest_within(&[p.x as f32, p.y as f32, p.z as f32], reach)?;
        (f64::from(n.dist_sq) <= max_dist_sq).then_some(n.index as u32)
    }

    fn mean(&self, i: u32) -> Vector3<f64> {
        self.point(i as usize)
    }

    fn covariance(&self, i: u32) -> Matrix3<f64> {
        self.covariance_of(i as usize)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::registration::covariance::regularise;

    #[test]
    fn a_packed_covariance_keeps_what_a_registration_uses_of_it() {
        // A plane patch tilted off every axis: the regularised shape the cost weighs.
        let axis = Vector3::new(0.3, -0.5, 0.81).normalize();
        let raw = Matrix3::identity() - axis * axis.transpose() * 0.999 + Matrix3::from_diagonal_element(1e-6);
        let c = regularise(&raw);
        let back = PackedCovariance::pack(&c).unpack();
        assert!((back - c).norm() < 1e-6, "{back} vs {c}");
        // The GICP weight (C + C)⁻¹ inverts the ε eigenvalue: it must move as little.
        let (inverse, inverse_back) = ((c + c).try_inverse().unwrap(), (back + back).try_inverse().unwrap());
        assert!((inverse_back - inverse).norm() < 1e-5 * inverse.norm(), "{inverse_back} vs {inverse}");
        // Shapeless points stay shapeless, and so does the plane turned by a rotation.
        assert_eq!(PackedCovariance::pack(&Matrix3::identity()).unpack(), Matrix3::identity());
        let r = nalgebra::Rotation3::from_euler_angles(0.4, -1.1, 2.0).into_inner();
        let turned = r * c * r.transpose();
        assert!((PackedCovariance::pack(&turned).unpack() - turned).norm() < 1e-6);
        assert!((PackedCovariance::pack(&c).rotated(&r) - turned).norm() < 1e-6);
        assert!((PackedCovariance::pack(&c).turned(&r).unpack() - turned).norm() < 1e-6);
        // The plane's normal is the covariance's least eigenvector, up to sign; none without a plane.
        let n = PackedCovariance::pack(&c).unit_normal().unwrap();
        assert!((n.dot(&axis).abs() - 1.0).abs() < 1e-6, "{n} vs {axis}");
        assert_eq!(PackedCovariance::pack(&Matrix3::identity()).unit_normal(), None);
    }

    #[test]
    fn a_regrown_cloud_has_the_covariances_of_one_estimated_anew() {
        for reversed in [false, true] {
            let (older, mut newer) = testkit::yard_seen_then_whole(21, 80.0, 4.0);
            if reversed {
                newer.reverse();
            }
            let earlier = GaussianCloud::growable(&older, 20);
            let grown = GaussianCloud::regrown(Some(&earlier), &newer, 20);
            let anew = GaussianCloud::new(&newer, 20);
            assert_eq!(grown.cloud.len(), newer.len());
            for i in 0..newer.len() {
                assert_eq!(grown.cloud.covariances[i], anew.covariances[i], "point {i} of {}", newer.len());
            }
            // Most of the first part is far from every change; the new part is all estimated.
            let first_part = newer.iter().filter(|p| p.x < 40.0).count();
            assert!(grown.reused > first_part / 2 && grown.reused < first_part, "{} of {first_part}", grown.reused);
            // Other neighbourhoods: nothing can be taken over.
            let other = GaussianCloud::regrown(Some(&earlier), &newer, 10);
            assert_eq!(other.reused, 0);
            assert!(other.cloud.covariances == GaussianCloud::new(&newer, 10).covariances);
        }
    }
}
