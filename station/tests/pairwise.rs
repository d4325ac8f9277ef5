//! Pairwise global registration against ground truth: a real KITTI reverse revisit, synthetic maps
//! moved by a large known transform, unrelated maps, degenerate input, and the invariances of the
//! features.

use cloud::PointCloud;
use cloud::formats::read_transform;
use cloud::global::fpfh::fpfh_at;
use cloud::global::harris::detect_keypoints;
use cloud::global::normals::{Surfels, estimate_normals};
use cloud::global::{HarrisConfig, NormalConfig, Orientation};
use cloud::se3::pose_error;
use nalgebra::{Isometry3, Point3, Rotation3, Vector3};
use station::pairwise::{PairwiseConfig, PairwiseError, PairwiseOutcome, register};

use testkit::{Rng, assert_pose_close, pose_from_yaw_deg, shared_data};

/// Inside the shared data folder.
const KITTI: &str = "kitti08_revisit";

/// Random points on the axis-aligned rectangle spanned by `corner`, `corner + a`, `corner + b`.
fn rectangle(
    rng: &mut Rng,
    corner: Vector3<f32>,
    a: Vector3<f32>,
    b: Vector3<f32>,
    per_m2: f32,
    out: &mut Vec<Point3<f32>>,
) {
    let n = (a.cross(&b).norm() * per_m2) as usize;
    for _ in 0..n {
        let noise = Vector3::new(rng.f32() - 0.5, rng.f32() - 0.5, rng.f32() - 0.5) * 0.02;
        out.push(Point3::from(corner + a * rng.f32() + b * rng.f32() + noise));
    }
}

/// The five visible faces of a box standing on the ground.
fn boxed(rng: &mut Rng, min: Vector3<f32>, size: Vector3<f32>, per_m2: f32, out: &mut Vec<Point3<f32>>) {
    let (x, y, z) = (Vector3::x() * size.x, Vector3::y() * size.y, Vector3::z() * size.z);
    rectangle(rng, min, x, z, per_m2, out);
    rectangle(rng, min + y, x, z, per_m2, out);
    rectangle(rng, min, y, z, per_m2, out);
    rectangle(rng, min + x, y, z, per_m2, out);
    rectangle(rng, min + z, x, y, per_m2, out);
}

/// A vertical pole of radius `r` and height `h` at `(x, y)`.
fn pole(rng: &mut Rng, x: f32, y: f32, r: f32, h: f32, per_m2: f32, out: &mut Vec<Point3<f32>>) {
    let n = (std::f32::consts::TAU * r * h * per_m2) as usize;
    for _ in 0..n {
        let a = rng.uniform_f32(0.0, std::f32::consts::TAU);
        out.push(Point3::new(x + r * a.cos(), y + r * a.sin(), rng.uniform_f32(0.0, h)));
    }
}

/// A street 100 m long: ground, irregular buildings on both sides, parked cars, poles.
fn street(seed: u64) -> Vec<Point3<f32>> {
    let mut rng = Rng::xorshift64_star(Rng::spread(seed));
    let density = 25.0;
    let mut pts = Vec::new();
    rectangle(&mut rng, Vector3::new(0.0, -12.0, 0.0), Vector3::x() * 100.0, Vector3::y() * 24.0, density, &mut pts);
    for side in [-1.0f32, 1.0] {
        let mut x = rng.uniform_f32(0.0, 4.0);
        while x < 96.0 {
            let w = rng.uniform_f32(5.0, 14.0).min(100.0 - x);
            let depth = rng.uniform_f32(4.0, 8.0);
            let setback = rng.uniform_f32(0.0, 2.5);
            let h = rng.uniform_f32(3.0, 12.0);
            let y0 = if side > 0.0 { 7.0 + setback } else { -7.0 - setback - depth };
            boxed(&mut rng, Vector3::new(x, y0, 0.0), Vector3::new(w, depth, h), density, &mut pts);
            x += w + rng.uniform_f32(1.0, 5.0);
        }
    }
    for _ in 0..14 {
        let (x, y) = (
            rng.uniform_f32(2.0, 95.0),
            if rng.f32() < 0.5 { rng.uniform_f32(-5.5, -4.0) } else { rng.uniform_f32(2.5, 4.0) },
        );
        let size = Vector3::new(rng.uniform_f32(3.8, 4.8), 1.8, rng.uniform_f32(1.3, 1.9));
        boxed(&mut rng, Vector3::new(x, y, 0.0), size, density, &mut pts);
    }
    for _ in 0..20 {
        let (x, y) = (rng.uniform_f32(1.0, 99.0), if rng.f32() < 0.5 { -6.2 } else { 6.2 });
        let h = rng.uniform_f32(3.0, 7.0);
        pole(&mut rng, x, y, 0.15, h, density * 2.0, &mut pts);
    }
    pts
}

