//! Global registration without an initial guess against ground truth: real KITTI scans (a reverse
//! revisit, two scans 11 m apart, a scan onto a map of other scans), a scan turned by a large yaw
//! onto itself, the next placement after one excluded (a place that appears twice), and bad input.

use cloud::PointCloud;
use cloud::formats::read_cloud;
use cloud::global::{
    Around, FeatureError, Features, GlobalAlignment, GlobalConfig, GlobalError, Role, align, estimate,
    estimate_excluding,
};
use cloud::se3::{from_matrix, pose_error};
use cloud::trajectory::Trajectory;
use cloud::voxel::downsample;
use nalgebra::{Isometry3, Matrix4, Point3};
use testkit::{assert_pose_close, pose_from_yaw_deg, shared_data};

/// What a scan registration must reach: the KITTI references are good to about a decimetre, and
/// the polish on 1 m voxels leaves one or two more.
const MAX_TRANSLATION_M: f64 = 0.3;
const MAX_ROTATION_DEG: f64 = 2.0;

fn scan(relative: &str) -> PointCloud {
    read_cloud(&shared_data(relative)).unwrap().cloud
}

/// Scan `i` of the kitti00 snippet.
fn kitti00(i: usize) -> PointCloud {
    scan(&format!("kitti00/velodyne/{i:06}.bin"))
}

/// The kitti00 reference poses (velodyne frame, the first one the identity).
fn kitti00_poses() -> Vec<Isometry3<f64>> {
    let text = std::fs::read_to_string(shared_data("kitti00/poses_velodyne.txt")).unwrap();
    Trajectory::parse_kitti(&text).unwrap().poses
}

/// The points of `cloud` mapped by `pose`.
fn moved(cloud: &PointCloud, pose: &Isometry3<f64>) -> PointCloud {
    let pose = pose.cast::<f32>();
    PointCloud::from_points(cloud.points.iter().map(|p| pose * p).collect())
}

/// Aligns with the scan defaults, prints the figures, and checks the transform against `truth`.
fn check(name: &str, source: &PointCloud, target: &PointCloud, truth: &Isometry3<f64>) -> GlobalAlignment {
    let found = align(source, target, &GlobalConfig::default()).unwrap();
    println!("{name}: {:?}\n  {found:?}", pose_error(&found.transform, truth));
    assert_pose_close!(&found.transform, truth, MAX_TRANSLATION_M, MAX_ROTATION_DEG, "{name}");
    // A right answer puts most of the overlapping scan on the target, with tens of inliers.
    assert!(found.inliers >= 15 && found.fitness > 0.5, "{name}: {found:?}");
    found
}

#[test]
fn kitti08_reverse_revisit_without_initial_guess() {
    let dir = shared_data("kitti08_revisit");
    let text = std::fs::read_to_string(dir.join("T_000720_001500.txt")).unwrap();
    let values: Vec<f64> = text.split_whitespace().map(|v| v.parse().unwrap()).collect();
    let truth = from_matrix(&Matrix4::from_row_slice(&values)).unwrap();
    // The same street driven the opposite way, 780 frames later: a turn of 148.5 deg.
    check("kitti08 1500 -> 720", &scan("kitti08_revisit/001500.bin"), &scan("kitti08_revisit/000720.bin"), &truth);
}

#[test]
fn kitti00_scans_11_m_apart_both_ways() {
    let poses = kitti00_poses();
    let (first, last) = (kitti00(0), kitti00(15));
    check("kitti00 15 -> 0", &last, &first, &(poses[0].inverse() * poses[15]));
    check("kitti00 0 -> 15", &first, &last, &(poses[15].inverse() * poses[0]));
}

#[test]
fn kitti00_scan_onto_a_local_map_of_other_scans() {
    // The re-localisation case: a map of scans 0, 3, ..., 12 in the frame of scan 0, and scan 15,
    // which the map does not hold.
    let poses = kitti00_poses();
    let mut points: Vec<Point3<f32>> = Vec::new();
    for i in (0..15).step_by(3) {
        points.extend(moved(&kitti00(i), &(poses[0].inverse() * poses[i])).points);
    }
    let map = downsample(&PointCloud::from_points(points), 0.2).unwrap();
    check("kitti00 15 -> map", &kitti00(15), &map, &(poses[0].inverse() * poses[15]));
}

