//! The built-in worlds and the robot routes through them.
//!
//! Layouts are fixed: randomised details (rack loads, trees, cars) come from a generator with a
//! constant seed, so a world is the same on every machine and in every run.

pub mod aisles;
pub mod campus;
pub mod corridor;
mod rack;
pub mod warehouse;

use nalgebra::{Point2, Point3, Vector2, Vector3};

use super::geometry::{Cuboid, Cylinder, Object, Plane, Shape, Sphere};
use super::trajectory::{Trajectory, TrajectoryConfig};
use super::world::{Terrain, World};

/// Reflectivities of the materials used (0..1, diffuse).
pub(crate) mod material {
    /// Painted concrete walls.
    pub const WALL: f32 = 0.35;
    /// Concrete floor.
    pub const FLOOR: f32 = 0.25;
    /// Roof sheeting seen from below.
    pub const CEILING: f32 = 0.2;
    /// Painted steel (racks, beams, posts).
    pub const STEEL: f32 = 0.55;
    /// Wooden pallets.
    pub const WOOD: f32 = 0.4;
    /// Cardboard boxes.
    pub const CARDBOARD: f32 = 0.45;
    /// Shrink-wrapped loads: brighter.
    pub const WRAP: f32 = 0.7;
    /// Safety-yellow machinery.
    pub const YELLOW: f32 = 0.75;
    /// Plastic bins.
    pub const PLASTIC: f32 = 0.5;
    /// Grass and soil.
    pub const GRASS: f32 = 0.2;
    /// Building facades.
    pub const FACADE: f32 = 0.4;
    /// Tree bark.
    pub const BARK: f32 = 0.15;
    /// Foliage (canopies).
    pub const FOLIAGE: f32 = 0.3;
    /// Car paint.
    pub const CAR: f32 = 0.6;
    /// Car windows.
    pub const GLASS: f32 = 0.1;
}

/// Collects the objects of a world under construction.
#[derive(Default)]
pub(crate) struct Builder {
    objects: Vec<Object>,
}

impl Builder {
    /// An axis-aligned box between two corners.
    fn block(&mut self, min: [f64; 3], max: [f64; 3], reflectivity: f32) {
        let shape = Cuboid::from_corners(Point3::from(min), Point3::from(max));
        self.objects.push(Object::new(Shape::Cuboid(shape), reflectivity));
    }

    /// A box of `size` standing on height `z`, centred at (x, y), turned by `yaw`.
    fn turned(&mut self, x: f64, y: f64, z: f64, size: [f64; 3], yaw: f64, reflectivity: f32) {
        let centre = Point3::new(x, y, z + size[2] / 2.0);
        let shape = Cuboid::new(centre, Vector3::from(size), yaw);
        self.objects.push(Object::new(Shape::Cuboid(shape), reflectivity));
    }

    /// A vertical cylinder.
    fn cylinder(&mut self, x: f64, y: f64, radius: f64, z: [f64; 2], reflectivity: f32) {
        let shape = Cylinder { center: Point3::new(x, y, 0.0), radius, z_min: z[0], z_max: z[1] };
        self.objects.push(Object::new(Shape::Cylinder(shape), reflectivity));
    }

    /// A sphere.
    fn sphere(&mut self, centre: [f64; 3], radius: f64, reflectivity: f32) {
        let shape = Sphere { center: Point3::from(centre), radius };
        self.objects.push(Object::new(Shape::Sphere(shape), reflectivity));
    }

    /// A horizontal unbounded plane (floor or ceiling of a closed building).
    fn plane(&mut self, z: f64, reflectivity: f32) {
        self.objects.push(Object::new(Shape::Plane(Plane::horizontal(z)), reflectivity));
    }

    /// Four walls of `thickness` whose inner faces enclose `[x0, x1] × [y0, y1]`.
    fn walls(&mut self, [x0, y0]: [f64; 2], [x1, y1]: [f64; 2], thickness: f64, height: f64) {
        let t = thickness;
        self.block([x0 - t, y0 - t, 0.0], [x1 + t, y0, height], material::WALL);
        self.block([x0 - t, y1, 0.0], [x1 + t, y1 + t, height], material::WALL);
        self.block([x0 - t, y0, 0.0], [x0, y1, height], material::WALL);
        self.block([x1, y0, 0.0], [x1 + t, y1, height], material::WALL);
    }

