//! A world: objects, the BVH over them, and the ground surface robots drive on.

use nalgebra::{Point3, Unit, Vector3};

use crate::bvh::Bvh;
use crate::geometry::{Aabb, Hit, Object, Plane, Ray, Shape, Triangle};

/// One sinusoidal component of a hilly ground: `amplitude · sin(kx·x + ky·y + phase)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Wave {
    /// Height amplitude, metres.
    pub amplitude: f64,
    /// Wave vector x component, radians per metre.
    pub kx: f64,
    /// Wave vector y component, radians per metre.
    pub ky: f64,
    /// Phase, radians.
    pub phase: f64,
}

/// The analytic ground surface robots drive on; the rendered ground (a plane or a triangle mesh)
/// follows it.
#[derive(Clone, Debug, PartialEq)]
pub enum Terrain {
    /// A horizontal floor at this height.
    Flat(f64),
    /// Smooth hills: a sum of sine waves, so height and normal are exact and infinitely smooth.
    Hills(Vec<Wave>),
}

impl Terrain {
    /// Ground height at (x, y).
    pub fn height(&self, x: f64, y: f64) -> f64 {
        match self {
            Terrain::Flat(z) => *z,
            Terrain::Hills(waves) => waves.iter().map(|w| w.amplitude * (w.kx * x + w.ky * y + w.phase).sin()).sum(),
        }
    }

    /// Upward unit normal of the ground at (x, y).
    pub fn normal(&self, x: f64, y: f64) -> Unit<Vector3<f64>> {
        match self {
            Terrain::Flat(_) => Vector3::z_axis(),
            Terrain::Hills(waves) => {
                let (mut gx, mut gy) = (0.0, 0.0);
                for w in waves {
                    let c = w.amplitude * (w.kx * x + w.ky * y + w.phase).cos();
                    gx += c * w.kx;
                    gy += c * w.ky;
                }
                Unit::new_normalize(Vector3::new(-gx, -gy, 1.0))
            }
        }
    }

    /// The objects that render this ground over the square `[min, max]²` (x and y): a plane when
    /// flat, else a mesh of `cell`-sized squares split in two triangles, vertices on the surface.
    pub fn render(&self, min: f64, max: f64, cell: f64, reflectivity: f32) -> Vec<Object> {
        if let Terrain::Flat(z) = self {
            return vec![Object::new(Shape::Plane(Plane::horizontal(*z)), reflectivity)];
        }
        let n = ((max - min) / cell).ceil().max(1.0) as usize;
        let step = (max - min) / n as f64;
        let vertex = |i: usize, j: usize| {
            let (x, y) = (min + i as f64 * step, min + j as f64 * step);
            Point3::new(x, y, self.height(x, y))
        };
        let mut out = Vec::with_capacity(2 * n * n);
        for i in 0..n {
            for j in 0..n {
                let [a, b, c, d] = [vertex(i, j), vertex(i + 1, j), vertex(i + 1, j + 1), vertex(i, j + 1)];
                for vertices in [[a, b, c], [a, c, d]] {
                    out.push(Object::new(Shape::Triangle(Triangle { vertices }), reflectivity));
                }
            }
        }
        out
    }
}

/// A surface point hit by a ray, with the object it belongs to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldHit {
    /// Distance and normal.
    pub hit: Hit,
    /// Index into [`World::objects`].
    pub object: u32,
}

/// A static world: objects, a BVH over the bounded ones, and the ground.
#[derive(Clone, Debug)]
pub struct World {
    objects: Vec<Object>,
    bvh: Bvh,
    /// Objects without bounds (planes), tested on every ray; worlds have one or two.
    unbounded: Vec<u32>,
    terrain: Terrain,
}

