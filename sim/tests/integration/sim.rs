//! The simulator against analytic truth: ray casting, BVH, noise, motion distortion, trajectories,
//! scenario layout.

use std::collections::HashSet;
use std::f64::consts::{FRAC_PI_4, PI};
use std::sync::Arc;

use cloud::PointCloud;
use nalgebra::{Isometry3, Point2, Point3, Vector3};
use sim::noise::SplitMix;
use sim::{
    Cuboid, Cylinder, Object, Plane, Ray, Scenario, SensorModel, Shape, SimConfig, Simulator, Terrain, Trajectory,
    TrajectoryConfig, Triangle, World,
};

const ALL: [&str; 4] = ["warehouse-small", "warehouse-large", "campus", "aisles"];

fn world_of(shapes: Vec<Shape>) -> World {
    World::new(shapes.into_iter().map(|s| Object::new(s, 0.5)).collect(), Terrain::Flat(0.0))
}

fn cast(world: &World, origin: [f64; 3], direction: [f64; 3]) -> Option<f64> {
    world.cast(&Ray::new(Point3::from(origin), Vector3::from(direction)), 1e3).map(|h| h.hit.t)
}

fn close(a: Option<f64>, b: f64) -> bool {
    a.is_some_and(|a| (a - b).abs() < 1e-9)
}

#[test]
fn rays_at_known_angles_hit_at_closed_form_distances() {
    // Box face 10 m ahead, seen 30° off-axis in the horizontal plane: 10 / cos 30°.
    let cube = Shape::Cuboid(Cuboid::from_corners(Point3::new(10.0, -20.0, -5.0), Point3::new(12.0, 20.0, 5.0)));
    let w = world_of(vec![cube]);
    let a = 30f64.to_radians();
    assert!(close(cast(&w, [0.0; 3], [a.cos(), a.sin(), 0.0]), 10.0 / a.cos()));
    // Box turned by 45°: its edge points at the origin, sqrt(2)·half-size nearer than its centre.
    let turned = Shape::Cuboid(Cuboid::new(Point3::new(8.0, 0.0, 0.0), Vector3::new(2.0, 2.0, 2.0), FRAC_PI_4));
    assert!(close(cast(&world_of(vec![turned]), [0.0; 3], [1.0, 0.0, 0.0]), 8.0 - 2f64.sqrt()));
    // Vertical cylinder of radius 1 at distance 5, ray offset sideways by 0.6: 5 − sqrt(1 − 0.36).
    let cyl = Shape::Cylinder(Cylinder { center: Point3::new(5.0, 0.0, 0.0), radius: 1.0, z_min: -1.0, z_max: 1.0 });
    assert!(close(cast(&world_of(vec![cyl]), [0.0, 0.6, 0.0], [1.0, 0.0, 0.0]), 5.0 - 0.8));
    // Ground plane 0.7 m below, beam 15° down: 0.7 / sin 15°.
    let floor = Shape::Plane(Plane::horizontal(-0.7));
    let e = 15f64.to_radians();
    assert!(close(cast(&world_of(vec![floor]), [0.0; 3], [e.cos(), 0.0, -e.sin()]), 0.7 / e.sin()));
    // Triangle in the plane x + z = 4 around (2, 0, 2); ray along +x from z = 1 meets it at x = 3.
    let tri = Shape::Triangle(Triangle {
        vertices: [Point3::new(4.0, -3.0, 0.0), Point3::new(4.0, 3.0, 0.0), Point3::new(0.0, 0.0, 4.0)],
    });
    let w = world_of(vec![tri]);
    assert!(close(cast(&w, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]), 3.0));
    assert_eq!(cast(&w, [0.0, 5.0, 1.0], [1.0, 0.0, 0.0]), None, "passes beside the triangle");
}