    /// The world of the collected objects plus the ground rendering of `terrain`.
    fn finish(mut self, terrain: Terrain, ground: Vec<Object>) -> World {
        self.objects.extend(ground);
        World::new(self.objects, terrain)
    }
}

/// Waypoints along lane centre lines through `corners`, each interior corner rounded by a circular
/// fillet of `radius` (smaller where the legs are short). The spline passes through points sampled
/// on each fillet arc, and through guide points on the legs beside it, so it follows the lines and
/// arcs closely instead of bulging out of the lane.
fn lanes(corners: &[[f64; 2]], radius: f64) -> Vec<Point2<f64>> {
    let p: Vec<Vector2<f64>> = corners.iter().map(|&c| Vector2::from(c)).collect();
    let n = p.len();
    let fillets: Vec<Option<Fillet>> =
        (0..n).map(|i| (i > 0 && i + 1 < n).then(|| Fillet::at(p[i - 1], p[i], p[i + 1], radius)).flatten()).collect();
    let inset = |f: &Option<Fillet>| f.as_ref().map_or(0.0, |f| f.tangent);
    let mut out = vec![Point2::from(p[0])];
    for i in 0..n - 1 {
        let leg = p[i + 1] - p[i];
        let (length, d) = (leg.norm(), leg.normalize());
        if let Some(f) = &fillets[i] {
            out.extend(f.arc.iter().map(|&a| Point2::from(a)));
        }
        // Guide points where the straight part of the leg starts and ends.
        let (a, b) = (inset(&fillets[i]), length - inset(&fillets[i + 1]));
        // Short straights between two turns need none: extra points there make the spline wiggle.
        let guide = ((b - a) / 3.0).min(1.0);
        if b - a > 2.0 {
            out.push(Point2::from(p[i] + (a + guide) * d));
            out.push(Point2::from(p[i] + (b - guide) * d));
        }
        if fillets[i + 1].is_none() {
            out.push(Point2::from(p[i + 1]));
        }
    }
    out
}

/// The circular arc that rounds one corner.
struct Fillet {
    /// Distance from the corner to where the arc meets each leg.
    tangent: f64,
    /// Points along the arc, from the incoming leg to the outgoing one.
    arc: Vec<Vector2<f64>>,
}

impl Fillet {
    /// The fillet at `corner` between the legs from `before` and to `after`, its radius reduced so
    /// it uses at most 40 % of either leg; `None` where the route runs straight on.
    fn at(before: Vector2<f64>, corner: Vector2<f64>, after: Vector2<f64>, radius: f64) -> Option<Fillet> {
        let (d_in, d_out) = ((corner - before).normalize(), (after - corner).normalize());
        let turn = d_in.perp(&d_out).atan2(d_in.dot(&d_out)); // signed, left positive
        if turn.abs() < 1e-3 {
            return None;
        }
        let half = (turn.abs() / 2.0).tan();
        let room = 0.4 * (corner - before).norm().min((after - corner).norm());
        let r = radius.min(room / half);
        let tangent = r * half;
        let start = corner - tangent * d_in;
        let left = Vector2::new(-d_in.y, d_in.x) * turn.signum();
        let centre = start + r * left;
        let steps = ((turn.abs() / (std::f64::consts::PI / 8.0)).ceil() as usize).max(2);
        let arc = (0..=steps)
            .map(|k| {
                let angle = turn * k as f64 / steps as f64;
                let (s, c) = angle.sin_cos();
                let from_centre = start - centre;
                centre + Vector2::new(c * from_centre.x - s * from_centre.y, s * from_centre.x + c * from_centre.y)
            })
            .collect();
        Some(Fillet { tangent, arc })
    }
}

/// A trajectory along `corners` (see [`lanes`]) driven with `config`.
fn route(corners: &[[f64; 2]], radius: f64, terrain: &Terrain, config: &TrajectoryConfig) -> Trajectory {
    // The built-in routes are fixed data checked by the tests; failing here is a programming error.
    Trajectory::new(&lanes(corners, radius), false, terrain, config).expect("built-in routes are valid")
}
