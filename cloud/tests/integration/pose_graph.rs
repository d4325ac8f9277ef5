//! The pose-graph optimiser against ground truth: synthetic graphs with known poses, a false loop,
//! and the standard g2o benchmarks against GTSAM's published figures.

use cloud::pose_graph::synthetic::{self, Synthetic, SyntheticConfig};
use cloud::pose_graph::{Edge, EdgeKind, PoseGraph, PoseGraphConfig, g2o};
use nalgebra::Isometry3;
use testkit::Rng;

/// GTSAM 4.3 on the shared benchmarks (data/posegraph/README.md): initial and final error.
const PARKING_GARAGE: (f64, f64) = (8363.60, 0.634192);
const SMALL_GRID: (f64, f64) = (83894.3, 517.925);

/// Eight laps of 150 poses around the ring, 5 % loops, noise drawn from `seed`.
fn ring(seed: u64) -> Synthetic {
    let mut rng = Rng::xorshift64_star(Rng::spread(seed));
    let config = SyntheticConfig { poses: 1200, poses_per_lap: 150, radius_m: 25.0, ..SyntheticConfig::default() };
    synthetic::generate(&config, || rng.gaussian(1.0))
}

/// ATE RMSE of `poses` against `truth`, unaligned (both start at the same first pose, which the
/// optimiser holds fixed).
fn ate(poses: &[Isometry3<f64>], truth: &[Isometry3<f64>]) -> f64 {
    cloud::trajectory::ate(truth, poses, false).unwrap().rmse
}

fn read(name: &str) -> PoseGraph {
    let path = testkit::shared_data(&format!("posegraph/{name}"));
    g2o::parse(&std::fs::read_to_string(&path).unwrap()).unwrap().graph
}

#[test]
fn loops_pull_a_drifting_trajectory_back_to_the_truth() {
    let Synthetic { mut graph, truth } = ring(1);
    let dead_reckoning = ate(graph.poses(), &truth);
    let report = graph.optimize(&PoseGraphConfig::default()).unwrap();
    let optimised = ate(graph.poses(), &truth);
    assert!(report.converged && report.final_error <= report.initial_error, "{report:?}");
    // Dead reckoning drifts metres. The loops (5 cm, 0.3 deg) tie the laps together; what is left
    // is the ring's shape, the odometry of one lap averaged over eight (about 0.6 m / √8).
    assert!(dead_reckoning > 1.0, "the test needs drift: {dead_reckoning} m");
    assert!(optimised < 0.25 && optimised < dead_reckoning / 8.0, "ATE {dead_reckoning} -> {optimised} m");
    // At the optimum the residuals are the measurement noise: the least-squares cost is ½ χ² with
    // 6 (edges − poses + 1) degrees of freedom: 3 per edge beyond a tree, with a standard deviation
    // of 8 % here (the bound is six of them).
    let expected = 3.0 * (graph.edges().len() + 1 - graph.poses().len()) as f64;
    let least_squares = graph.error(&PoseGraphConfig::least_squares());
    assert!((least_squares - expected).abs() < 0.5 * expected, "{least_squares} vs {expected}");
}

#[test]
fn the_cauchy_kernel_ignores_a_false_loop_that_least_squares_follows() {
    let Synthetic { graph, truth } = ring(2);
    // A loop claiming that two poses half a ring apart (50 m) are the same place, as confident as a
    // true one.
    let (a, b) = (300, 375);
    let information = graph.edges().iter().find(|e| e.kind == EdgeKind::Loop).unwrap().information;
    let mut with_false = graph.clone();
    with_false
        .add_edge(Edge { from: a, to: b, measurement: Isometry3::identity(), information, kind: EdgeKind::Loop })
        .unwrap();

    let mut clean = graph.clone();
    clean.optimize(&PoseGraphConfig::default()).unwrap();
    let mut robust = with_false.clone();
    robust.optimize(&PoseGraphConfig::default()).unwrap();
    let mut plain = with_false;
    plain.optimize(&PoseGraphConfig::least_squares()).unwrap();

    let (clean, robust, plain) = (ate(clean.poses(), &truth), ate(robust.poses(), &truth), ate(plain.poses(), &truth));
    // With the kernel the false loop changes the result by millimetres; without it, metres.
    assert!(robust < 0.25 && (robust - clean).abs() < 0.01, "clean {clean} m, with the false loop {robust} m");
    assert!(plain > 1.0, "least squares with the false loop: {plain} m");
}