/// Random origins over the world's extent and directions uniform on the sphere.
fn random_rays(world: &World, n: usize, seed: u64) -> Vec<Ray> {
    let e = world.extent();
    let mut rng = SplitMix::new(seed);
    (0..n)
        .map(|_| {
            let o = Point3::new(rng.range(e.min.x, e.max.x), rng.range(e.min.y, e.max.y), rng.range(0.2, 8.0));
            let z: f64 = rng.range(-1.0, 1.0);
            let phi = rng.range(-PI, PI);
            let r = (1.0 - z * z).sqrt();
            Ray::new(o, Vector3::new(r * phi.cos(), r * phi.sin(), z))
        })
        .collect()
}

#[test]
fn bvh_agrees_with_brute_force_in_every_world() {
    for name in ["warehouse-small", "campus", "aisles"] {
        let scenario = Scenario::by_name(name).unwrap();
        let world = scenario.world();
        let rays = random_rays(world, if name == "campus" { 1500 } else { 4000 }, 11);
        let mut hits = 0;
        for ray in &rays {
            let fast = world.cast(ray, 150.0).map(|h| h.hit.t);
            let slow = world.cast_brute_force(ray, 150.0).map(|h| h.hit.t);
            assert_eq!(fast, slow, "{name}: ray {ray:?}");
            hits += usize::from(fast.is_some());
        }
        assert!(hits > rays.len() / 2, "{name}: only {hits} hits");
        // Axis-parallel rays from origins on a 0.1 m grid: many start exactly in a face's plane,
        // where a careless slab test computes 0 · ∞.
        for ray in random_rays(world, 300, 12) {
            let o = ray.origin.map(|c| (c * 10.0).round() / 10.0);
            for d in [Vector3::x(), -Vector3::x(), Vector3::y(), -Vector3::y(), Vector3::z(), -Vector3::z()] {
                let ray = Ray::new(o, d);
                let fast = world.cast(&ray, 150.0).map(|h| h.hit.t);
                assert_eq!(fast, world.cast_brute_force(&ray, 150.0).map(|h| h.hit.t), "{name}: ray {ray:?}");
            }
        }
    }
}

fn bits(c: &PointCloud) -> Vec<u32> {
    let mut v: Vec<u32> = c.points.iter().flat_map(|p| [p.x, p.y, p.z]).map(f32::to_bits).collect();
    v.extend(c.intensity.iter().flatten().map(|x| x.to_bits()));
    v.extend(c.time.iter().flatten().map(|x| x.to_bits()));
    v.extend(c.ring.iter().flatten().map(|&r| u32::from(r)));
    v
}

#[test]
fn same_seed_gives_bit_identical_scans_on_any_thread_count() {
    let scenario = Scenario::by_name("warehouse-small").unwrap();
    let sim = |seed| Simulator::new(scenario.clone(), 1, SimConfig { seed, ..SimConfig::default() }).unwrap();
    let a = sim(42).scan(300);
    let one_thread = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let b = one_thread.install(|| sim(42).scan(300));
    assert_eq!(bits(&a.cloud), bits(&b.cloud));
    assert_eq!(a.ground_truth, b.ground_truth);
    let c = sim(43).scan(300);
    let same = a.cloud.points.iter().zip(&c.cloud.points).filter(|(p, q)| p == q).count();
    assert!(same < a.cloud.len() / 100, "{same} of {} points unchanged by the seed", a.cloud.len());
}

#[test]
fn channels_are_complete_and_in_range() {
    let sim = Simulator::new(Scenario::by_name("campus").unwrap(), 2, SimConfig::default()).unwrap();
    let scan = sim.scan(500);
    scan.cloud.validate().unwrap();
    let n = scan.cloud.len();
    assert!(n > 15_000, "{n} points");
    assert!(scan.cloud.intensity.as_ref().unwrap().iter().all(|i| (0.0..=1.0).contains(i)));
    assert!(scan.cloud.ring.as_ref().unwrap().iter().all(|&r| r < 16));
    let time = scan.cloud.time.as_ref().unwrap();
    assert!(time.windows(2).all(|w| w[0] <= w[1]), "points come in firing order");
    assert!(time.iter().all(|&t| (0.0..0.1).contains(&t)));
    assert_eq!(scan.stamp, 50.0);
    assert_eq!(scan.ground_truth, sim.pose_at(50.1));
}