#[test]
fn a_scan_turned_by_a_large_yaw_onto_itself() {
    let target = kitti00(0);
    // Translations off the voxel grid, so that the two downsamplings differ as in real scans.
    for (yaw, t) in [(90.0, [5.37, -3.11, 0.23]), (120.0, [20.13, 9.77, -0.31]), (165.0, [-12.29, 4.61, 0.07])] {
        let pose = pose_from_yaw_deg(yaw, t);
        let found = check(&format!("yaw {yaw}"), &moved(&target, &pose), &target, &pose.inverse());
        assert_pose_close!(&found.transform, &pose.inverse(), 0.05, 0.1, "yaw {yaw}: the same scan fits closely");
    }
}

#[test]
fn repeats_exactly_whatever_the_thread_count() {
    let (source, target) = (scan("kitti08_revisit/001500.bin"), scan("kitti08_revisit/000720.bin"));
    let config = GlobalConfig::default();
    let here = align(&source, &target, &config).unwrap();
    let one_thread = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    assert_eq!(one_thread.install(|| align(&source, &target, &config)).unwrap(), here);
    assert_eq!(align(&source, &target, &config).unwrap(), here);
}

/// True when `e` says that too few points of the `role` cloud survived `stage`.
fn too_few(e: &GlobalError, role: Role, stage: &str) -> bool {
    matches!(e, GlobalError::Features { role: r, error: FeatureError::TooFewPoints { stage: s, .. } }
        if *r == role && *s == stage)
}

#[test]
fn bad_input_is_an_error_naming_the_problem() {
    let good = kitti00(0);
    let config = GlobalConfig::default();
    let empty = PointCloud::default();
    assert_eq!(align(&empty, &good, &config), Err(GlobalError::Empty(Role::Source)));
    assert_eq!(align(&good, &empty, &config), Err(GlobalError::Empty(Role::Target)));

    let nan = PointCloud::from_points(vec![Point3::new(f32::NAN, 0.0, 1.0); 500]);
    let err = align(&nan, &good, &config).unwrap_err();
    assert!(too_few(&err, Role::Source, "dropping non-finite points"), "{err}");
    assert!(err.to_string().contains("non-finite"), "{err}");
    // Ten thousand copies of one point are one voxel.
    let one_spot = PointCloud::from_points(vec![Point3::new(1.0, 2.0, 3.0); 10_000]);
    let err = align(&good, &one_spot, &config).unwrap_err();
    assert!(too_few(&err, Role::Target, "voxel downsampling"), "{err}");
    // A line has points but no plane to fit a normal to.
    let line = PointCloud::from_points((0..5000).map(|i| Point3::new(i as f32 * 0.1, 0.0, 0.0)).collect());
    let err = align(&line, &good, &config).unwrap_err();
    assert!(too_few(&err, Role::Source, "normal estimation"), "{err}");

    let mut invalid = config;
    invalid.preprocess.voxel_size = f32::NAN;
    assert!(matches!(align(&good, &good, &invalid), Err(GlobalError::Config(FeatureError::InvalidConfig(_)))));
}

#[test]
fn features_keep_no_neighbourhood_lists() {
    // The lists serve the feature steps only; a map's features are kept for a whole run.
    let features = cloud::global::Features::compute(&kitti00(0), &GlobalConfig::default()).unwrap();
    assert!(!features.surfels.neighbourhoods.is_held());
    let reach = features.surfels.neighbourhoods.reach();
    assert!(features.surfels.neighbours(0, reach, usize::MAX).is_empty());
    // What the later steps use is all there.
    assert_eq!(features.surfels.points.len(), features.surfels.normals.len());
    assert_eq!(features.surfels.tree.len(), features.surfels.points.len());
}

