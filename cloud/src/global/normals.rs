//! Step 2 — surface normals by least-squares plane fitting, consistently oriented.
//!
//! The normal of a point is the eigenvector of the smallest eigenvalue of its neighbourhood's
//! covariance (the total-least-squares plane, as PCL's NormalEstimation and Open3D's
//! `estimate_normals` with a hybrid radius / max-neighbours search). Points whose neighbourhood is
//! too small or collinear get no normal (a zero vector) and are ignored by the later steps.
//!
//! A plane fit fixes the normal only up to sign, and FPFH is not sign-invariant: the two maps must
//! orient the same surface the same way. Robot maps carry no sensor position per point, so the
//! default orientation ([`Orientation::LocalMass`]) is a function of local geometry only, and hence
//! identical in both maps whatever their frames: a normal points towards the side of its surface
//! that holds more of the surrounding points. The ground then points up (the scene stands on it),
//! facades point out to the street (the ground in front of them), which is also where a ground
//! robot's sensor saw them from. Where the surroundings are balanced (an isolated flat patch) the
//! normal points up (+z), the gravity prior of ground-robot maps. Scans still in their sensor frame
//! can use [`Orientation::Viewpoint`] at the origin; [`Orientation::AboveCentroid`] is the simple
//! "viewpoint above the map" rule.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use super::error::FeatureError;
use crate::PointCloud;
use crate::eigen3::symmetric_eigen3;
use crate::kdtree::KdTree;
use crate::memory::{HeapSize, vec_bytes};
use crate::moments::mean_covariance;

/// How the sign of each normal is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Orientation {
    /// Towards the side holding more points within `radius` metres; +z when balanced.
    LocalMass {
        /// Radius of the neighbourhood weighed, metres (default: the FPFH radius).
        radius: f32,
    },
    /// Towards a fixed point (the sensor origin for a scan in its own frame).
    Viewpoint(Point3<f32>),
    /// Towards a point `height` metres above the cloud's centroid.
    AboveCentroid {
        /// Height of the viewpoint above the centroid, metres.
        height: f32,
    },
}

/// Settings of step 2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NormalConfig {
    /// Neighbourhood radius of the plane fit, metres (default 2 × voxel = 0.8, as Open3D's tutorial).
    pub radius: f32,
    /// At most this many nearest neighbours within the radius are used (default 30).
    pub max_neighbours: usize,
    /// Points with fewer neighbours (self included) get no normal and are dropped (default 5).
    pub min_neighbours: usize,
    /// Sign rule (default: local mass within 2.0 m, the FPFH radius).
    pub orientation: Orientation,
}

impl Default for NormalConfig {
    fn default() -> Self {
        Self { radius: 0.8, max_neighbours: 30, min_neighbours: 5, orientation: Orientation::LocalMass { radius: 2.0 } }
    }
}

impl NormalConfig {
    /// Checks radii and counts.
    pub fn validate(&self) -> Result<(), FeatureError> {
        let radius_ok = |r: f32| r > 0.0 && r.is_finite();
        let orientation_ok = match self.orientation {
            Orientation::LocalMass { radius } => radius_ok(radius),
            Orientation::Viewpoint(p) => p.coords.iter().all(|c| c.is_finite()),
            Orientation::AboveCentroid { height } => height.is_finite(),
        };
        if !radius_ok(self.radius) || self.max_neighbours < 3 || !orientation_ok {
            return Err(FeatureError::InvalidConfig(
                "normals need a positive radius, max_neighbours >= 3 and a finite orientation",
            ));
        }
        Ok(())
    }
}

/// One entry of a shared neighbour list: half the size of a [`crate::kdtree::Neighbour`], because a map's lists
/// hold tens of millions of entries (80 per point at the indoor reach).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Near {
    index: u32,
    /// Squared distance to the point whose list holds this entry, m².
    pub dist_sq: f32,
}

impl Near {
    /// Index of the neighbour in the surfels.
    pub fn index(&self) -> usize {
        self.index as usize
    }
}

/// Every point's neighbours within a fixed reach, nearest first, computed once and shared by the
/// later steps (the k-d tree's radius search dominates their cost otherwise).
///
/// The lists are stored per block of `BLOCK` consecutive points, each block built by one task
/// into one buffer: no allocation per point and no final copy of the whole set.
pub struct Neighbourhoods {
    reach: f32,
    blocks: Vec<NeighbourBlock>,
}

/// Points per block of lists.
const BLOCK: usize = 1024;

/// The lists of [`BLOCK`] consecutive points.
struct NeighbourBlock {
    /// `BLOCK + 1` (fewer in the last block) bounds into `entries`.
    offsets: Vec<u32>,
    entries: Vec<Near>,
}

