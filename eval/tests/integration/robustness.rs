//! The robustness matrix's cases against their ground truth: the right scans, the right
//! poses, shuffling that keeps the points, and failures reported as rows.

use std::path::PathBuf;

use cloud::Preset;
use cloud::trajectory::Trajectory;
use edge::recording::{self, RecordingOptions};
use eval::robustness::{
    self, Case, HoldCriterion, Motion, Part, Planned, Recipe, RunOptions, SimCase, kitti_every, run_ours, shuffled,
    simulated,
};
use nalgebra::{Isometry3, Vector3};

fn kitti() -> PathBuf {
    testkit::shared_data("kitti00")
}

fn kitti_truth() -> Vec<Isometry3<f64>> {
    let text = std::fs::read_to_string(kitti().join("poses_velodyne.txt")).unwrap();
    Trajectory::parse_kitti(&text).unwrap().poses
}

fn kitti_times() -> Vec<f64> {
    let text = std::fs::read_to_string(kitti().join("times.txt")).unwrap();
    text.lines().map(|l| l.trim().parse().unwrap()).collect()
}

/// Points of a cloud as sortable bit patterns (x, y, z, intensity).
fn point_set(cloud: &cloud::PointCloud) -> Vec<[u32; 4]> {
    let intensity = cloud.intensity.as_deref().unwrap();
    let mut set: Vec<[u32; 4]> = cloud
        .points
        .iter()
        .zip(intensity)
        .map(|(p, i)| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits(), i.to_bits()])
        .collect();
    set.sort_unstable();
    set
}

#[test]
fn kitti_every_second_scan_from_5_has_the_sequence_poses_and_stamps() {
    let case = kitti_every(&kitti(), 5, 2).unwrap();
    let indices: Vec<usize> = case.scans.iter().map(|s| s.index).collect();
    assert_eq!(indices, [5, 7, 9, 11, 13, 15]);
    assert_eq!((case.preset, case.scan_period, case.deskew), (Preset::Outdoor, 0.1, false));
    let (truth, times) = (kitti_truth(), kitti_times());
    for scan in &case.scans {
        assert_eq!(scan.ground_truth, Some(truth[scan.index]));
        assert_eq!(scan.stamp, times[scan.index]);
        // Read as the odometry reads recordings: rings and times derived.
        assert!(scan.cloud.ring.is_some() && scan.cloud.time.is_some());
        let raw = std::fs::metadata(kitti().join(format!("velodyne/{:06}.bin", scan.index))).unwrap().len();
        assert!(scan.cloud.len() as u64 <= raw / 16 && scan.cloud.len() as u64 > raw / 16 - 100);
    }
    // Relative motion between picked scans is the sequence's: scan 5 to scan 7.
    let case_truth = case.truth();
    let step = case_truth[0].inverse() * case_truth[1];
    let expected = truth[5].inverse() * truth[7];
    testkit::assert_pose_close!(&step, &expected, 1e-12, 1e-9);
}

#[test]
fn a_start_past_the_sequence_is_an_empty_case_error() {
    let err = kitti_every(&kitti(), 99, 2).unwrap_err();
    assert_eq!(err.to_string(), "the case has no scans");
}

/// A short warehouse case: robot 1 from 40 s, every `every`-th sweep at `rate_hz`.
fn warehouse(every: usize, rate_hz: f64, scans: usize) -> Case {
    simulated(&SimCase { every, rate_hz, scans, ..SimCase::default() }).unwrap()
}

#[test]
fn a_simulated_case_takes_every_kth_sweep_from_mid_run() {
    let case = warehouse(5, 2.0, 4);
    // 40 s at 2 Hz is sweep 80; then every 5th.
    let indices: Vec<usize> = case.scans.iter().map(|s| s.index).collect();
    assert_eq!(indices, [80, 85, 90, 95]);
    assert_eq!(case.scan_period, 0.5);
    let route = sim::Scenario::by_name("warehouse-small").unwrap().robots()[0].clone();
    for scan in &case.scans {
        assert_eq!(scan.stamp, scan.index as f64 * 0.5);
        // Truth at the sweep end, on the robot's route.
        assert_eq!(scan.ground_truth, Some(route.pose(scan.stamp + 0.5)));
        let last = scan.cloud.time.as_ref().unwrap().iter().copied().fold(0.0, f32::max);
        assert!(last > 0.49 && last < 0.5);
    }
    // Mid-run: the robot is moving when the first scan is taken.
    assert!(route.speed(40.0) > 0.5);
}

