//! GICP/VGICP against ground truth: a real LiDAR pair with a reference pose, and seeded synthetic scenes.

use cloud::PointCloud;
use cloud::formats::read_cloud;
use cloud::registration::{
    GaussianCloud, GaussianVoxelMap, GicpFactor, Method, RegistrationConfig, RegistrationError, align, linear_system,
    register,
};
use cloud::se3::from_matrix;
use cloud::voxel::downsample;
use nalgebra::{Isometry3, Matrix4, Point3, Vector3};
use testkit::{Rng, assert_pose_close, pose_from_axis_angle as pose};

/// `n` random points on a room (floor, ceiling, four walls) with three boxes inside: planes in
/// every direction, so all six degrees of freedom are observable.
fn structured_scene(rng: &mut Rng, n: usize) -> Vec<Vector3<f64>> {
    // Axis-aligned boxes as (min, max); the first is the room, whose inside faces are sampled.
    let boxes = [
        ([-10.0, -7.0, 0.0], [12.0, 8.0, 4.0]),
        ([1.0, 1.0, 0.0], [3.0, 2.5, 1.5]),
        ([-5.0, -4.0, 0.0], [-3.5, -1.0, 2.5]),
        ([4.0, -5.0, 0.0], [7.0, -4.0, 0.8]),
    ];
    (0..n)
        .map(|_| {
            let (lo, hi) = boxes[(rng.f64() * boxes.len() as f64) as usize];
            let face = (rng.f64() * 6.0) as usize;
            let axis = face / 2;
            let mut p = Vector3::new(rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]), rng.uniform(lo[2], hi[2]));
            p[axis] = if face.is_multiple_of(2) { lo[axis] } else { hi[axis] };
            p
        })
        .collect()
}

/// A cloud of `points` mapped by `pose`, with Gaussian noise of `sigma` metres per axis.
fn to_cloud(points: &[Vector3<f64>], pose: &Isometry3<f64>, rng: &mut Rng, sigma: f64) -> PointCloud {
    PointCloud::from_points(
        points
            .iter()
            .map(|p| {
                let q = pose * Point3::from(*p);
                Point3::new(
                    (q.x + rng.gaussian(sigma)) as f32,
                    (q.y + rng.gaussian(sigma)) as f32,
                    (q.z + rng.gaussian(sigma)) as f32,
                )
            })
            .collect(),
    )
}

/// Two independent samplings of the scene: target in the world frame, source in a frame moved by
/// `truth` (`T_target_source`), both with 5 mm noise.
fn synthetic_pair(truth: &Isometry3<f64>, seed: u64) -> (PointCloud, PointCloud) {
    let mut rng = Rng::new(seed);
    let target = structured_scene(&mut rng, 20_000);
    let source = structured_scene(&mut rng, 20_000);
    let target = to_cloud(&target, &Isometry3::identity(), &mut rng, 0.005);
    let source = to_cloud(&source, &truth.inverse(), &mut rng, 0.005);
    let down = |c: &PointCloud| downsample(c, 0.2).unwrap();
    (down(&source), down(&target))
}

/// The gicp_pair clouds downsampled to 0.25 m (as small_gicp's examples) and the reference pose.
fn real_pair() -> (PointCloud, PointCloud, Isometry3<f64>) {
    let dir = testkit::shared_data("gicp_pair");
    let read = |name: &str| read_cloud(&dir.join(name)).unwrap().cloud;
    let down = |c: PointCloud| downsample(&c, 0.25).unwrap();
    let text = std::fs::read_to_string(dir.join("T_target_source.txt")).unwrap();
    let values: Vec<f64> = text.split_whitespace().map(|v| v.parse().unwrap()).collect();
    let reference = from_matrix(&Matrix4::from_row_slice(&values)).unwrap();
    (down(read("source.ply")), down(read("target.ply")), reference)
}

/// Allowed error on the real pair. The reference pose is itself only good to a few tenths of a
/// degree: small_gicp 1.0.1 (Python) with 20 neighbours lands 0.88 cm / 0.68° from it with GICP and
/// 1.76 cm / 0.32° with VGICP (its own tests allow 0.2 m / 2.5°). We agree with small_gicp to
/// < 0.1 cm / 0.01° at equal settings; these bounds hold the methods at that level.
const REAL_MAX_M: f64 = 0.02;
const REAL_MAX_DEG: f64 = 0.75;

