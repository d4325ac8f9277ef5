//! The joint pose graph against the simulator's truth: two robots drive the same campus road, each
//! keyframe a deskewed sweep taken at its true pose, their keyframe poses bent by a drift of known
//! size. Judged is the global ATE (every keyframe against the truth in the reference robot's true
//! frame) of the joint graph beside the rigid placement it started from.
//!
//! Three classes: drifts that differ (the graph should take out what one rigid transform per robot
//! cannot), drifts that agree (nothing to learn from each other: the graph must not make it
//! worse), and straight maps whose rigid placement is off (the graph should find the place).

use std::sync::Arc;

use cloud::PointCloud;
use cloud::se3::pose_error;
use cloud::trajectory::ate;
use cloud::voxel::downsample;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rayon::prelude::*;
use sim::{Scenario, SimConfig, Simulator};
use station::joint::consistency::consistent;
use station::joint::{JointConfig, JointError, RobotPath, constraints, solve};

/// Keyframe voxel, metres (the outdoor odometry preset's).
const KEYFRAME_VOXEL: f32 = 0.2;

/// Sweeps between keyframes: at the campus's 2 m/s and 10 Hz, a keyframe every metre.
const STRIDE: usize = 5;

/// Keyframes per robot: 60 m of road.
const KEYFRAMES: usize = 60;

/// A robot's keyframes: true poses in the world and sweeps in the sensor frame.
struct Drive {
    truth: Vec<Isometry3<f64>>,
    clouds: Vec<Arc<PointCloud>>,
}

/// Campus robot 0 from sweep `offset` on, a keyframe every [`STRIDE`] sweeps.
fn drive(offset: usize) -> Drive {
    let scenario = Scenario::by_name("campus").unwrap();
    let sim = Simulator::new(scenario, 0, SimConfig::default()).unwrap();
    let (truth, clouds) = (0..KEYFRAMES)
        .into_par_iter()
        .map(|k| {
            let scan = sim.scan(offset + k * STRIDE);
            (scan.ground_truth, Arc::new(downsample(&sim.deskewed(&scan), KEYFRAME_VOXEL).unwrap()))
        })
        .unzip();
    Drive { truth, clouds }
}

/// The keyframe poses an odometry would give in the robot's own frame: the true steps, each
/// turned by `yaw_deg_per_m` for every metre it travels and stretched by `scale`.
fn drifted(truth: &[Isometry3<f64>], yaw_deg_per_m: f64, scale: f64) -> Vec<Isometry3<f64>> {
    let mut poses = vec![Isometry3::identity()];
    for k in 1..truth.len() {
        let step = truth[k - 1].inverse() * truth[k];
        let length = step.translation.vector.norm();
        let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), (yaw_deg_per_m * length).to_radians());
        let stretched = Isometry3::from_parts(Translation3::from(step.translation.vector * scale), step.rotation);
        poses.push(poses[k - 1] * stretched * Isometry3::from_parts(Translation3::identity(), turn));
    }
    poses
}

/// Global ATE RMSE of both robots' keyframes, `placed[r][k]` against the truth in robot 0's true
/// first frame.
fn global_ate(drives: &[&Drive], placed: &[Vec<Isometry3<f64>>]) -> f64 {
    let frame = drives[0].truth[0].inverse();
    let truth: Vec<Isometry3<f64>> = drives.iter().flat_map(|d| d.truth.iter().map(|t| frame * t)).collect();
    let estimate: Vec<Isometry3<f64>> = placed.iter().flatten().copied().collect();
    ate(&truth, &estimate, false).unwrap().rmse
}

/// Robot paths for `drives` with odometry `poses`, robot 0 placed at the identity and the others
/// at their true first frame moved by `offset`.
fn paths(drives: &[&Drive], poses: Vec<Vec<Isometry3<f64>>>, offset: Isometry3<f64>) -> Vec<RobotPath> {
    let frame = drives[0].truth[0].inverse();
    drives
        .iter()
        .zip(poses)
        .enumerate()
        .map(|(r, (d, poses))| {
            let placement = if r == 0 { Isometry3::identity() } else { offset * frame * d.truth[0] };
            RobotPath { placement, poses, clouds: d.clouds.clone() }
        })
        .collect()
}