#[test]
fn spinning_in_place_ground_truth_turns_at_the_asked_rate() {
    let motion = Motion::Spin { scenario: "warehouse-small".into(), at: [10.0, 12.0], deg_per_s: 90.0 };
    let case = simulated(&SimCase { motion, start_s: 0.0, scans: 5, ..SimCase::default() }).unwrap();
    let truth = case.truth();
    for (i, w) in truth.windows(2).enumerate() {
        let step = w[0].inverse() * w[1];
        // 90 deg/s at 10 Hz: 9 degrees a sweep, about the vertical, in place.
        assert!((step.rotation.scaled_axis() - Vector3::new(0.0, 0.0, 9f64.to_radians())).norm() < 1e-12, "{i}");
        assert!(step.translation.vector.norm() < 1e-12);
        assert!((w[0].translation.vector - Vector3::new(10.0, 12.0, 0.7)).norm() < 1e-12);
    }
}

#[test]
fn a_car_case_starts_at_speed() {
    let motion = Motion::Car { speed: 20.0 };
    let spec = SimCase { motion, sensor: sim::SensorKind::Vlp16, start_s: 0.0, scans: 3, ..SimCase::default() };
    let truth = simulated(&spec).unwrap().truth();
    // Two metres a sweep from the first on (2 % for the roof mast tilting on the hills).
    for w in truth.windows(2) {
        let d = (w[1].translation.vector - w[0].translation.vector).norm();
        assert!((d - 2.0).abs() < 0.04, "{d}");
    }
}

#[test]
fn a_compensated_case_holds_the_raw_sweeps_points_where_the_sensor_ends_its_sweep() {
    let raw = SimCase { scans: 2, ..SimCase::default() };
    let compensated = SimCase { compensated: true, ..raw.clone() };
    let (raw, compensated) = (simulated(&raw).unwrap(), simulated(&compensated).unwrap());
    assert_eq!(raw.truth(), compensated.truth());
    let sim = sim::Simulator::new(
        sim::Scenario::by_name("warehouse-small").unwrap(),
        0,
        sim::SimConfig { sensor: sim::SensorKind::Vlp16.model(), ..sim::SimConfig::default() },
    )
    .unwrap();
    for (r, c) in raw.scans.iter().zip(&compensated.scans) {
        assert!(c.cloud.time.is_none() && c.cloud.ring == r.cloud.ring && c.cloud.intensity == r.cloud.intensity);
        let end = r.ground_truth.unwrap();
        let times = r.cloud.time.as_ref().unwrap();
        let mut moved = 0;
        for ((p, q), &t) in r.cloud.points.iter().zip(&c.cloud.points).zip(times) {
            // The raw point placed by the pose at its own firing time, the compensated one by the
            // sweep's end pose: the same world point.
            let world = sim.pose_at(r.stamp + f64::from(t)) * p.cast::<f64>();
            assert!((world - end * q.cast::<f64>()).norm() < 1e-3, "{p} -> {q}");
            moved += usize::from((p - q).norm() > 0.01);
        }
        assert!(moved > r.cloud.len() / 2, "compensation moved only {moved} of {} points", r.cloud.len());
    }
}

#[test]
fn seeds_redraw_simulated_and_shuffled_noise_and_real_scans_have_one_draw() {
    let kitti_case = Planned {
        name: "k".into(),
        class: "every-k",
        part: Part::Tuned,
        recipe: Recipe::Kitti { dir: kitti(), start: 0, every: 8 },
    };
    assert!(kitti_case.seeded(0).is_some() && kitti_case.seeded(1).is_none());
    let sim_case = Planned { recipe: Recipe::Sim(SimCase { scans: 1, ..SimCase::default() }), ..kitti_case.clone() };
    let points = |p: Planned| p.build().unwrap().scans[0].cloud.points.clone();
    let (zero, one) = (points(sim_case.seeded(0).unwrap()), points(sim_case.seeded(1).unwrap()));
    assert_ne!(zero, one);
    assert_eq!(zero, points(sim_case.clone()));
    let shuffled = Planned {
        recipe: Recipe::Shuffled { of: Box::new(kitti_case.recipe.clone()), seed: 7, derive_channels: true },
        ..kitti_case
    };
    assert_ne!(points(shuffled.seeded(0).unwrap()), points(shuffled.seeded(1).unwrap()));
}