/// A 60 m × 20 m room without a roof: walls 1 m thick at x = ±30 and y = ±10.
fn room() -> Arc<World> {
    let wall = |a: [f64; 3], b: [f64; 3]| Object::new(Shape::Cuboid(Cuboid::from_corners(a.into(), b.into())), 0.5);
    Arc::new(World::new(
        vec![
            Object::new(Shape::Plane(Plane::horizontal(0.0)), 0.3),
            wall([30.0, -11.0, 0.0], [31.0, 11.0, 5.0]),
            wall([-31.0, -11.0, 0.0], [-30.0, 11.0, 5.0]),
            wall([-31.0, 10.0, 0.0], [31.0, 11.0, 5.0]),
            wall([-31.0, -11.0, 0.0], [31.0, -10.0, 5.0]),
        ],
        Terrain::Flat(0.0),
    ))
}

/// A robot driving along +x at a constant `speed` from x = −20 to x = 28 in [`room`].
fn straight_run(speed: f64, noise: f64) -> Simulator {
    straight_run_of(SensorModel::vlp16(), speed, noise)
}

/// [`straight_run`] with another sensor.
fn straight_run_of(sensor: SensorModel, speed: f64, noise: f64) -> Simulator {
    let config = TrajectoryConfig {
        cruise_speed: speed,
        start_at_rest: false,
        stop_at_end: false,
        ..TrajectoryConfig::default()
    };
    let path = [Point2::new(-20.0, 0.0), Point2::new(28.0, 0.0)];
    let robot = Trajectory::new(&path, false, &Terrain::Flat(0.0), &config).unwrap();
    let scenario = Scenario::new("room", "straight run", room(), vec![robot]);
    let config = SimConfig { range_noise: noise, dropout: 0.0, sensor, ..SimConfig::default() };
    Simulator::new(scenario, 0, config).unwrap()
}

/// Distance from a world point to the nearest room surface.
fn room_residual(p: &Point3<f64>) -> f64 {
    [(p.x - 30.0).abs(), (p.x + 30.0).abs(), (p.y - 10.0).abs(), (p.y + 10.0).abs(), p.z.abs()]
        .into_iter()
        .fold(f64::INFINITY, f64::min)
}

/// Each point of a scan with its time within the sweep.
fn timed_points(c: &PointCloud) -> impl Iterator<Item = (Point3<f64>, f64)> + '_ {
    c.points.iter().zip(c.time.iter().flatten()).map(|(p, &t)| (p.cast::<f64>(), f64::from(t)))
}

#[test]
fn wall_ahead_approaches_at_the_driving_speed_within_a_sweep() {
    let (v, sigma) = (2.0, 0.01);
    let sim = straight_run(v, sigma);
    // At t = 23 s the sensor is at x = 26, 4 m from the front wall: the wall spans a wide angle.
    let frame = 230;
    let scan = sim.scan(frame);
    let d0 = 30.0 - sim.pose_at(scan.stamp).translation.x;
    assert!((d0 - 4.0).abs() < 1e-6);
    let mut residuals = Vec::new();
    let (mut st, mut sx, mut stt, mut stx) = (0.0, 0.0, 0.0, 0.0);
    for (p, t) in timed_points(&scan.cloud) {
        if p.x > 1.0 && p.z > -0.4 && p.y.abs() < 8.0 {
            residuals.push(p.x - (d0 - v * t));
            (st, sx, stt, stx) = (st + t, sx + p.x, stt + t * t, stx + t * p.x);
        }
    }
    let n = residuals.len() as f64;
    assert!(n > 1000.0, "{n} wall points");
    let rms = (residuals.iter().map(|r| r * r).sum::<f64>() / n).sqrt();
    assert!(rms < 1.5 * sigma, "wall points off d0 − v·t by {rms} m rms");
    let slope = (n * stx - st * sx) / (n * stt - st * st);
    assert!((slope + v).abs() < 0.1, "the wall approaches at {} m/s, expected {v}", -slope);
}