#[test]
fn real_pair_from_identity_all_methods() {
    let (source, target, reference) = real_pair();
    let config = RegistrationConfig::default();
    // Point-to-plane ignores the source covariances and lands a little farther (as in small_gicp).
    for (method, max_m) in [(Method::Gicp, REAL_MAX_M), (Method::Vgicp, REAL_MAX_M), (Method::PointToPlane, 0.03)] {
        let r = align(&source, &target, &Isometry3::identity(), method, &config).unwrap();
        assert!(r.converged, "{method:?} did not converge: {r:?}");
        assert!(r.inliers > source.len() / 2, "{method:?}: {} inliers of {}", r.inliers, source.len());
        // Mean squared distance to the matched Gaussians: points for GICP, 1 m voxel means for VGICP.
        let max_fitness = if method == Method::Vgicp { 0.25 } else { 0.1 };
        assert!(r.fitness.is_finite() && r.fitness < max_fitness, "{method:?} fitness {}", r.fitness);
        assert_pose_close!(&r.transform, &reference, max_m, REAL_MAX_DEG, "{method:?}");
        // The information matrix is symmetric positive definite (all six directions observed).
        assert!((r.hessian - r.hessian.transpose()).norm() <= 1e-9 * r.hessian.norm());
        assert!(r.hessian.cholesky().is_some(), "{method:?}: hessian not positive definite");
    }
}

#[test]
fn real_pair_vgicp_single_level_and_wider_search() {
    // small_gicp's exact setting (one level, DIRECT1) and the 7-neighbour search both land.
    let (source, target, reference) = real_pair();
    let single = RegistrationConfig { coarse_levels: 0, ..RegistrationConfig::default() };
    let direct7 = RegistrationConfig { voxel_search: cloud::registration::VoxelSearch::Direct7, ..single.clone() };
    for config in [single, direct7] {
        let r = align(&source, &target, &Isometry3::identity(), Method::Vgicp, &config).unwrap();
        assert!(r.converged, "{:?}: {r:?}", config.voxel_search);
        assert_pose_close!(&r.transform, &reference, REAL_MAX_M, REAL_MAX_DEG, "VGICP {:?}", config.voxel_search);
    }
}

/// small_gicp's inverse check: registering target onto source gives the inverse of source onto
/// target. The two directions fit different correspondences (each source point to its nearest
/// target Gaussian), so they agree only as well as either agrees with the reference, whose error
/// comes from the same source: the bounds on the reference hold between the two directions too.
#[test]
fn real_pair_reverse_direction_gives_the_inverse() {
    let (source, target, _) = real_pair();
    let config = RegistrationConfig::default();
    for method in [Method::Gicp, Method::Vgicp] {
        let forward = align(&source, &target, &Isometry3::identity(), method, &config).unwrap();
        let backward = align(&target, &source, &Isometry3::identity(), method, &config).unwrap();
        assert!(forward.converged && backward.converged, "{method:?}: {forward:?} {backward:?}");
        let e = cloud::se3::pose_error(&backward.transform.inverse(), &forward.transform);
        eprintln!("{method:?}: forward vs inverted backward {:.4} m {:.4} deg", e.translation_m, e.rotation_deg);
        assert_pose_close!(
            &backward.transform.inverse(),
            &forward.transform,
            REAL_MAX_M,
            REAL_MAX_DEG,
            "{method:?} target onto source, inverted"
        );
    }
}

#[test]
fn synthetic_known_transform_is_recovered() {
    let truth = pose([0.4, -0.3, 0.1], [0.02, -0.03, 0.12]);
    let (source, target) = synthetic_pair(&truth, 0x5eed_1234_abcd_0001);
    let config = RegistrationConfig::default();
    for method in [Method::Gicp, Method::Vgicp, Method::PointToPlane] {
        let r = align(&source, &target, &Isometry3::identity(), method, &config).unwrap();
        assert!(r.converged, "{method:?}: {r:?}");
        assert_pose_close!(&r.transform, &truth, 0.005, 0.05, "synthetic {method:?}");
    }
}

#[test]
fn large_initial_error_stays_finite() {
    // 90 degrees and 6 metres off: no method may produce NaN; a wrong answer must be finite.
    let truth = pose([0.4, -0.3, 0.1], [0.02, -0.03, 0.12]);
    let (source, target) = synthetic_pair(&truth, 0x5eed_1234_abcd_0002);
    let init = pose([6.0, -4.0, 2.0], [0.3, 0.2, std::f64::consts::FRAC_PI_2]);
    let config = RegistrationConfig::default();
    for method in [Method::Gicp, Method::Vgicp, Method::PointToPlane] {
        let r = align(&source, &target, &init, method, &config).unwrap();
        assert!(r.transform.to_homogeneous().iter().all(|v| v.is_finite()), "{method:?}: {r:?}");
        assert!(r.hessian.iter().all(|v| v.is_finite()) && r.error.is_finite());
        if r.converged {
            // Claiming convergence is fine only with a sane, finite fit.
            assert!(r.inliers > 0 && r.fitness.is_finite());
        }
    }
    // Far beyond any correspondence: no inliers, reported as not converged, pose untouched.
    let far = pose([500.0, 0.0, 0.0], [0.0, 0.0, 0.0]);
    let r = align(&source, &target, &far, Method::Gicp, &config).unwrap();
    assert!(!r.converged && r.inliers == 0);
    assert_eq!(r.transform, far);
}