impl Neighbourhoods {
    /// Radius searches of `reach` around every point, in parallel.
    pub fn build(points: &[Point3<f32>], tree: &KdTree, reach: f32) -> Self {
        let blocks = points
            .par_chunks(BLOCK)
            .map(|chunk| {
                let mut offsets = Vec::with_capacity(chunk.len() + 1);
                let mut entries = Vec::new();
                offsets.push(0);
                for p in chunk {
                    let start = entries.len();
                    tree.for_each_within(&[p.x, p.y, p.z], reach, |index, dist_sq| {
                        entries.push(Near { index: index as u32, dist_sq });
                    });
                    // Ties (common on gridded maps) go to the lower index, so lists do not depend on the tree.
                    entries[start..]
                        .sort_unstable_by(|a, b| a.dist_sq.total_cmp(&b.dist_sq).then(a.index.cmp(&b.index)));
                    offsets.push(entries.len() as u32);
                }
                NeighbourBlock { offsets, entries }
            })
            .collect();
        Self { reach, blocks }
    }

    /// The neighbours of point `i` within `radius` (at most the reach), itself included, nearest
    /// first, at most `max` of them; none once [`Neighbourhoods::release`]d.
    pub fn of(&self, i: usize, radius: f32, max: usize) -> &[Near] {
        let Some(block) = self.blocks.get(i / BLOCK) else { return &[] };
        let k = i % BLOCK;
        let all = &block.entries[block.offsets[k] as usize..block.offsets[k + 1] as usize];
        let within = all.partition_point(|n| n.dist_sq <= radius * radius);
        &all[..within.min(max)]
    }

    /// The radius the lists were built with, metres.
    pub fn reach(&self) -> f32 {
        self.reach
    }

    /// Frees the lists: 8 bytes per neighbour, a hundred neighbours a point within a 2 m reach at
    /// 0.4 m spacing, so tens of megabytes for a robot's map, needed only while its features are
    /// computed. Afterwards no point has neighbours.
    pub fn release(&mut self) {
        self.blocks = Vec::new();
    }

    /// True until [`Neighbourhoods::release`]d.
    pub fn is_held(&self) -> bool {
        !self.blocks.is_empty()
    }
}

impl HeapSize for Neighbourhoods {
    fn heap_bytes(&self) -> usize {
        self.blocks.iter().map(|b| vec_bytes(&b.offsets) + vec_bytes(&b.entries)).sum::<usize>()
            + vec_bytes(&self.blocks)
    }
}

impl HeapSize for Surfels {
    fn heap_bytes(&self) -> usize {
        vec_bytes(&self.points) + vec_bytes(&self.normals) + self.tree.heap_bytes() + self.neighbourhoods.heap_bytes()
    }
}

/// Points with unit normals (zero where no plane fits), their k-d tree and neighbourhoods.
///
/// Points without a normal stay in the set so that indices and neighbourhoods are computed once;
/// the later steps skip them (a zero normal adds nothing to the Harris tensor, and FPFH pair
/// features are undefined for it).
pub struct Surfels {
    /// Positions, metres.
    pub points: Vec<Point3<f32>>,
    /// Unit normals oriented by the configured rule, or zero where no reliable plane fits.
    pub normals: Vec<Vector3<f32>>,
    /// Nearest-neighbour index over `points`.
    pub tree: KdTree,
    /// Neighbours of every point within the reach given at construction.
    pub neighbourhoods: Neighbourhoods,
}

impl Surfels {
    /// Surfels from points and normals, with neighbourhoods up to `reach` metres.
    pub fn new(points: Vec<Point3<f32>>, normals: Vec<Vector3<f32>>, reach: f32) -> Self {
        let tree = KdTree::from_points(&points);
        let neighbourhoods = Neighbourhoods::build(&points, &tree, reach);
        Self { points, normals, tree, neighbourhoods }
    }

    /// Points within `radius` (capped at the reach) of point `i`, itself included, nearest first,
    /// at most `max` of them.
    pub fn neighbours(&self, i: usize, radius: f32, max: usize) -> &[Near] {
        self.neighbourhoods.of(i, radius, max)
    }

    /// True when point `i` has a normal.
    pub fn has_normal(&self, i: usize) -> bool {
        self.normals[i] != Vector3::zeros()
    }

    /// Number of points with a normal.
    pub fn with_normals(&self) -> usize {
        (0..self.len()).filter(|&i| self.has_normal(i)).count()
    }

    /// Number of surfels.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True when there is none.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }
}