#[test]
fn per_point_poses_undo_the_skew_and_a_single_pose_does_not() {
    let (v, sigma) = (2.0, 0.01);
    let sim = straight_run(v, sigma);
    let scan = sim.scan(100);
    let period = sim.config().sensor.period;
    let (mut own, mut skew_error, mut single) = (Vec::new(), Vec::new(), Vec::new());
    let (mut first, mut last) = (Vec::new(), Vec::new());
    for (p, t) in timed_points(&scan.cloud) {
        let truth = sim.pose_at(scan.stamp + t) * p;
        own.push(room_residual(&truth));
        // Walls across the motion, away from the floor: there a single pose shows the skew.
        if truth.x.abs() > 29.0 && truth.z > 0.5 {
            let q = scan.ground_truth * p;
            let shift = q.x - truth.x;
            single.push(room_residual(&q));
            // The end-of-sweep pose is v·(period − t) ahead of the firing pose.
            skew_error.push(shift - v * (period - t));
            if truth.x < 0.0 && t < 0.002 {
                first.push(shift);
            } else if truth.x < 0.0 && t > period - 0.002 {
                last.push(shift);
            }
        }
    }
    let rms = |v: &[f64]| (v.iter().map(|r| r * r).sum::<f64>() / v.len() as f64).sqrt();
    assert!(rms(&own) < 1.5 * sigma, "re-projected with per-point poses: {} m rms", rms(&own));
    assert!(single.len() > 1000, "{} wall points", single.len());
    assert!(rms(&single) > 5.0 * sigma, "a single pose should leave the skew: {} m rms", rms(&single));
    assert!(rms(&skew_error) < 1e-3, "the skew differs from v·(period − t) by {} m rms", rms(&skew_error));
    // The seam behind the robot: the first columns are a whole sweep old, the last ones current.
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!(!first.is_empty() && !last.is_empty());
    assert!((mean(&first) - v * period).abs() < 0.005, "skew at the sweep start {}", mean(&first));
    assert!(mean(&last).abs() < 0.005, "skew at the sweep end {}", mean(&last));
}

#[test]
fn a_deskewed_sweep_lies_on_the_room_at_its_ground_truth_pose() {
    let (v, sigma) = (2.0, 0.01);
    let sim = straight_run(v, sigma);
    let scan = sim.scan(100);
    let deskewed = sim.deskewed(&scan);
    assert_eq!(deskewed.len(), scan.cloud.len());
    let rms = |c: &PointCloud, pose: &Isometry3<f64>| {
        let r: Vec<f64> = c.points.iter().map(|p| room_residual(&(pose * p.cast::<f64>()))).collect();
        (r.iter().map(|x| x * x).sum::<f64>() / r.len() as f64).sqrt()
    };
    assert!(rms(&deskewed, &scan.ground_truth) < 1.5 * sigma, "deskewed: {} m rms", rms(&deskewed, &scan.ground_truth));
    assert!(rms(&scan.cloud, &scan.ground_truth) > 3.0 * sigma, "raw: {} m rms", rms(&scan.cloud, &scan.ground_truth));
}