/// `points` with `world` mapped into a frame whose pose in the world is `frame`.
fn in_frame(points: &[Point3<f32>], frame: &Isometry3<f64>) -> PointCloud {
    let inv = frame.inverse().cast::<f32>();
    PointCloud::from_points(points.iter().map(|p| inv * p).collect())
}

fn summary(outcome: &PairwiseOutcome) -> String {
    match outcome.best() {
        Some(r) => format!(
            "aligned {}, keypoints {}/{}, corr {}, inliers {} ({:.3}), conf {:?}, {:.1} ms",
            outcome.aligned().is_some(),
            r.keypoints.0.len(),
            r.keypoints.1.len(),
            r.correspondences,
            r.inliers.len(),
            r.inlier_ratio,
            r.confidence,
            r.timing.total.as_secs_f64() * 1e3
        ),
        None => format!("{outcome:?}"),
    }
}

#[test]
fn kitti_reverse_revisit_without_initial_guess() {
    let read = |name: &str| cloud::formats::read_cloud(&shared_data(KITTI).join(name)).unwrap().cloud;
    let (source, target) = (read("001500.bin"), read("000720.bin"));
    let truth = read_transform(&shared_data(KITTI).join("T_000720_001500.txt")).unwrap();
    let outcome = register(&source, &target, &PairwiseConfig::outdoor()).unwrap();
    let result = outcome.aligned().expect("the revisit must align");
    assert_pose_close!(&result.transform, &truth, 0.2, 1.0);
}

#[test]
fn synthetic_halves_moved_far_apart_are_recovered() {
    let world = street(1);
    let target: Vec<Point3<f32>> = world.iter().copied().filter(|p| p.x > 35.0).collect();
    let source_world: Vec<Point3<f32>> = world.iter().copied().filter(|p| p.x < 65.0).collect();
    // The source map's frame sits 20 m away, turned by 90°: the truth maps source into target.
    let truth = pose_from_yaw_deg(90.0, [20.0, -7.0, 0.3]);
    let source = in_frame(&source_world, &truth);
    let outcome = register(&source, &PointCloud::from_points(target), &PairwiseConfig::outdoor()).unwrap();
    println!("{}", summary(&outcome));
    let result = outcome.aligned().expect("overlapping halves must align");
    let e = pose_error(&result.transform, &truth);
    println!("{e:?}, before polish {:?}", pose_error(&result.coarse_transform, &truth));
    assert_pose_close!(&result.transform, &truth, 0.05, 0.5);
}

#[test]
fn unrelated_maps_get_a_low_confidence() {
    let config = PairwiseConfig::outdoor();
    let a = street(1);
    let true_pair = register(
        &in_frame(
            &a.iter().copied().filter(|p| p.x < 65.0).collect::<Vec<_>>(),
            &pose_from_yaw_deg(90.0, [20.0, -7.0, 0.3]),
        ),
        &PointCloud::from_points(a.iter().copied().filter(|p| p.x > 35.0).collect()),
        &config,
    )
    .unwrap();
    let other = register(&PointCloud::from_points(street(2)), &PointCloud::from_points(a), &config).unwrap();
    println!("true pair: {}\nunrelated: {}", summary(&true_pair), summary(&other));
    let (good, bad) = (true_pair.best().unwrap(), other.best().expect("RANSAC always keeps a best guess here"));
    assert!(other.aligned().is_none(), "unrelated maps must not be accepted");
    assert!(bad.confidence.score < 0.5 * good.confidence.score);
    // The outdoor merge threshold sits above what a similar-looking unrelated street scores.
    assert!(bad.confidence.score < station::merge::OUTDOOR_MIN_CONFIDENCE, "{}", bad.confidence.score);
    assert!(bad.inlier_ratio < good.inlier_ratio);
}

#[test]
fn degenerate_input_is_an_error_or_not_aligned_never_a_panic() {
    let config = PairwiseConfig::outdoor();
    let good = PointCloud::from_points(street(3));
    let inputs = [
        PointCloud::default(),
        PointCloud::from_points(vec![
            Point3::new(0.0, 0.0, 0.0),
            Point3::new(1.0, 0.0, 0.0),
            Point3::new(0.0, 1.0, 0.0),
        ]),
        PointCloud::from_points(vec![Point3::new(1.0, 2.0, 3.0); 10_000]),
        PointCloud::from_points(vec![Point3::new(f32::NAN, 0.0, 0.0); 500]),
        PointCloud::from_points((0..5000).map(|i| Point3::new(i as f32 * 0.01, 0.0, 0.0)).collect()),
    ];
    for bad in &inputs {
        for (s, t) in [(bad, &good), (&good, bad), (bad, bad)] {
            match register(s, t, &config) {
                Err(PairwiseError::Source(_) | PairwiseError::Target(_)) => {}
                Ok(o) => assert!(o.aligned().is_none(), "{}", summary(&o)),
                Err(e) => panic!("unexpected {e}"),
            }
        }
    }
    // A flat plane has points and normals but nothing to lock a transform on.
    let mut rng = Rng::xorshift64_star(5);
    let mut plane = Vec::new();
    rectangle(&mut rng, Vector3::zeros(), Vector3::x() * 30.0, Vector3::y() * 30.0, 20.0, &mut plane);
    let plane = PointCloud::from_points(plane);
    match register(&plane, &plane, &config) {
        Ok(o) => println!("plane: {}", summary(&o)),
        Err(e) => println!("plane: {e}"),
    }
    let mut invalid = config;
    invalid.global.preprocess.voxel_size = f32::NAN;
    assert!(matches!(register(&good, &good, &invalid), Err(PairwiseError::Config(_))));
}

