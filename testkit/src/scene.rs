//! A synthetic place: what a sensor at the origin sees of boxes standing at irregular places.

use nalgebra::Point3;

use crate::Rng;

/// Forty boxes, 2 m wide and 0.5-6 m tall, scattered over 70 x 70 m around the origin (seeded),
/// with the ground 2 m below the sensor: a scan's points, as a place descriptor sees them.
pub fn boxes_around(seed: u64) -> Vec<Point3<f32>> {
    let mut rng = Rng::new(seed);
    let mut points = Vec::new();
    for _ in 0..40 {
        let (cx, cy) = (rng.uniform(-35.0, 35.0), rng.uniform(-35.0, 35.0));
        let h = rng.uniform(0.5, 6.0);
        for _ in 0..200 {
            let (dx, dy, z) = (rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.8, h - 2.0));
            points.push(Point3::new((cx + dx) as f32, (cy + dy) as f32, z as f32));
        }
    }
    points
}