#[test]
fn a_rosette_sweep_looks_ahead_without_rings_and_lies_on_the_room() {
    let sigma = 0.01;
    let sim = straight_run_of(SensorModel::avia(), 2.0, sigma);
    // At t = 10 s the sensor is at x = 0, 30 m from the front wall, which fills the view.
    let scan = sim.scan(100);
    let cloud = &scan.cloud;
    assert!(cloud.ring.is_none(), "a rosette has no rings");
    // The room has no ceiling: rays passing over the 5 m walls 30 m ahead (pitch above ~8°,
    // about a third of the disc) return nothing.
    assert!(cloud.len() > 2400 && cloud.len() <= 4800, "{} points of 4800 rays", cloud.len());
    let mut residuals = Vec::new();
    for (p, t) in timed_points(cloud) {
        assert!(p.x > 0.0, "a point behind a forward-looking sensor: {p}");
        residuals.push(room_residual(&(sim.pose_at(scan.stamp + t) * p)));
    }
    let rms = (residuals.iter().map(|r| r * r).sum::<f64>() / residuals.len() as f64).sqrt();
    assert!(rms < 1.5 * sigma, "rosette points off the room by {rms} m rms");
    // The next sweep fires in other directions: no point of it repeats one of this sweep's.
    let next = sim.scan(101);
    let direction = |p: &Point3<f32>| p.coords.normalize();
    let repeated = next
        .cloud
        .points
        .iter()
        .take(200)
        .filter(|q| cloud.points.iter().any(|p| direction(p).dot(&direction(q)) > (0.01f32.to_radians()).cos()));
    assert!(repeated.count() < 20, "the rosette repeats itself between sweeps");
}

/// Measured minus true range of every point, the truth cast without noise from the pose at the
/// point's own time along the point's own direction.
fn range_residuals(sim: &Simulator, frame: usize) -> Vec<f64> {
    let scan = sim.scan(frame);
    timed_points(&scan.cloud)
        .map(|(p, t)| {
            let p = p.coords;
            let pose = sim.pose_at(scan.stamp + t);
            let ray = Ray::new(Point3::from(pose.translation.vector), pose.rotation * p);
            let truth = sim.scenario().world().cast(&ray, 200.0).expect("a returned ray hits").hit.t;
            p.norm() - truth
        })
        .collect()
}