impl World {
    /// A world of `objects` (which should include the rendered ground) on `terrain`.
    pub fn new(objects: Vec<Object>, terrain: Terrain) -> World {
        let (bounded, unbounded): (Vec<u32>, Vec<u32>) =
            (0..objects.len() as u32).partition(|&i| objects[i as usize].shape.bounds().is_some());
        let bvh = Bvh::build(&objects, &bounded);
        World { objects, bvh, unbounded, terrain }
    }

    /// All objects.
    pub fn objects(&self) -> &[Object] {
        &self.objects
    }

    /// The ground robots drive on.
    pub fn terrain(&self) -> &Terrain {
        &self.terrain
    }

    /// Nodes in the BVH (for reports).
    pub fn bvh_nodes(&self) -> usize {
        self.bvh.node_count()
    }

    /// The nearest surface along `ray` within `max_range`, through the BVH.
    pub fn cast(&self, ray: &Ray, max_range: f64) -> Option<WorldHit> {
        // Planes first: the floor is usually near and bounds the BVH search.
        let mut best = self.nearest(ray, max_range, self.unbounded.iter().copied());
        let t_max = best.map_or(max_range, |b| b.hit.t);
        if let Some((hit, object)) = self.bvh.cast(&self.objects, ray, t_max) {
            best = Some(WorldHit { hit, object });
        }
        best
    }

    /// The same as [`World::cast`] by testing every object: the reference the BVH is checked against.
    pub fn cast_brute_force(&self, ray: &Ray, max_range: f64) -> Option<WorldHit> {
        self.nearest(ray, max_range, 0..self.objects.len() as u32)
    }

    /// Nearest hit closer than `max_range` among `candidates`.
    fn nearest(&self, ray: &Ray, max_range: f64, candidates: impl Iterator<Item = u32>) -> Option<WorldHit> {
        let mut best: Option<WorldHit> = None;
        for object in candidates {
            if let Some(hit) = self.objects[object as usize].shape.intersect(ray)
                && hit.t < best.map_or(max_range, |b| b.hit.t)
            {
                best = Some(WorldHit { hit, object });
            }
        }
        best
    }

    /// True when no solid object comes within `clearance` of `p` (ground surfaces do not count).
    pub fn is_free(&self, p: &Point3<f64>, clearance: f64) -> bool {
        self.bvh.find_near(&self.objects, p, clearance, |o| o.shape.contains(p, clearance)).is_none()
    }

    /// Bounding box of all bounded objects except ground triangles (the built-up area, for drawing).
    pub fn extent(&self) -> Aabb {
        self.objects
            .iter()
            .filter(|o| !matches!(o.shape, Shape::Triangle(_)))
            .filter_map(|o| o.shape.bounds())
            .fold(Aabb::empty(), |a, b| a.union(&b))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hill_normal_matches_finite_differences() {
        let t = Terrain::Hills(vec![
            Wave { amplitude: 2.0, kx: 0.03, ky: 0.01, phase: 0.4 },
            Wave { amplitude: 0.7, kx: -0.02, ky: 0.05, phase: 1.0 },
        ]);
        let (x, y, h) = (12.0, -7.0, 1e-5);
        let gx = (t.height(x + h, y) - t.height(x - h, y)) / (2.0 * h);
        let gy = (t.height(x, y + h) - t.height(x, y - h)) / (2.0 * h);
        let expected = Vector3::new(-gx, -gy, 1.0).normalize();
        assert!((t.normal(x, y).into_inner() - expected).norm() < 1e-8);
    }

    #[test]
    fn mesh_vertices_lie_on_the_terrain() {
        let t = Terrain::Hills(vec![Wave { amplitude: 1.0, kx: 0.1, ky: 0.0, phase: 0.0 }]);
        for o in t.render(-4.0, 4.0, 2.0, 0.3) {
            let Shape::Triangle(tri) = o.shape else { panic!("hills render as triangles") };
            for v in tri.vertices {
                assert!((v.z - t.height(v.x, v.y)).abs() < 1e-12);
            }
        }
    }
}