/// Step 2: fits a plane around every point and orients the normals; `reach` (at least the normal
/// radius) is the largest neighbourhood radius the later steps will ask for.
pub fn estimate_normals(cloud: &PointCloud, config: &NormalConfig, reach: f32) -> Result<Surfels, FeatureError> {
    config.validate()?;
    let reach = reach.max(config.radius);
    let mut surfels = Surfels::new(cloud.points.clone(), vec![Vector3::zeros(); cloud.len()], reach);
    let normals: Vec<Vector3<f32>> = (0..surfels.len())
        .into_par_iter()
        .map(|i| {
            let nn = surfels.neighbours(i, config.radius, config.max_neighbours);
            if nn.len() < config.min_neighbours.max(3) {
                return Vector3::zeros();
            }
            plane_normal(&surfels.points, nn).unwrap_or_else(Vector3::zeros)
        })
        .collect();
    surfels.normals = normals;
    orient(&mut surfels, &config.orientation);
    Ok(surfels)
}

/// The least-squares plane normal of the neighbourhood, or `None` when it is (near) collinear.
fn plane_normal(points: &[Point3<f32>], nn: &[Near]) -> Option<Vector3<f32>> {
    let (_, cov) = mean_covariance(nn.iter().map(|k| points[k.index()].coords.cast::<f64>()));
    let eig = symmetric_eigen3(&cov);
    // A line (λ₁ ≈ 0) has no unique plane; its "normal" would be noise.
    if eig.values[2].is_nan() || eig.values[2] <= 0.0 || eig.values[1] < 1e-4 * eig.values[2] {
        return None;
    }
    let normal = eig.vectors.column(0).into_owned().cast::<f32>();
    normal.iter().all(|c| c.is_finite()).then_some(normal)
}

/// Flips normals so that each follows the orientation rule.
fn orient(surfels: &mut Surfels, rule: &Orientation) {
    let towards: Vec<Vector3<f32>> = match *rule {
        Orientation::LocalMass { radius } => mass_directions(surfels, radius),
        Orientation::Viewpoint(v) => surfels.points.iter().map(|p| v - p).collect(),
        Orientation::AboveCentroid { height } => {
            let n = surfels.len().max(1) as f64;
            let c = surfels.points.iter().fold(Vector3::zeros(), |acc, p| acc + p.coords.cast::<f64>()) / n;
            let view = Point3::from(c.cast::<f32>() + Vector3::z() * height);
            surfels.points.iter().map(|p| view - p).collect()
        }
    };
    for (n, t) in surfels.normals.iter_mut().zip(&towards) {
        if n.dot(t) < 0.0 {
            *n = -*n;
        }
    }
}

/// Per point, the direction its normal should face: the side with more mass, else up.
fn mass_directions(surfels: &Surfels, radius: f32) -> Vec<Vector3<f32>> {
    (0..surfels.len())
        .into_par_iter()
        .map(|i| {
            let p = surfels.points[i];
            let nn = surfels.neighbours(i, radius, usize::MAX);
            let offset = nn.iter().fold(Vector3::<f32>::zeros(), |acc, k| acc + (surfels.points[k.index()] - p))
                / nn.len() as f32;
            // Balanced (the centroid lies in the plane within 1% of the radius): use the +z prior.
            let n = surfels.normals[i];
            if n.dot(&offset).abs() < 0.01 * radius { Vector3::z() } else { offset }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ground_points_up_and_wall_faces_the_ground_side() {
        // Ground z = 0 over x in [0, 6], wall x = 6 rising from it.
        let mut pts = Vec::new();
        for i in 0..60 {
            for j in 0..30 {
                pts.push(Point3::new(i as f32 * 0.1, j as f32 * 0.1, 0.0));
                if i < 30 {
                    pts.push(Point3::new(6.0, j as f32 * 0.1, i as f32 * 0.1));
                }
            }
        }
        let config =
            NormalConfig { radius: 0.25, orientation: Orientation::LocalMass { radius: 2.0 }, ..Default::default() };
        let s = estimate_normals(&PointCloud::from_points(pts), &config, 2.0).unwrap();
        for (p, n) in s.points.iter().zip(&s.normals) {
            if p.z == 0.0 && p.x < 4.0 {
                assert!(n.z > 0.99, "{p} {n}");
            }
            // Higher up, the ground is out of reach and nothing tells the sides apart.
            if p.x == 6.0 && p.z > 0.5 && p.z < 1.5 {
                assert!(n.x < -0.99, "{p} {n}");
            }
        }
    }

    #[test]
    fn collinear_points_get_no_normal() {
        let line: Vec<_> = (0..50).map(|i| Point3::new(i as f32 * 0.1, 0.0, 0.0)).collect();
        let s = estimate_normals(&PointCloud::from_points(line), &NormalConfig::default(), 1.0).unwrap();
        assert_eq!(s.with_normals(), 0);
    }
}