/// Rigid and joint global ATE of `paths`, and how many inter-robot edges were found.
fn rigid_and_joint(drives: &[&Drive], paths: &[RobotPath]) -> (f64, f64, usize) {
    let rigid: Vec<Vec<Isometry3<f64>>> =
        paths.iter().map(|p| (0..p.poses.len()).map(|k| p.placed(k)).collect()).collect();
    let solution = solve(paths, 0, &JointConfig::default()).unwrap();
    assert_eq!(solution.joined, vec![true, true], "the robots drive the same road: linked");
    assert!(solution.report.is_some_and(|r| r.final_error <= r.initial_error));
    (global_ate(drives, &rigid), global_ate(drives, &solution.poses), solution.constraints.len())
}

/// The second robot drives the first's road a few sweeps behind it (its keyframes fall between
/// the first's).
fn two_drives() -> (Drive, Drive) {
    (drive(0), drive(STRIDE / 2 + 1))
}

#[test]
fn drifts_that_differ_are_taken_out_where_the_robots_meet() {
    let (a, b) = two_drives();
    let drives = [&a, &b];
    // Each robot's odometry turns the other way by 0.01 deg/m (the default odometry deviation) and
    // one stretches by 0.5 %: about 0.3 m off at the end of 60 m, each.
    let poses = vec![drifted(&a.truth, 0.01, 1.0), drifted(&b.truth, -0.01, 1.005)];
    let (rigid, joint, edges) = rigid_and_joint(&drives, &paths(&drives, poses, Isometry3::identity()));
    println!("differing drifts: rigid {rigid:.3} m, joint {joint:.3} m, {edges} inter-robot edges");
    assert!(edges >= KEYFRAMES / 2, "{edges} inter-robot edges");
    assert!(joint < 0.5 * rigid, "joint {joint:.3} m against rigid {rigid:.3} m");
}

#[test]
fn drifts_that_agree_are_left_no_worse() {
    let (a, b) = two_drives();
    let drives = [&a, &b];
    let poses = vec![drifted(&a.truth, 0.01, 1.0), drifted(&b.truth, 0.01, 1.0)];
    let (rigid, joint, edges) = rigid_and_joint(&drives, &paths(&drives, poses, Isometry3::identity()));
    println!("agreeing drifts: rigid {rigid:.3} m, joint {joint:.3} m, {edges} inter-robot edges");
    assert!(joint <= rigid * 1.05 + 0.01, "joint {joint:.3} m against rigid {rigid:.3} m");
}

#[test]
fn a_rigid_placement_that_is_off_is_pulled_onto_the_other_map() {
    let (a, b) = two_drives();
    let drives = [&a, &b];
    let straight = |d: &Drive| drifted(&d.truth, 0.0, 1.0);
    // Off by 0.3 m and a degree of yaw: what a merge of maps that share little can leave.
    let off = Isometry3::new(Vector3::new(0.2, -0.2, 0.05), Vector3::z() * 1f64.to_radians());
    let paths = paths(&drives, vec![straight(&a), straight(&b)], off);
    let (rigid, joint, edges) = rigid_and_joint(&drives, &paths);
    println!("placement off: rigid {rigid:.3} m, joint {joint:.3} m, {edges} inter-robot edges");
    assert!(joint < 0.05, "joint {joint:.3} m against rigid {rigid:.3} m");
    let solution = solve(&paths, 0, &JointConfig::default()).unwrap();
    let frame = a.truth[0].inverse();
    let error = pose_error(&solution.poses[1][0], &(frame * b.truth[0]));
    assert!(error.translation_m < 0.05 && error.rotation_deg < 0.2, "{error:?}");
}

/// Campus robot `robot` from sweep `offset` on, a keyframe every sweep for `sweeps` sweeps, its
/// keyframe poses the truth in `frame`.
fn every_sweep(robot: usize, offset: usize, sweeps: usize, frame: &Isometry3<f64>) -> (Drive, Vec<Isometry3<f64>>) {
    let scenario = Scenario::by_name("campus").unwrap();
    let sim = Simulator::new(scenario, robot, SimConfig::default()).unwrap();
    let (truth, clouds): (Vec<_>, Vec<_>) = (0..sweeps)
        .into_par_iter()
        .map(|k| {
            let scan = sim.scan(offset + k);
            (scan.ground_truth, Arc::new(downsample(&sim.deskewed(&scan), KEYFRAME_VOXEL).unwrap()))
        })
        .unzip();
    let poses = truth.iter().map(|t| frame * t).collect();
    (Drive { truth, clouds }, poses)
}

