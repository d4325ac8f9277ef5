//! `corridor`: a 4 m wide corridor whose 3 m walls run far beyond a sensor's range, closed at one
//! end with pillars in front of that end. Away from the end every scan sees two parallel walls and
//! a floor: nothing fixes the position along the corridor, the trap of odometry and loop closure
//! alike. Not a scenario of the catalog: tests build their own paths through it.

use std::sync::Arc;

use nalgebra::{Point3, Vector3};

use crate::geometry::{Cuboid, Object, Shape};
use crate::world::{Terrain, World};

/// The corridor: walls at y = ±2.1 m from x = -10 to 210 m, the closed end at x = -4 m, pillars
/// between the end and x = 3 m, a flat floor.
pub fn world() -> Arc<World> {
    let wall = |y: f64| {
        Object::new(Shape::Cuboid(Cuboid::new(Point3::new(100.0, y, 1.5), Vector3::new(220.0, 0.2, 3.0), 0.0)), 0.6)
    };
    let mut objects = vec![wall(-2.1), wall(2.1)];
    objects.push(Object::new(
        Shape::Cuboid(Cuboid::new(Point3::new(-4.0, 0.0, 1.5), Vector3::new(0.2, 4.0, 3.0), 0.0)),
        0.6,
    ));
    for (x, y) in [(-2.5, -1.2), (-1.0, 1.3), (1.0, -1.4), (3.0, 1.2)] {
        objects.push(Object::new(
            Shape::Cuboid(Cuboid::new(Point3::new(x, y, 0.5), Vector3::new(0.4, 0.4, 1.0), 0.4)),
            0.5,
        ));
    }
    let terrain = Terrain::Flat(0.0);
    objects.extend(terrain.render(0.0, 0.0, 1.0, 0.3));
    Arc::new(World::new(objects, terrain))
}
