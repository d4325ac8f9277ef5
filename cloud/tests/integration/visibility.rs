//! The free-space acceptance ([`cloud::visibility`]) on real KITTI scans at their reference
//! placements and at wrong ones: a true placement agrees with what the other sensor saw, a wrong
//! one puts surfaces where its rays passed.

use std::sync::Arc;

use cloud::PointCloud;
use cloud::formats::read_cloud;
use cloud::se3::from_matrix;
use cloud::trajectory::Trajectory;
use cloud::visibility::{Acceptance, RangeImage, View, Views, VisibilityConfig, acceptance};
use cloud::voxel::downsample;
use nalgebra::{Isometry3, Matrix4, Point3, Translation3, UnitQuaternion, Vector3};
use testkit::shared_data;

/// Keyframe voxel of the outdoor odometry preset: what an edge sends.
const KEYFRAME_VOXEL: f32 = 0.2;
/// Points judged: the outdoor merge's surfel voxel.
const SURFEL_VOXEL: f32 = 0.4;

fn scan(relative: &str) -> PointCloud {
    downsample(&read_cloud(&shared_data(relative)).unwrap().cloud, KEYFRAME_VOXEL).unwrap()
}

/// A robot's keyframes: poses in its map frame and sensor-frame scans.
struct Robot {
    keyframes: Vec<(Isometry3<f64>, PointCloud)>,
}

impl Robot {
    fn views(&self, config: &VisibilityConfig) -> Views {
        Views::new(
            self.keyframes
                .iter()
                .map(|(pose, cloud)| View {
                    pose: pose.cast(),
                    image: Arc::new(RangeImage::new(&cloud.points, config)),
                })
                .collect(),
        )
    }

    fn surfels(&self) -> Vec<Point3<f32>> {
        let mut all = PointCloud::default();
        for (pose, cloud) in &self.keyframes {
            all.extend(&cloud.transformed(&pose.cast()));
        }
        downsample(&all, SURFEL_VOXEL).unwrap().points
    }
}

/// Both ways: `b`'s surfels in `a`'s views at `t` (maps `b` into `a`), and `a`'s in `b`'s.
fn both_ways(a: &Robot, b: &Robot, t: &Isometry3<f64>, config: &VisibilityConfig) -> Acceptance {
    let t = t.cast::<f32>();
    acceptance(&b.surfels(), &t, &a.views(config), 5_000, config)
        + acceptance(&a.surfels(), &t.inverse(), &b.views(config), 5_000, config)
}

fn yaw_deg(deg: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_scaled_axis(Vector3::z() * deg.to_radians())
}

/// KITTI 08's reverse revisit: scan 1500 placed into scan 720's frame.
fn revisit() -> (Robot, Robot, Isometry3<f64>) {
    let text = std::fs::read_to_string(shared_data("kitti08_revisit/T_000720_001500.txt")).unwrap();
    let values: Vec<f64> = text.split_whitespace().map(|v| v.parse().unwrap()).collect();
    let truth = from_matrix(&Matrix4::from_row_slice(&values)).unwrap();
    let one = |name: &str| Robot { keyframes: vec![(Isometry3::identity(), scan(name))] };
    (one("kitti08_revisit/000720.bin"), one("kitti08_revisit/001500.bin"), truth)
}

/// KITTI 00's 16 frames as two robots: frames 0-7 and 8-15, each in the frame of its first.
fn kitti00_halves() -> (Robot, Robot, Isometry3<f64>) {
    let text = std::fs::read_to_string(shared_data("kitti00/poses_velodyne.txt")).unwrap();
    let poses = Trajectory::parse_kitti(&text).unwrap().poses;
    let half = |frames: std::ops::Range<usize>| {
        let origin = poses[frames.start].inverse();
        Robot {
            keyframes: frames.map(|i| (origin * poses[i], scan(&format!("kitti00/velodyne/{i:06}.bin")))).collect(),
        }
    };
    (half(0..8), half(8..16), poses[0].inverse() * poses[8])
}

/// `t` moved in the target frame: translated by `(x, y)` metres and turned by `yaw` degrees.
fn off(t: &Isometry3<f64>, x: f64, y: f64, yaw: f64) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(x, y, 0.0), yaw_deg(yaw)) * t
}

/// A true placement (and one 20 cm off it: drift) agrees with both sensors; placements 5-10 m off
/// or turned by 90-180° put surfaces where the other sensor saw through. The merge refuses edges
/// below 0.9; these bounds are the margin it relies on.
fn check(name: &str, (a, b, truth): (Robot, Robot, Isometry3<f64>)) {
    let config = VisibilityConfig::outdoor();
    for (what, t) in [("the reference", truth), ("20 cm off", off(&truth, 0.2, 0.0, 0.0))] {
        let found = both_ways(&a, &b, &t, &config);
        println!("{name}, {what}: {found:?}, ω {:.3}", found.index());
        assert!(found.index() >= 0.95 && found.agree > 2_000, "{name}: {what} placement refused");
    }
    let wrong = [
        ("10 m along x", off(&truth, 10.0, 0.0, 0.0)),
        ("5 m along y", off(&truth, 0.0, 5.0, 0.0)),
        ("turned 90°", off(&truth, 0.0, 0.0, 90.0)),
        ("turned 180°", off(&truth, 0.0, 0.0, 180.0)),
    ];
    for (what, t) in wrong {
        let found = both_ways(&a, &b, &t, &config);
        println!("{name}, {what}: {found:?}, ω {:.3}", found.index());
        assert!(found.index() < 0.8 && found.conflict > 500, "{name}: {what} placement accepted");
    }
}

#[test]
fn kitti08_reverse_revisit_agrees_at_the_reference_and_conflicts_off_it() {
    check("kitti08 1500 -> 720", revisit());
}

#[test]
fn kitti00_halves_agree_at_the_reference_and_conflict_off_it() {
    check("kitti00 8-15 -> 0-7", kitti00_halves());
}