/// Our initial error is GTSAM's (the same cost and conventions), and we reach its optimum or lower.
fn matches_gtsam(name: &str, size: (usize, usize), (initial, gtsam): (f64, f64)) {
    let mut graph = read(name);
    assert_eq!((graph.poses().len(), graph.edges().len()), size);
    let report = graph.optimize(&PoseGraphConfig::least_squares()).unwrap();
    assert!((report.initial_error - initial).abs() < 1e-4 * initial, "{name}: {report:?}");
    assert!(report.converged && report.final_error <= gtsam * (1.0 + 1e-4), "{name}: {report:?}");
}

#[test]
fn parking_garage_matches_gtsam() {
    matches_gtsam("parking-garage.g2o", (1661, 6275), PARKING_GARAGE);
}

#[test]
fn small_grid_matches_gtsam() {
    matches_gtsam("smallGrid3D.g2o", (125, 297), SMALL_GRID);
}

#[test]
fn optimising_gives_the_same_poses_whatever_the_thread_count() {
    let Synthetic { graph, .. } = ring(3);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let mut g = graph.clone();
        let report = pool.install(|| g.optimize(&PoseGraphConfig::default())).unwrap();
        (report.final_error, g.poses().to_vec())
    };
    assert_eq!(run(1), run(2));
}

#[test]
fn g2o_files_round_trip() {
    for name in ["parking-garage.g2o", "smallGrid3D.g2o"] {
        let graph = read(name);
        let text = g2o::write(&graph);
        let again = g2o::parse(&text).unwrap().graph;
        assert_eq!(again.ids(), graph.ids(), "{name}");
        assert_eq!(again.edges().len(), graph.edges().len());
        for (a, b) in again.poses().iter().zip(graph.poses()) {
            testkit::assert_pose_close!(a, b, 1e-12, 1e-9, "{name}");
        }
        for (a, b) in again.edges().iter().zip(graph.edges()) {
            assert_eq!((a.from, a.to, a.kind, a.information), (b.from, b.to, b.kind, b.information), "{name}");
            testkit::assert_pose_close!(&a.measurement, &b.measurement, 1e-12, 1e-9, "{name}");
        }
        // Written numbers are Rust's shortest round-trip form: the text is a fixed point.
        assert!(g2o::write(&again) == text, "{name}: writing the graph read back changes the text");
    }
}

/// A file whose one loop edge has an information matrix that is not positive semi-definite (as
/// SE-Sync's `cubicle` has): read as GTSAM reads it, repaired and reported, and optimised to the
/// optimum of the same graph with the edge as it should have been.
#[test]
fn an_indefinite_information_matrix_is_repaired_and_the_optimum_holds() {
    let Synthetic { graph, truth } = ring(3);
    let text = g2o::write(&graph);
    // The first loop edge: its translation x-y coupling past sqrt(I11 I22) makes it indefinite.
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    let at = lines
        .iter()
        .position(|l| {
            let w: Vec<&str> = l.split_whitespace().collect();
            w[0] == "EDGE_SE3:QUAT" && w[2].parse::<i64>().unwrap() != w[1].parse::<i64>().unwrap() + 1
        })
        .expect("a loop edge");
    let mut words: Vec<String> = lines[at].split_whitespace().map(str::to_owned).collect();
    let (i11, i22): (f64, f64) = (words[10].parse().unwrap(), words[16].parse().unwrap());
    words[11] = (1.05 * (i11 * i22).sqrt()).to_string();
    lines[at] = words.join(" ");
    let read = g2o::parse(&lines.join("\n")).unwrap();
    assert_eq!(read.repaired.len(), 1, "{:?}", read.repaired);
    assert_eq!(read.repaired[0].line, at + 1);
    assert!(read.repaired[0].min_eigenvalue < 0.0);

    let config = PoseGraphConfig::least_squares();
    let (mut repaired, mut intact) = (read.graph, graph);
    let (a, b) = (repaired.optimize(&config).unwrap(), intact.optimize(&config).unwrap());
    assert!(a.converged && b.converged, "{a:?} {b:?}");
    let relative = (a.final_error - b.final_error).abs() / b.final_error;
    let (ate_repaired, ate_intact) = (ate(repaired.poses(), &truth), ate(intact.poses(), &truth));
    println!(
        "final error {:.4} repaired, {:.4} intact ({:.4} %); ATE {ate_repaired:.4} / {ate_intact:.4} m",
        a.final_error,
        b.final_error,
        relative * 100.0
    );
    assert!(relative < 1e-3, "the repaired graph's optimum is {:.3} % off", relative * 100.0);
    // The repaired edge weighs its coupled directions differently, so the optimum moves a little;
    // it must not cost accuracy against the truth.
    assert!(ate_repaired <= 1.02 * ate_intact, "ATE {ate_repaired} against {ate_intact}");
}