#[test]
fn shuffling_keeps_the_point_set_and_drops_rings_and_times() {
    let case = warehouse(1, 10.0, 2);
    let mixed = shuffled(case.clone(), 7);
    assert_eq!((mixed.name.as_str(), mixed.class.as_str()), ("sim-vlp16-10hz-every-1-shuffled", "shuffled"));
    for (a, b) in case.scans.iter().zip(&mixed.scans) {
        assert_eq!((a.index, a.stamp, a.ground_truth), (b.index, b.stamp, b.ground_truth));
        assert!(b.cloud.ring.is_none() && b.cloud.time.is_none());
        assert_eq!(point_set(&a.cloud), point_set(&b.cloud));
        assert_ne!(a.cloud.points, b.cloud.points, "the order changed");
    }
    // Seeded: the same seed gives the same order, another seed another.
    assert_eq!(shuffled(case.clone(), 7).scans[0].cloud.points, mixed.scans[0].cloud.points);
    assert_ne!(shuffled(case, 8).scans[0].cloud.points, mixed.scans[0].cloud.points);
}

#[test]
fn a_case_written_to_disk_reads_back_as_the_same_scans_and_truth() {
    let case = shuffled(kitti_every(&kitti(), 10, 5).unwrap(), 3);
    let dir = tempfile::tempdir().unwrap();
    robustness::export::write_kitti(&case, dir.path()).unwrap();
    let read: Vec<_> = recording::open(dir.path(), &RecordingOptions::default()).unwrap().map(Result::unwrap).collect();
    assert_eq!(read.len(), 2);
    for (scan, back) in case.scans.iter().zip(&read) {
        assert_eq!(scan.cloud.points, back.cloud.points, "the shuffled order is what is written");
        assert!((scan.stamp - case.scans[0].stamp - back.stamp).abs() < 1e-6);
    }
    let text = std::fs::read_to_string(dir.path().join("poses.txt")).unwrap();
    let poses = Trajectory::parse_kitti(&text).unwrap().poses;
    let truth = kitti_truth();
    testkit::assert_pose_close!(&poses[0], &Isometry3::identity(), 1e-12, 1e-9);
    testkit::assert_pose_close!(&poses[1], &(truth[10].inverse() * truth[15]), 1e-8, 1e-6);
}

#[test]
fn a_simulated_case_from_rest_holds_so_the_truth_matches_the_odometry_frame() {
    // From the start of the route (at rest) our odometry is known to track the warehouse within
    // centimetres (edge/tests/integration/odometry_sim.rs): a case whose truth were off by a frame or a half
    // sweep would not hold.
    let case = simulated(&SimCase { start_s: 0.0, scans: 120, ..SimCase::default() }).unwrap();
    let outcome = run_ours(&case, &HoldCriterion::default());
    let verdict = outcome.verdict.unwrap();
    assert!(verdict.held && verdict.ate.unaligned < 0.05, "{verdict:?}");
    assert!(verdict.path_m > 10.0, "{verdict:?}");
    assert!(outcome.ms_per_scan.is_some() && outcome.lost == Some(0) && outcome.recoveries.is_some());
}