/// Surfels of `points` rotated by `r`, with normals rotated the same way.
fn rotated(s: &Surfels, r: &Rotation3<f32>) -> Surfels {
    let points: Vec<Point3<f32>> = s.points.iter().map(|p| r * p).collect();
    Surfels::new(points, s.normals.iter().map(|n| r * n).collect(), s.neighbourhoods.reach())
}

#[test]
fn fpfh_is_invariant_to_rotation() {
    let config = PairwiseConfig::outdoor().global;
    let cloud = PointCloud::from_points(street(4).into_iter().filter(|p| p.x < 40.0).collect());
    let down = cloud::voxel::downsample(&cloud, 0.4).unwrap();
    let surfels = estimate_normals(&down, &config.normals, config.reach()).unwrap();
    let keypoints: Vec<usize> = (0..surfels.len()).step_by(17).collect();
    let r = Rotation3::from_euler_angles(0.7, -1.2, 2.5);
    let a = fpfh_at(&surfels, &keypoints, &config.descriptors);
    let b = fpfh_at(&rotated(&surfels, &r), &keypoints, &config.descriptors);
    let mut worst = 0.0f32;
    for (da, db) in a.iter().zip(&b) {
        let (Some(da), Some(db)) = (da, db) else {
            assert_eq!(da.is_some(), db.is_some());
            continue;
        };
        let diff: f32 = da.iter().zip(db).map(|(x, y)| (x - y).abs()).sum();
        let total: f32 = da.iter().sum();
        worst = worst.max(diff / total);
    }
    // Only angles landing within float rounding of a bin edge may move: far below 1% of the mass.
    assert!(worst < 0.01, "worst relative L1 difference {worst}");
    // Through the whole pipeline (normals re-estimated and re-oriented) a yaw keeps them too.
    let yaw = Rotation3::from_euler_angles(0.0, 0.0, 1.1);
    let turned = PointCloud::from_points(down.points.iter().map(|p| yaw * p).collect());
    let s2 = estimate_normals(&turned, &config.normals, config.reach()).unwrap();
    assert_eq!(s2.len(), surfels.len());
    let c = fpfh_at(&s2, &keypoints, &config.descriptors);
    let close = a.iter().zip(&c).filter(|(x, y)| match (x, y) {
        (Some(x), Some(y)) => x.iter().zip(y.iter()).map(|(p, q)| (p - q).abs()).sum::<f32>() < 1.0,
        _ => false,
    });
    assert!(close.count() as f64 > 0.95 * keypoints.len() as f64);
}

#[test]
fn harris_keypoints_of_a_cube_are_its_corners() {
    let mut rng = Rng::xorshift64_star(9);
    let mut pts = Vec::new();
    let e = 2.0;
    for (corner, a, b) in [
        (Vector3::zeros(), Vector3::x(), Vector3::y()),
        (Vector3::z(), Vector3::x(), Vector3::y()),
        (Vector3::zeros(), Vector3::x(), Vector3::z()),
        (Vector3::y(), Vector3::x(), Vector3::z()),
        (Vector3::zeros(), Vector3::y(), Vector3::z()),
        (Vector3::x(), Vector3::y(), Vector3::z()),
    ] {
        rectangle(&mut rng, corner * e, a * e, b * e, 2500.0, &mut pts);
    }
    let cloud = cloud::voxel::downsample(&PointCloud::from_points(pts), 0.05).unwrap();
    let normals = NormalConfig {
        radius: 0.1,
        orientation: Orientation::Viewpoint(Point3::new(1.0, 1.0, 1.0)),
        ..NormalConfig::default()
    };
    let surfels = estimate_normals(&cloud, &normals, 0.4).unwrap();
    let harris = HarrisConfig { radius: 0.2, nms_radius: 0.4, min_keypoints: 8, ..HarrisConfig::default() };
    let keypoints = detect_keypoints(&surfels, &harris);
    assert_eq!(keypoints.len(), 8, "{:?}", keypoints.iter().map(|&i| surfels.points[i]).collect::<Vec<_>>());
    for &k in &keypoints {
        let p = surfels.points[k];
        let corner = p.map(|c| if c < e / 2.0 { 0.0 } else { e });
        assert!((p - corner).norm() < 0.15, "{p} far from {corner}");
    }
}