/// Every `stride`-th keyframe of each robot, placed at the truth.
fn thinned(robots: &[(Drive, Vec<Isometry3<f64>>)], stride: usize) -> Vec<RobotPath> {
    robots
        .iter()
        .map(|(d, poses)| RobotPath {
            placement: Isometry3::identity(),
            poses: poses.iter().step_by(stride).copied().collect(),
            clouds: d.clouds.iter().step_by(stride).cloned().collect(),
        })
        .collect()
}

/// Median translation (m) and rotation (deg) error of `edges` against the truth of `paths`.
fn median_edge_error(paths: &[RobotPath], edges: &[station::joint::Constraint]) -> (f64, f64) {
    let (mut metres, mut degrees): (Vec<f64>, Vec<f64>) = edges
        .iter()
        .map(|c| {
            let truth = paths[c.target.robot].placed(c.target.keyframe).inverse()
                * paths[c.source.robot].placed(c.source.keyframe);
            let e = pose_error(&c.measurement, &truth);
            (e.translation_m, e.rotation_deg)
        })
        .unzip();
    metres.sort_by(f64::total_cmp);
    degrees.sort_by(f64::total_cmp);
    (metres[metres.len() / 2], degrees[degrees.len() / 2])
}

/// Two campus robots whose roads cross, keyframes at their true poses, keyed every sweep (10 Hz,
/// 0.2 m apart: what a robot that keys each sweep sends) and every fifth sweep (a metre apart, the
/// robots' own spacing): the inter-robot edges are as many and as good either way. Keyed every
/// sweep with the submap a fixed two keyframes either side (0.8 m of path instead of 2 m) and
/// every keyframe tried, the edges were five times as many and a third worse in rotation.
#[test]
fn edges_do_not_depend_on_how_often_a_robot_keys() {
    let sweeps = 200;
    let frame = {
        let sim = Simulator::new(Scenario::by_name("campus").unwrap(), 0, SimConfig::default()).unwrap();
        sim.ground_truth(0).inverse()
    };
    let half = {
        let sim = Simulator::new(Scenario::by_name("campus").unwrap(), 1, SimConfig::default()).unwrap();
        (sim.trajectory().duration() / sim.config().sensor.period) as usize / 2
    };
    let robots = [every_sweep(0, 0, sweeps, &frame), every_sweep(1, half, sweeps, &frame)];
    let config = JointConfig::default();
    let per_metre = thinned(&robots, STRIDE);
    let per_sweep = thinned(&robots, 1);
    let sparse = constraints::find(&per_metre, &config);
    let dense = constraints::find(&per_sweep, &config);
    let (sparse_m, sparse_deg) = median_edge_error(&per_metre, &sparse);
    let (dense_m, dense_deg) = median_edge_error(&per_sweep, &dense);
    println!(
        "keyed every metre: {} edges, median {:.1} cm / {:.2} deg; every sweep: {} edges, median {:.1} cm / {:.2} deg",
        sparse.len(),
        sparse_m * 100.0,
        sparse_deg,
        dense.len(),
        dense_m * 100.0,
        dense_deg
    );
    assert!(sparse.len() >= 10, "the roads cross: {} edges", sparse.len());
    assert!(dense.len() <= 2 * sparse.len(), "{} edges keyed every sweep against {}", dense.len(), sparse.len());
    assert!(dense_m <= sparse_m + 0.005, "every sweep {dense_m:.3} m against every metre {sparse_m:.3} m");
    assert!(dense_deg <= sparse_deg + 0.05, "every sweep {dense_deg:.2} deg against every metre {sparse_deg:.2} deg");
}

