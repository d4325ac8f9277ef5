//! A synthetic place: what a sensor at the origin sees of boxes standing at irregular places.

use nalgebra::{Isometry3, Point3, Vector3};

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

/// A synthetic yard: `size` x `size` m of ground from the origin and boxes of random sizes on it
/// (seeded), `per_m2` points per square metre.
pub fn yard(seed: u64, size: f32, per_m2: f32) -> Vec<Point3<f32>> {
    let mut rng = Rng::xorshift64_star(Rng::spread(seed));
    let mut unit = move || rng.f32();
    let mut points = Vec::new();
    let patch =
        |points: &mut Vec<Point3<f32>>, unit: &mut dyn FnMut() -> f32, o: [f32; 3], a: [f32; 3], b: [f32; 3]| {
            let area = {
                let (a, b) = (Vector3::from(a), Vector3::from(b));
                a.cross(&b).norm()
            };
            for _ in 0..(area * per_m2) as usize {
                let (u, v) = (unit(), unit());
                points.push(Point3::from(std::array::from_fn(|i| o[i] + u * a[i] + v * b[i])));
            }
        };
    patch(&mut points, &mut unit, [0.0, 0.0, 0.0], [size, 0.0, 0.0], [0.0, size, 0.0]);
    for _ in 0..(size * size / 40.0) as usize {
        let (x, y) = (unit() * (size - 6.0), unit() * (size - 6.0));
        let (w, d, h) = (1.0 + 5.0 * unit(), 1.0 + 5.0 * unit(), 0.5 + 4.0 * unit());
        patch(&mut points, &mut unit, [x, y, 0.0], [w, 0.0, 0.0], [0.0, 0.0, h]);
        patch(&mut points, &mut unit, [x, y + d, 0.0], [w, 0.0, 0.0], [0.0, 0.0, h]);
        patch(&mut points, &mut unit, [x, y, 0.0], [0.0, d, 0.0], [0.0, 0.0, h]);
        patch(&mut points, &mut unit, [x + w, y, 0.0], [0.0, d, 0.0], [0.0, 0.0, h]);
        patch(&mut points, &mut unit, [x, y, h], [w, 0.0, 0.0], [0.0, d, 0.0]);
    }
    points
}

/// A [`yard`] seen in part (x below half its size), then whole, as a robot's map grows: the
/// first part's points stay where they were and in their order, but for one in a thousand moved a
/// centimetre and one in a thousand gone (a voxel map's centroids as a robot passes again); the
/// rest of the yard follows them. Returns (older, newer).
pub fn yard_seen_then_whole(seed: u64, size: f32, per_m2: f32) -> (Vec<Point3<f32>>, Vec<Point3<f32>>) {
    let yard = yard(seed, size, per_m2);
    let half = size / 2.0;
    let older: Vec<Point3<f32>> = yard.iter().filter(|p| p.x < half).copied().collect();
    let mut newer: Vec<Point3<f32>> = older
        .iter()
        .enumerate()
        .filter(|(i, _)| i % 997 != 5)
        .map(|(i, p)| if i % 1009 == 3 { p + Vector3::new(0.01, 0.0, 0.0) } else { *p })
        .collect();
    newer.extend(yard.iter().filter(|p| p.x >= half));
    (older, newer)
}

/// Two maps that share a small part: each holds the same 40 m yard at its origin and a 100 m yard
/// of its own beside it (the target's to +x, the source's to -x); the source is seen from a frame
/// `truth` away (its points are `truth⁻¹` of the world's), so `truth` maps it into the target.
/// Returns (target, source). The shared place's centre is (20, 20) in the world.
pub fn yards_sharing_one(truth: &Isometry3<f64>) -> (Vec<Point3<f32>>, Vec<Point3<f32>>) {
    let beside = |seed, x: f32| yard(seed, 100.0, 6.0).into_iter().map(move |p| p + Vector3::new(x, -50.0, 0.0));
    let target: Vec<Point3<f32>> = yard(11, 40.0, 6.0).into_iter().chain(beside(12, 41.0)).collect();
    let seen_from = truth.inverse().cast::<f32>();
    let source = yard(11, 40.0, 6.0).into_iter().chain(beside(13, -101.0)).map(|p| seen_from * p).collect();
    (target, source)
}
