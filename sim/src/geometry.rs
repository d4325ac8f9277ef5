//! Analytic primitives and their closed-form ray intersections.
//!
//! Every intersection returns the nearest hit with `t > 0` along a unit-direction ray, so `t` is the
//! range in metres. Solids (cuboids, cylinders, spheres) are hit from outside on their near face; a
//! ray starting inside one hits the far face, which never happens for a sensor in free space.

use nalgebra::{Point3, Vector3};

/// A ray `origin + t · direction` with a unit direction, so `t` is a distance in metres.
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    /// Start point.
    pub origin: Point3<f64>,
    /// Unit direction.
    pub direction: Vector3<f64>,
    /// Component-wise `1 / direction` (see [`reciprocal`]), for slab tests.
    inverse: Vector3<f64>,
}

impl Ray {
    /// A ray from `origin` along `direction` (normalised here; must not be zero).
    pub fn new(origin: Point3<f64>, direction: Vector3<f64>) -> Self {
        let direction = direction.normalize();
        Self { origin, direction, inverse: reciprocal(&direction) }
    }

    /// Component-wise `1 / direction`, ±1e300 along axes the ray does not move on.
    pub fn inverse(&self) -> Vector3<f64> {
        self.inverse
    }

    /// The point at distance `t`.
    pub fn at(&self, t: f64) -> Point3<f64> {
        self.origin + t * self.direction
    }
}

/// Component-wise `1 / v`, with ±1e300 standing in for ±∞: slab tests then never compute
/// `0 · ∞ = NaN` for a ray starting on a slab it runs parallel to.
fn reciprocal(v: &Vector3<f64>) -> Vector3<f64> {
    v.map(|d| (1.0 / d).clamp(-1e300, 1e300))
}

/// An axis-aligned bounding box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Smallest corner.
    pub min: Point3<f64>,
    /// Largest corner.
    pub max: Point3<f64>,
}

impl Aabb {
    /// The box that contains nothing; growing it by a point gives that point.
    pub fn empty() -> Self {
        Self { min: Point3::from([f64::INFINITY; 3]), max: Point3::from([f64::NEG_INFINITY; 3]) }
    }

    /// The smallest box holding both.
    pub fn union(&self, other: &Aabb) -> Aabb {
        Aabb { min: self.min.inf(&other.min), max: self.max.sup(&other.max) }
    }

    /// The smallest box holding this one and `p`.
    pub fn grow(&self, p: &Point3<f64>) -> Aabb {
        Aabb { min: self.min.inf(p), max: self.max.sup(p) }
    }

    /// The centre point.
    pub fn centroid(&self) -> Point3<f64> {
        nalgebra::center(&self.min, &self.max)
    }

    /// Surface area, the SAH's estimate of how often a random ray hits the box (0 when empty).
    pub fn area(&self) -> f64 {
        let e = self.max - self.min;
        if e.iter().any(|&v| v < 0.0) {
            return 0.0;
        }
        2.0 * (e.x * e.y + e.y * e.z + e.z * e.x)
    }

    /// Distance at which `ray` enters the box, if it does before `t_max` (0 when it starts inside).
    #[inline]
    pub fn entry(&self, ray: &Ray, t_max: f64) -> Option<f64> {
        // Unrolled over the axes: this is the innermost loop of the BVH traversal.
        let (o, inv) = (&ray.origin, &ray.inverse);
        let (ax, bx) = ((self.min.x - o.x) * inv.x, (self.max.x - o.x) * inv.x);
        let (ay, by) = ((self.min.y - o.y) * inv.y, (self.max.y - o.y) * inv.y);
        let (az, bz) = ((self.min.z - o.z) * inv.z, (self.max.z - o.z) * inv.z);
        // min/max skip the NaN of a zero direction component on a slab face.
        let t0 = ax.min(bx).max(ay.min(by)).max(az.min(bz)).max(0.0);
        let t1 = ax.max(bx).min(ay.max(by)).min(az.max(bz)).min(t_max);
        (t0 <= t1).then_some(t0)
    }
}

/// Where a ray meets a surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the ray, metres.
    pub t: f64,
    /// Unit surface normal at the hit (sign not significant: surfaces are two-sided for intensity).
    pub normal: Vector3<f64>,
}

/// A box with vertical and horizontal faces, turned by `yaw` about the vertical through its centre.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cuboid {
    /// Centre.
    pub center: Point3<f64>,
    /// Half the size along the box's own x, y, z axes.
    pub half: Vector3<f64>,
    /// Rotation about the vertical, radians, counter-clockwise seen from above.
    pub yaw: f64,
    cos: f64,
    sin: f64,
}