/// Six campus robots (each of the three from its start and from half its run), 300 sweeps each,
/// keyed every sweep at their true poses and placed at the truth: exact maps, so all the joint
/// graph can do is add its edges' errors. Keyframes 5-10 m apart register 0.8-3.3 cm and 0.1-0.6
/// deg off the truth, those within a metre 0.2-0.5 cm and 0.03-0.14 deg: weighed alike (3 cm /
/// 0.3 deg), the edges bent these maps by 3.1 cm; weighed by the distance between the keyframes
/// (`JointConfig::sigma_growth`), 1.8.
#[test]
fn exact_maps_keyed_every_sweep_are_bent_less_than_two_centimetres() {
    let sweeps = 300;
    let campus = || Scenario::by_name("campus").unwrap();
    let frame = Simulator::new(campus(), 0, SimConfig::default()).unwrap().ground_truth(0).inverse();
    let robots: Vec<(Drive, Vec<Isometry3<f64>>)> = (0..3)
        .flat_map(|r| {
            let sim = Simulator::new(campus(), r, SimConfig::default()).unwrap();
            let moving = (sim.trajectory().duration() / sim.config().sensor.period) as usize;
            [0, moving / 2].map(|offset| every_sweep(r, offset, sweeps, &frame))
        })
        .collect();
    let paths = thinned(&robots, 1);
    let solution = solve(&paths, 0, &JointConfig::default()).unwrap();
    let joined = solution.joined.iter().filter(|&&j| j).count();
    let truth: Vec<Isometry3<f64>> = robots.iter().flat_map(|(_, poses)| poses.iter().copied()).collect();
    let joint: Vec<Isometry3<f64>> = solution.poses.iter().flatten().copied().collect();
    let error = ate(&truth, &joint, false).unwrap().rmse;
    println!("exact maps: {} edges, {joined} robots joined, joint {:.1} cm", solution.constraints.len(), error * 100.0);
    assert!(joined >= 3, "the robots' roads meet: {:?}", solution.joined);
    assert!(error < 0.02, "the joint graph bent exact maps by {:.1} cm", error * 100.0);
}

#[test]
fn edges_that_disagree_with_the_rest_are_dropped_and_a_robot_apart_keeps_its_placement() {
    let (a, b) = two_drives();
    // A third robot on the far side of the campus loop: nowhere near the others' 60 m.
    let c = drive(600);
    let drives = [&a, &b, &c];
    let straight = |d: &Drive| drifted(&d.truth, 0.0, 1.0);
    let off = Isometry3::new(Vector3::new(0.2, -0.2, 0.05), Vector3::z() * 1f64.to_radians());
    let paths = paths(&drives, vec![straight(&a), straight(&b), straight(&c)], off);
    let config = JointConfig::default();
    let solution = solve(&paths, 0, &config).unwrap();
    assert_eq!(solution.joined, vec![true, true, false]);
    for (k, pose) in solution.poses[2].iter().enumerate() {
        assert_eq!(*pose, paths[2].placed(k), "a robot apart keeps its rigid placement");
    }
    // Forge edges that slid half a metre along the road (what a corridor does to a registration):
    // a fifth of the true ones, shifted alike, so they agree with each other but not with the rest.
    let mut edges = solution.constraints.clone();
    let slid = Isometry3::translation(0.5, 0.0, 0.0);
    let forged: Vec<_> = edges
        .iter()
        .step_by(5)
        .map(|c| {
            let mut c = c.clone();
            c.measurement = slid * c.measurement;
            c
        })
        .collect();
    let truthful = edges.len();
    edges.extend(forged.iter().cloned());
    let kept = consistent(&paths, &edges, &config);
    assert_eq!(kept.len(), truthful, "every true edge kept, every forged one dropped");
    assert!(forged.iter().all(|f| !kept.contains(f)));
}

#[test]
fn bad_input_is_refused_with_what_is_wrong() {
    let cloud = Arc::new(PointCloud::default());
    let path = |poses: usize| RobotPath {
        placement: Isometry3::identity(),
        poses: vec![Isometry3::identity(); poses],
        clouds: vec![cloud.clone(); 2],
    };
    let config = JointConfig::default();
    assert!(matches!(
        solve(&[path(2), path(3)], 0, &config),
        Err(JointError::MismatchedKeyframes { robot: 1, poses: 3, clouds: 2 })
    ));
    assert!(matches!(solve(&[path(2)], 1, &config), Err(JointError::UnknownReference { reference: 1, robots: 1 })));
    for invalid in [
        JointConfig { spacing: -1.0, ..JointConfig::default() },
        JointConfig { window: f64::NAN, ..JointConfig::default() },
        JointConfig { reach: 0.0, ..JointConfig::default() },
        JointConfig { sigma_growth: -1.0, ..JointConfig::default() },
    ] {
        assert!(matches!(solve(&[path(2)], 0, &invalid), Err(JointError::InvalidConfig)), "{invalid:?}");
    }
    // Empty clouds register nothing: each robot keeps its placement.
    let alone = solve(&[path(2), path(2)], 0, &config).unwrap();
    assert_eq!((alone.joined, alone.registered), (vec![true, false], 0));
}