/// A scan moved by `pose` (the source) and a target holding the scan twice, as it is and moved
/// by the returned copy pose, 200 m away: the features of both.
fn one_place_twice(pose: &Isometry3<f64>) -> (Isometry3<f64>, Features, Features) {
    let scan = kitti00(0);
    let copy = pose_from_yaw_deg(0.0, [200.0, 0.0, 0.0]);
    let mut target = scan.clone();
    target.points.extend(moved(&scan, &copy).points);
    let config = GlobalConfig::default();
    let features = |cloud: &PointCloud| Features::compute(cloud, &config).unwrap();
    (copy, features(&moved(&scan, pose)), features(&target))
}

#[test]
fn excluding_a_placement_finds_the_other_copy_of_a_place() {
    // The target holds the same scan twice, 200 m apart: two equally good placements of the
    // source. The first estimate picks one; excluding it, the next picks the other.
    let pose = pose_from_yaw_deg(90.0, [5.37, -3.11, 0.23]);
    let (copy, s, t) = one_place_twice(&pose);
    let config = GlobalConfig::default();
    let placements = [pose.inverse(), copy * pose.inverse()];
    let close = |found: &Isometry3<f64>| {
        placements.iter().position(|p| {
            let e = pose_error(found, p);
            e.translation_m < MAX_TRANSLATION_M && e.rotation_deg < MAX_ROTATION_DEG
        })
    };
    let first = estimate(&s, &t, &config).unwrap();
    let which = close(&first.transform).expect("the first estimate is one of the copies");
    let margin = 3.0 * config.ransac.inlier_distance;
    let next = estimate_excluding(&s, &t, &config, &[first.transform], margin, None).unwrap();
    assert_eq!(close(&next.transform), Some(1 - which), "{:?}", next.transform);
    assert!(next.inliers.len() >= 15, "{} inliers", next.inliers.len());
    assert_eq!(next.matches, first.matches, "every correspondence still counts");
    // Excluding both copies leaves nothing consistent to find.
    let rest = estimate_excluding(&s, &t, &config, &[first.transform, next.transform], margin, None);
    assert!(rest.is_err() || rest.as_ref().unwrap().inliers.len() < 15, "{:?}", rest.map(|r| r.inliers.len()));
}

#[test]
fn around_a_shared_place_the_estimate_finds_the_copy_there() {
    // The target holds the same scan twice, 200 m apart; told where the source's place lies in the
    // target (each copy's sensor position in turn), the estimate finds that copy, from the
    // correspondences near both places only.
    let pose = pose_from_yaw_deg(-60.0, [-4.2, 7.9, 0.1]);
    let (copy, s, t) = one_place_twice(&pose);
    let config = GlobalConfig::default();
    let sensor = Point3::from(pose.translation.vector.cast::<f32>());
    let all = estimate(&s, &t, &config).unwrap().matches.len();
    for placement in [Isometry3::identity(), copy] {
        let place = Point3::from(placement.translation.vector.cast::<f32>());
        let around = Around { source: sensor, target: place, radius: 80.0 };
        let found = estimate_excluding(&s, &t, &config, &[], 0.0, Some(&around)).unwrap();
        let truth = placement * pose.inverse();
        assert_pose_close!(&found.transform, &truth, MAX_TRANSLATION_M, MAX_ROTATION_DEG, "around {place}");
        assert!(found.inliers.len() >= 15, "{} inliers", found.inliers.len());
        // Only correspondences near both places count, so about half of the whole cloud's.
        assert!(found.matches.len() < all, "{} of {all}", found.matches.len());
        for c in &found.matches {
            assert!((s.keypoint(c.source) - sensor).norm() <= 80.0);
            assert!((t.keypoint(c.target) - place).norm() <= 80.0);
        }
    }
    // A place neither cloud has anything at: no correspondence, no model.
    let nowhere = Around { source: Point3::new(0.0, 0.0, 500.0), target: Point3::new(0.0, 0.0, 500.0), radius: 80.0 };
    assert_eq!(
        estimate_excluding(&s, &t, &config, &[], 0.0, Some(&nowhere)).map(|e| e.matches.len()),
        Err(cloud::global::NoModel { correspondences: 0 })
    );
}