impl Cuboid {
    /// A box of full `size` centred at `center`, turned by `yaw` radians.
    pub fn new(center: Point3<f64>, size: Vector3<f64>, yaw: f64) -> Self {
        Self { center, half: size / 2.0, yaw, cos: yaw.cos(), sin: yaw.sin() }
    }

    /// An axis-aligned box between two corners.
    pub fn from_corners(a: Point3<f64>, b: Point3<f64>) -> Self {
        Self::new(nalgebra::center(&a, &b), (b - a).abs(), 0.0)
    }

    /// A vector from the world frame into the box frame.
    fn box_frame(&self, v: &Vector3<f64>) -> Vector3<f64> {
        Vector3::new(self.cos * v.x + self.sin * v.y, -self.sin * v.x + self.cos * v.y, v.z)
    }

    /// A vector from the box frame into the world frame.
    fn world_frame(&self, v: &Vector3<f64>) -> Vector3<f64> {
        Vector3::new(self.cos * v.x - self.sin * v.y, self.sin * v.x + self.cos * v.y, v.z)
    }

    /// The four corners of the footprint, counter-clockwise, for drawing.
    pub fn footprint(&self) -> [Point3<f64>; 4] {
        let (hx, hy) = (self.half.x, self.half.y);
        [(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)]
            .map(|(x, y)| self.center + self.world_frame(&Vector3::new(x, y, 0.0)))
    }

    /// Slab test in the box frame; the normal is the face crossed.
    fn intersect(&self, ray: &Ray) -> Option<Hit> {
        let o = self.box_frame(&(ray.origin - self.center));
        // Unturned boxes (most of them) reuse the ray's reciprocal direction: no division.
        let inverse = if self.yaw == 0.0 { ray.inverse } else { reciprocal(&self.box_frame(&ray.direction)) };
        let a = (-self.half - o).component_mul(&inverse);
        let b = (self.half - o).component_mul(&inverse);
        let near = Vector3::new(a.x.min(b.x), a.y.min(b.y), a.z.min(b.z));
        let far = Vector3::new(a.x.max(b.x), a.y.max(b.y), a.z.max(b.z));
        let t_in = near.x.max(near.y).max(near.z);
        let t_out = far.x.min(far.y).min(far.z);
        if t_in > t_out || t_out <= 0.0 {
            return None;
        }
        // Entering from outside, else leaving (a ray that starts inside sees the far face).
        let (t, faces) = if t_in > 0.0 { (t_in, near) } else { (t_out, far) };
        let axis = if t == faces.x {
            0
        } else if t == faces.y {
            1
        } else {
            2
        };
        let mut n = Vector3::zeros();
        n[axis] = 1.0;
        Some(Hit { t, normal: self.world_frame(&n) })
    }

    /// True when `p` is inside the box grown by `margin` on every side.
    fn contains(&self, p: &Point3<f64>, margin: f64) -> bool {
        let q = self.box_frame(&(p - self.center));
        (0..3).all(|i| q[i].abs() < self.half[i] + margin)
    }

    /// Bounding box of the turned box.
    fn bounds(&self) -> Aabb {
        let ex = self.cos.abs() * self.half.x + self.sin.abs() * self.half.y;
        let ey = self.sin.abs() * self.half.x + self.cos.abs() * self.half.y;
        let e = Vector3::new(ex, ey, self.half.z);
        Aabb { min: self.center - e, max: self.center + e }
    }
}

/// A vertical solid cylinder with flat caps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cylinder {
    /// Axis position (x, y); z is ignored.
    pub center: Point3<f64>,
    /// Radius, metres.
    pub radius: f64,
    /// Bottom of the cylinder.
    pub z_min: f64,
    /// Top of the cylinder.
    pub z_max: f64,
}

impl Cylinder {
    /// The side (quadratic in the horizontal plane) and both caps; nearest positive candidate wins.
    fn intersect(&self, ray: &Ray) -> Option<Hit> {
        let (ox, oy) = (ray.origin.x - self.center.x, ray.origin.y - self.center.y);
        let (dx, dy, dz) = (ray.direction.x, ray.direction.y, ray.direction.z);
        let mut best: Option<Hit> = None;
        let mut consider = |t: f64, normal: Vector3<f64>| {
            if t > 0.0 && best.is_none_or(|b| t < b.t) {
                best = Some(Hit { t, normal });
            }
        };
        let a = dx * dx + dy * dy;
        if a > 0.0 {
            let b = ox * dx + oy * dy;
            let c = ox * ox + oy * oy - self.radius * self.radius;
            let disc = b * b - a * c;
            if disc >= 0.0 {
                let root = disc.sqrt();
                for t in [(-b - root) / a, (-b + root) / a] {
                    let z = ray.origin.z + t * dz;
                    if (self.z_min..=self.z_max).contains(&z) {
                        let n = Vector3::new(ox + t * dx, oy + t * dy, 0.0) / self.radius;
                        consider(t, n);
                    }
                }
            }
        }
        if dz != 0.0 {
            for z in [self.z_min, self.z_max] {
                let t = (z - ray.origin.z) / dz;
                let (x, y) = (ox + t * dx, oy + t * dy);
                if x * x + y * y <= self.radius * self.radius {
                    consider(t, Vector3::z());
                }
            }
        }
        best
    }