#[test]
fn per_thread_reduction_equals_single_thread_sum() {
    let truth = pose([0.2, 0.1, 0.0], [0.0, 0.0, 0.05]);
    let (source, target) = synthetic_pair(&truth, 0x5eed_1234_abcd_0003);
    let config = RegistrationConfig::default();
    let source = GaussianCloud::new(&source.points, config.neighbours);
    let target = GaussianCloud::new(&target.points, config.neighbours);
    let map = GaussianVoxelMap::new(&target, 1.0, Default::default());
    let at = Isometry3::identity();
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let many = rayon::ThreadPoolBuilder::new().num_threads(4).build().unwrap();
    let sys = |pool: &rayon::ThreadPool| {
        pool.install(|| {
            (
                linear_system(&source, &target, &GicpFactor, &at, 1.0),
                linear_system(&source, &map, &GicpFactor, &at, 1.0),
            )
        })
    };
    let (serial, parallel) = (sys(&one), sys(&many));
    for (a, b) in [(serial.0, parallel.0), (serial.1, parallel.1)] {
        assert!(a.inliers > 1000);
        assert_eq!(a.inliers, b.inliers);
        // Only the summation order differs.
        assert!((a.h - b.h).norm() <= 1e-10 * a.h.norm(), "{} vs {}", a.h, b.h);
        assert!((a.b - b.b).norm() <= 1e-10 * a.b.norm().max(1.0));
        assert!((a.error - b.error).abs() <= 1e-10 * a.error);
        assert!((a.sum_sq_distance - b.sum_sq_distance).abs() <= 1e-10 * a.sum_sq_distance);
    }
    // And the whole registration agrees.
    let run = |pool: &rayon::ThreadPool| pool.install(|| register(&source, &map, &GicpFactor, &at, &config).unwrap());
    let (a, b) = (run(&one), run(&many));
    assert_eq!(a.iterations, b.iterations);
    assert_pose_close!(&a.transform, &b.transform, 1e-9, 1e-7, "1 vs 4 threads");
}

#[test]
fn guard_rails_return_errors() {
    let truth = Isometry3::identity();
    let (good, _) = synthetic_pair(&truth, 7);
    let config = RegistrationConfig::default();
    let id = Isometry3::identity();
    let empty = PointCloud::default();
    let single = PointCloud::from_points(vec![Point3::new(1.0, 2.0, 3.0)]);
    let same = PointCloud::from_points(vec![Point3::new(1.0, 2.0, 3.0); 500]);
    let mut nan = good.clone();
    nan.points[10].y = f32::NAN;
    for method in [Method::Gicp, Method::Vgicp, Method::PointToPlane] {
        let run = |s: &PointCloud, t: &PointCloud| align(s, t, &id, method, &config);
        assert_eq!(run(&empty, &good), Err(RegistrationError::TooFewPoints { cloud: "source", found: 0 }));
        assert_eq!(run(&good, &empty), Err(RegistrationError::TooFewPoints { cloud: "target", found: 0 }));
        assert_eq!(run(&single, &good), Err(RegistrationError::TooFewPoints { cloud: "source", found: 1 }));
        assert_eq!(run(&good, &single), Err(RegistrationError::TooFewPoints { cloud: "target", found: 1 }));
        assert_eq!(run(&same, &good), Err(RegistrationError::Degenerate { cloud: "source" }));
        assert_eq!(run(&good, &same), Err(RegistrationError::Degenerate { cloud: "target" }));
        assert_eq!(run(&nan, &good), Err(RegistrationError::NonFinitePoint { cloud: "source", index: 10 }));
        let mut bad_init = id;
        bad_init.translation.x = f64::NAN;
        assert_eq!(align(&good, &good, &bad_init, method, &config), Err(RegistrationError::NonFiniteInitialGuess));
    }
    let bad = RegistrationConfig { voxel_resolution: 0.0, ..config.clone() };
    assert!(matches!(align(&good, &good, &id, Method::Vgicp, &bad), Err(RegistrationError::InvalidConfig(_))));
    let bad = RegistrationConfig { max_correspondence_distance: f64::NAN, ..config };
    assert!(matches!(align(&good, &good, &id, Method::Gicp, &bad), Err(RegistrationError::InvalidConfig(_))));
}