#[test]
fn range_noise_has_the_configured_sigma_on_sloped_ground() {
    let scenario = Scenario::by_name("campus").unwrap();
    for sigma in [0.01, 0.03] {
        let config = SimConfig { range_noise: sigma, seed: 5, ..SimConfig::default() };
        let sim = Simulator::new(scenario.clone(), 3, config).unwrap();
        let r = range_residuals(&sim, 400);
        let n = r.len() as f64;
        let mean = r.iter().sum::<f64>() / n;
        let std = (r.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
        assert!(n > 10_000.0);
        assert!(mean.abs() < 0.05 * sigma, "bias {mean}");
        assert!((std / sigma - 1.0).abs() < 0.1, "std {std} for sigma {sigma}");
    }
}

#[test]
fn dropout_rate_matches_the_setting() {
    let scenario = Scenario::by_name("warehouse-small").unwrap();
    let count = |dropout| {
        let config = SimConfig { dropout, seed: 9, ..SimConfig::default() };
        Simulator::new(scenario.clone(), 0, config).unwrap().scan(200).cloud.len() as f64
    };
    let all = count(0.0);
    for p in [0.05, 0.3] {
        let kept = count(p) / all;
        assert!((kept - (1.0 - p)).abs() < 0.02, "dropout {p}: kept {kept}");
    }
}

/// Horizontal position and heading of a pose.
fn planar(pose: &Isometry3<f64>) -> (Point2<f64>, f64) {
    let x = pose.rotation * Vector3::x();
    (Point2::new(pose.translation.x, pose.translation.y), x.y.atan2(x.x))
}

fn wrap(a: f64) -> f64 {
    (a + PI).rem_euclid(2.0 * PI) - PI
}

#[test]
fn trajectories_are_smooth_and_within_the_limits() {
    let limits = TrajectoryConfig::default();
    for name in ALL {
        let scenario = Scenario::by_name(name).unwrap();
        for (r, robot) in scenario.robots().iter().enumerate() {
            let h = 0.05;
            let n = (robot.duration() / h) as usize;
            let states: Vec<(Point2<f64>, f64)> = (0..=n).map(|i| planar(&robot.pose(i as f64 * h))).collect();
            let cruise = if name == "campus" { 2.0 } else { 1.5 };
            // Starting and stopping at rest: the ramps take cruise / max_accel each.
            let ramp = cruise / limits.max_accel + 0.5;
            for i in 1..n {
                let t = i as f64 * h;
                let (prev, cur, next) = (states[i - 1], states[i], states[i + 1]);
                let speed = (next.0 - prev.0).norm() / (2.0 * h);
                let accel = ((next.0 - cur.0) - (cur.0 - prev.0)).norm() / (h * h);
                let yaw_rate = wrap(next.1 - prev.1) / (2.0 * h);
                let at = format!("{name} robot {r} at t = {t:.2} s");
                // 2 % for the sensor mast tilting with the slope on the campus hills.
                assert!(speed <= 1.02 * cruise, "{at}: speed {speed}");
                if t > ramp && t < robot.duration() - ramp {
                    assert!(speed >= 0.5, "{at}: speed {speed}");
                }
                let total = (limits.max_accel.powi(2) + limits.max_lateral_accel.powi(2)).sqrt();
                assert!(accel <= 1.1 * total, "{at}: acceleration {accel}");
                assert!(yaw_rate.abs() <= 1.05 * limits.max_yaw_rate, "{at}: yaw rate {yaw_rate}");
            }
        }
    }
}

#[test]
fn waypoints_and_paths_keep_clear_of_every_obstacle() {
    let clearance = 0.35;
    for name in ALL {
        let scenario = Scenario::by_name(name).unwrap();
        let world = scenario.world();
        for (r, robot) in scenario.robots().iter().enumerate() {
            let mount = robot.pose(0.0).translation.z
                - world.terrain().height(robot.pose(0.0).translation.x, robot.pose(0.0).translation.y);
            let ground = |p: Point2<f64>| Point3::new(p.x, p.y, world.terrain().height(p.x, p.y));
            let points = robot.waypoints().iter().map(|&p| ground(p)).chain(robot.ground_samples(0.2));
            for p in points {
                for up in [0.15, 0.5, mount] {
                    let q = p + Vector3::new(0.0, 0.0, up);
                    assert!(
                        world.is_free(&q, clearance),
                        "{name} robot {r}: {q} is within {clearance} m of an obstacle"
                    );
                }
            }
        }
    }
}

#[test]
fn warehouse_small_robot_0_loops_and_robot_1_does_not() {
    let s = Scenario::by_name("warehouse-small").unwrap();
    let gap = |r: &Trajectory| (r.pose(r.duration()).translation.vector - r.pose(0.0).translation.vector).norm();
    assert!(gap(&s.robots()[0]) < 1.0);
    assert!(gap(&s.robots()[1]) > 10.0);
    assert!(s.robots()[0].length() >= 200.0, "odometry benchmark length {}", s.robots()[0].length());
    assert!(s.frames() as f64 / 10.0 >= s.robots()[0].duration());
}

/// World-frame voxels (of `voxel` metres) scanned by robot `robot` every `every` frames, with a
/// coarse sensor (0.8° azimuth) to keep the test quick.
fn scanned_voxels(scenario: &Scenario, robot: usize, every: usize, voxel: f64) -> HashSet<[i64; 3]> {
    let sensor = SensorModel { columns: 450, ..SensorModel::vlp16() };
    let sim = Simulator::new(scenario.clone(), robot, SimConfig { sensor, ..SimConfig::default() }).unwrap();
    let mut voxels = HashSet::new();
    for frame in (0..sim.frames()).step_by(every) {
        let scan = sim.scan(frame);
        for (p, t) in timed_points(&scan.cloud) {
            let p = sim.pose_at(scan.stamp + t) * p;
            voxels.insert([p.x, p.y, p.z].map(|c| (c / voxel).floor() as i64));
        }
    }
    voxels
}

/// Overlap of robots 0 and 1: shared voxels of their scanned maps over all voxels (IoU), and the
/// fraction of robot 1's path within 3 m of robot 0's (shared places).
fn overlap(name: &str) -> (f64, f64) {
    let s = Scenario::by_name(name).unwrap();
    let (a, b) = (scanned_voxels(&s, 0, 25, 1.0), scanned_voxels(&s, 1, 25, 1.0));
    let iou = a.intersection(&b).count() as f64 / a.union(&b).count() as f64;
    let (pa, pb) = (s.robots()[0].ground_samples(1.0), s.robots()[1].ground_samples(1.0));
    let shared = pb.iter().filter(|p| pa.iter().any(|q| (*p - q).norm() < 3.0)).count();
    (iou, shared as f64 / pb.len() as f64)
}

#[test]
fn warehouse_large_overlaps_much_more_than_warehouse_small() {
    let (small, large) = (overlap("warehouse-small"), overlap("warehouse-large"));
    eprintln!("overlap (voxel IoU, shared path): warehouse-small {small:.2?}, warehouse-large {large:.2?}");
    // Line of sight through the door shares part of the small map; the paths barely meet.
    assert!(small.0 < 0.55 && large.0 > 0.85, "voxel IoU small {} large {}", small.0, large.0);
    assert!(small.1 > 0.0 && small.1 < 0.15, "shared path small {}", small.1);
    assert!(large.1 > 0.8, "shared path large {}", large.1);
}

#[test]
fn aisles_robots_scan_disjoint_places() {
    let s = Scenario::by_name("aisles").unwrap();
    let (a, b) = (scanned_voxels(&s, 0, 20, 0.5), scanned_voxels(&s, 1, 20, 0.5));
    assert!(a.len() > 1000 && b.len() > 1000);
    assert_eq!(a.intersection(&b).count(), 0, "the halls share scanned voxels");
    // Hall A ends at y = 20.8, hall B starts at y = 23: a 2.2 m wall between the point sets.
    assert!(a.iter().all(|v| v[1] as f64 * 0.5 < 21.0));
    assert!(b.iter().all(|v| (v[1] + 1) as f64 * 0.5 > 22.9));
}

#[test]
fn aisles_look_the_same_locally() {
    // Mid-aisle in hall A and in hall B, same heading: the scans match point for point.
    let s = Scenario::by_name("aisles").unwrap();
    let config = SimConfig { range_noise: 0.0, dropout: 0.0, ..SimConfig::default() };
    let sim = Simulator::new(s, 0, config).unwrap();
    let world = sim.scenario().world();
    let sensor = &sim.config().sensor;
    let cast_from = |x: f64, y: f64| -> Vec<Option<f64>> {
        (0..sensor.columns)
            .step_by(5)
            .flat_map(|c| (0..sensor.beams()).map(move |b| (c, b)))
            .map(|(c, b)| {
                let ray = Ray::new(Point3::new(x, y, 0.7), sensor.direction(b, c));
                world.cast(&ray, 6.0).map(|h| h.hit.t)
            })
            .collect()
    };
    // Aisle between the first two rows of each hall, 2 bays in: within 6 m only racks are seen.
    let (a, b) = (cast_from(9.6, 7.5), cast_from(9.6, 30.5));
    let same = a.iter().zip(&b).filter(|(p, q)| match (p, q) {
        (Some(p), Some(q)) => (p - q).abs() < 1e-9,
        (None, None) => true,
        _ => false,
    });
    assert_eq!(same.count(), a.len());
}

#[test]
fn unknown_names_are_reported_with_the_choices() {
    let err = Scenario::by_name("garage").unwrap_err().to_string();
    for name in ALL {
        assert!(err.contains(name), "{err}");
    }
    let s = Scenario::by_name("aisles").unwrap();
    let err = Simulator::new(s, 2, SimConfig::default()).unwrap_err().to_string();
    assert!(err.contains("2 robots"), "{err}");
}