    /// True when `p` is inside the cylinder grown by `margin`.
    fn contains(&self, p: &Point3<f64>, margin: f64) -> bool {
        let r = self.radius + margin;
        let (x, y) = (p.x - self.center.x, p.y - self.center.y);
        x * x + y * y < r * r && p.z > self.z_min - margin && p.z < self.z_max + margin
    }

    /// Bounding box.
    fn bounds(&self) -> Aabb {
        let r = self.radius;
        Aabb {
            min: Point3::new(self.center.x - r, self.center.y - r, self.z_min),
            max: Point3::new(self.center.x + r, self.center.y + r, self.z_max),
        }
    }
}

/// A solid sphere (tree canopies, bollard tops).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sphere {
    /// Centre.
    pub center: Point3<f64>,
    /// Radius, metres.
    pub radius: f64,
}

impl Sphere {
    /// The nearest positive root of `|o + t d - c|² = r²`.
    fn intersect(&self, ray: &Ray) -> Option<Hit> {
        let oc = ray.origin - self.center;
        let b = oc.dot(&ray.direction);
        let c = oc.norm_squared() - self.radius * self.radius;
        let disc = b * b - c;
        if disc < 0.0 {
            return None;
        }
        let root = disc.sqrt();
        let t = [-b - root, -b + root].into_iter().find(|&t| t > 0.0)?;
        Some(Hit { t, normal: (oc + t * ray.direction) / self.radius })
    }
}

/// A two-sided triangle (terrain mesh).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Triangle {
    /// The corners.
    pub vertices: [Point3<f64>; 3],
}

impl Triangle {
    /// Möller–Trumbore: solve `o + t d = a + u (b - a) + v (c - a)` by Cramer's rule.
    fn intersect(&self, ray: &Ray) -> Option<Hit> {
        let [a, b, c] = self.vertices;
        let (e1, e2) = (b - a, c - a);
        let p = ray.direction.cross(&e2);
        let det = e1.dot(&p);
        if det.abs() < 1e-14 {
            return None;
        }
        let inv = 1.0 / det;
        let s = ray.origin - a;
        let u = s.dot(&p) * inv;
        if !(0.0..=1.0).contains(&u) {
            return None;
        }
        let q = s.cross(&e1);
        let v = ray.direction.dot(&q) * inv;
        if v < 0.0 || u + v > 1.0 {
            return None;
        }
        let t = e2.dot(&q) * inv;
        (t > 0.0).then(|| Hit { t, normal: e1.cross(&e2).normalize() })
    }
}

/// An unbounded plane `normal · p = offset` (floors and ceilings of closed buildings).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plane {
    /// Unit normal.
    pub normal: Vector3<f64>,
    /// Signed distance of the plane from the origin along `normal`.
    pub offset: f64,
}

impl Plane {
    /// The horizontal plane at height `z`.
    pub fn horizontal(z: f64) -> Self {
        Self { normal: Vector3::z(), offset: z }
    }

    /// `t = (offset - n·o) / (n·d)` when the ray is not parallel.
    fn intersect(&self, ray: &Ray) -> Option<Hit> {
        let denom = self.normal.dot(&ray.direction);
        if denom == 0.0 {
            return None;
        }
        let t = (self.offset - self.normal.dot(&ray.origin.coords)) / denom;
        (t > 0.0).then_some(Hit { t, normal: self.normal })
    }
}

/// The geometric shape of a world object.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// A box, possibly turned about the vertical.
    Cuboid(Cuboid),
    /// A vertical cylinder.
    Cylinder(Cylinder),
    /// A sphere.
    Sphere(Sphere),
    /// A triangle.
    Triangle(Triangle),
    /// An unbounded plane (kept out of the BVH).
    Plane(Plane),
}