#[test]
fn bare_shuffled_scans_run_on_voxel_features_and_a_case_that_cannot_be_built_is_an_error_row() {
    let of = Box::new(Recipe::Kitti { dir: kitti(), start: 0, every: 8 });
    let planned = Planned {
        name: "bare".into(),
        class: "shuffled",
        part: Part::Tuned,
        recipe: Recipe::Shuffled { of, seed: 1, derive_channels: false },
    };
    let row =
        robustness::run_case(&planned, 0, &RunOptions { criterion: HoldCriterion::default(), kiss: None, out: None });
    assert_eq!((row.name.as_str(), row.class.as_str(), row.scans), ("bare", "shuffled", 2));
    // Without ring or time channels the odometry takes its features from voxel shapes: it runs.
    assert!(row.ours.verdict.is_ok(), "{:?}", row.ours.verdict);
    assert!(row.kiss.is_none());
    // A case that cannot be built is a row too.
    let missing = Planned { recipe: Recipe::Kitti { dir: "/no/such/dir".into(), start: 0, every: 1 }, ..planned };
    let row =
        robustness::run_case(&missing, 0, &RunOptions { criterion: HoldCriterion::default(), kiss: None, out: None });
    assert!(row.ours.verdict.unwrap_err().contains("/no/such/dir"));
}

#[test]
fn the_matrix_names_every_case_once_and_quick_is_a_subset() {
    let full = robustness::matrix(&kitti(), false);
    let quick = robustness::matrix(&kitti(), true);
    let names: Vec<&str> = full.iter().map(|p| p.name.as_str()).collect();
    let mut unique = names.clone();
    unique.sort_unstable();
    unique.dedup();
    assert_eq!(unique.len(), names.len(), "{names:?}");
    assert!(quick.len() < full.len() && quick.iter().all(|q| names.contains(&q.name.as_str())));
    for class in ["every-k", "rate", "car", "spin", "sensor", "shuffled"] {
        assert!(full.iter().any(|p| p.class == class && p.part == Part::Tuned), "{class}");
    }
    // The held-back part: classes of their own, each run with the odometry's defaults.
    let held: Vec<_> = full.iter().filter(|p| p.part == Part::HeldBack).collect();
    for class in ["solid-state", "highway", "sparse-outdoor", "fast-turn", "compensated", "rolling"] {
        assert!(held.iter().any(|p| p.class == class), "{class}");
    }
    assert!(quick.iter().any(|p| p.part == Part::HeldBack));
    for p in held {
        let Recipe::Sim(spec) = &p.recipe else { panic!("{} is not simulated", p.name) };
        assert_eq!(spec.preset, cloud::Preset::Indoor, "{}", p.name);
    }
}

fn emr_eval(args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_emr-eval")).args(args).output().unwrap()
}

#[test]
fn the_command_prints_a_row_per_chosen_case_and_refuses_an_unknown_one() {
    let data = kitti();
    let data = data.to_str().unwrap();
    let run = emr_eval(&["robustness", "--no-kiss", "--case", "from-5-every-5", "--data", data]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let table = String::from_utf8(run.stdout).unwrap();
    let lines: Vec<&str> = table.lines().take_while(|l| !l.is_empty()).collect();
    assert_eq!(lines.len(), 3, "{table}");
    // The summary: one part, one run, held, no KISS-ICP; the case over its one seed.
    assert!(table.contains("\n| tuned | 1 | 1 | - | 0.00 / 0.00 (0 runs) | 0 of 0 |\n"), "{table}");
    assert!(table.contains("\n| kitti00-from-5-every-5 | tuned | 1 | "), "{table}");
    assert!(lines[0].starts_with("| case | class | scans | path m | ours ATE m | ours held | lost | recoveries |"));
    let cells: Vec<&str> = lines[2].split('|').map(str::trim).collect();
    assert_eq!(&cells[1..4], ["kitti00-from-5-every-5", "every-k", "3"]);
    // Counts of lost scans and recoveries, no KISS-ICP.
    assert_eq!(cells[7], "0", "{}", lines[2]);
    assert!(cells[8].parse::<usize>().is_ok(), "{}", lines[2]);
    assert_eq!(&cells[9..11], ["-", "-"], "{}", lines[2]);
    assert!(String::from_utf8_lossy(&run.stderr).contains("[1/1] kitti00-from-5-every-5"));
    let none = emr_eval(&["robustness", "--no-kiss", "--case", "no-such-case", "--data", data]);
    assert!(!none.status.success());
    assert!(String::from_utf8_lossy(&none.stderr).contains("no case matches \"no-such-case\""));
}