impl Shape {
    /// The nearest hit with `t > 0`, if any.
    #[inline]
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        match self {
            Shape::Cuboid(s) => s.intersect(ray),
            Shape::Cylinder(s) => s.intersect(ray),
            Shape::Sphere(s) => s.intersect(ray),
            Shape::Triangle(s) => s.intersect(ray),
            Shape::Plane(s) => s.intersect(ray),
        }
    }

    /// Bounding box; `None` for an unbounded plane.
    pub fn bounds(&self) -> Option<Aabb> {
        match self {
            Shape::Cuboid(s) => Some(s.bounds()),
            Shape::Cylinder(s) => Some(s.bounds()),
            Shape::Sphere(s) => {
                let r = Vector3::repeat(s.radius);
                Some(Aabb { min: s.center - r, max: s.center + r })
            }
            Shape::Triangle(s) => Some(s.vertices.iter().fold(Aabb::empty(), |b, v| b.grow(v))),
            Shape::Plane(_) => None,
        }
    }

    /// True when `p` lies inside the solid grown by `margin`; surfaces (planes, triangles) have no
    /// inside, so a robot on the ground is never "inside" it.
    pub fn contains(&self, p: &Point3<f64>, margin: f64) -> bool {
        match self {
            Shape::Cuboid(s) => s.contains(p, margin),
            Shape::Cylinder(s) => s.contains(p, margin),
            Shape::Sphere(s) => (p - s.center).norm() < s.radius + margin,
            Shape::Triangle(_) | Shape::Plane(_) => false,
        }
    }
}

/// A shape with a surface property.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Object {
    /// Geometry.
    pub shape: Shape,
    /// Diffuse reflectivity 0..1; the simulated intensity is `reflectivity · |cos(incidence)|`.
    pub reflectivity: f32,
}

impl Object {
    /// An object of `shape` with `reflectivity`.
    pub fn new(shape: Shape, reflectivity: f32) -> Self {
        Self { shape, reflectivity }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_4;

    fn ray(o: [f64; 3], d: [f64; 3]) -> Ray {
        Ray::new(Point3::from(o), Vector3::from(d))
    }

    #[test]
    fn cuboid_face_distance_and_turned_box_corner() {
        let b = Cuboid::new(Point3::new(10.0, 0.0, 0.0), Vector3::new(2.0, 2.0, 2.0), 0.0);
        let hit = b.intersect(&ray([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])).unwrap();
        assert!((hit.t - 9.0).abs() < 1e-12);
        assert!((hit.normal.x.abs() - 1.0).abs() < 1e-12);
        // Turned by 45°, the corner points at the origin: sqrt(2) closer than the centre.
        let d = Cuboid::new(Point3::new(10.0, 0.0, 0.0), Vector3::new(2.0, 2.0, 2.0), FRAC_PI_4);
        let hit = d.intersect(&ray([0.0, 0.0, 0.5], [1.0, 0.0, 0.0])).unwrap();
        assert!((hit.t - (10.0 - 2f64.sqrt())).abs() < 1e-12);
    }

    #[test]
    fn rays_from_inside_hit_the_far_face() {
        let b = Cuboid::from_corners(Point3::new(-1.0, -1.0, -1.0), Point3::new(1.0, 1.0, 1.0));
        let hit = b.intersect(&ray([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])).unwrap();
        assert!((hit.t - 1.0).abs() < 1e-12);
    }

    #[test]
    fn cylinder_side_and_cap() {
        let c = Cylinder { center: Point3::new(5.0, 0.0, 0.0), radius: 1.0, z_min: 0.0, z_max: 2.0 };
        let side = c.intersect(&ray([0.0, 0.0, 1.0], [1.0, 0.0, 0.0])).unwrap();
        assert!((side.t - 4.0).abs() < 1e-12);
        let cap = c.intersect(&ray([5.0, 0.5, 10.0], [0.0, 0.0, -1.0])).unwrap();
        assert!((cap.t - 8.0).abs() < 1e-12);
        assert!(c.intersect(&ray([0.0, 0.0, 3.0], [1.0, 0.0, 0.0])).is_none());
    }

    #[test]
    fn sphere_and_plane() {
        let s = Sphere { center: Point3::new(0.0, 0.0, 10.0), radius: 2.0 };
        assert!((s.intersect(&ray([0.0; 3], [0.0, 0.0, 1.0])).unwrap().t - 8.0).abs() < 1e-12);
        let p = Plane::horizontal(-2.0);
        let hit = p.intersect(&ray([0.0; 3], [1.0, 0.0, -1.0])).unwrap();
        assert!((hit.t - 2.0 * 2f64.sqrt()).abs() < 1e-12);
        assert!(p.intersect(&ray([0.0; 3], [1.0, 0.0, 0.0])).is_none());
    }

    #[test]
    fn turned_cuboid_bounds_hold_its_footprint() {
        let b = Cuboid::new(Point3::new(1.0, 2.0, 0.0), Vector3::new(4.0, 1.0, 1.0), 0.7);
        let bounds = b.bounds();
        for p in b.footprint() {
            assert!(p.x >= bounds.min.x - 1e-12 && p.x <= bounds.max.x + 1e-12);
            assert!(p.y >= bounds.min.y - 1e-12 && p.y <= bounds.max.y + 1e-12);
        }
    }
}
