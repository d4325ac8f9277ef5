//! `emr-edge sim`: the command writes the simulator's scans in the KITTI layout, and says clearly
//! what is wrong with its arguments.

use sim::{Scenario, SimConfig, Simulator};

const ALL: [&str; 4] = ["warehouse-small", "warehouse-large", "campus", "aisles"];

fn emr_edge(args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_emr-edge")).args(args).output().unwrap()
}

#[test]
fn cli_writes_the_kitti_layout() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("seq");
    let svg = dir.path().join("aisles.svg");
    let run = emr_edge(&[
        "sim",
        "--scenario",
        "aisles",
        "--robot",
        "2",
        "--out",
        out.to_str().unwrap(),
        "--frames",
        "4",
        "--seed",
        "3",
        "--svg",
        svg.to_str().unwrap(),
    ]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let mut bins: Vec<_> = std::fs::read_dir(out.join("velodyne")).unwrap().map(|e| e.unwrap().file_name()).collect();
    bins.sort();
    assert_eq!(bins, ["000000.bin", "000001.bin", "000002.bin", "000003.bin"]);
    // The files hold exactly the library's scans (CLI robot ids are 1-based: robot 2 is index 1).
    let sim =
        Simulator::new(Scenario::by_name("aisles").unwrap(), 1, SimConfig { seed: 3, ..SimConfig::default() }).unwrap();
    let bytes = std::fs::read(out.join("velodyne/000002.bin")).unwrap();
    assert_eq!(bytes, cloud::formats::kitti::encode(&sim.scan(2).cloud));
    let poses = std::fs::read_to_string(out.join("poses.txt")).unwrap();
    let rows: Vec<Vec<f64>> = poses.lines().map(|l| l.split(' ').map(|v| v.parse().unwrap()).collect()).collect();
    assert_eq!(rows.len(), 4);
    let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
    assert!(rows[0].iter().zip(identity).all(|(a, b)| (a - b).abs() < 1e-9), "{:?}", rows[0]);
    let expected = sim.ground_truth(0).inverse() * sim.ground_truth(3);
    let last = cloud::se3::from_kitti_row(&rows[3].clone().try_into().unwrap()).unwrap();
    assert!(cloud::se3::pose_error(&last, &expected).translation_m < 1e-8);
    let times = std::fs::read_to_string(out.join("times.txt")).unwrap();
    let times: Vec<f64> = times.lines().map(|l| l.parse().unwrap()).collect();
    assert_eq!(times, [0.0, 0.1, 0.2, 0.3]);
    assert!(std::fs::read_to_string(svg).unwrap().starts_with("<svg"));
}

#[test]
fn cli_errors_are_clear() {
    let run = emr_edge(&["sim", "--scenario", "aisles", "--robot", "7", "--out", "/nonexistent/never"]);
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("has 2 robots"));
    let run = emr_edge(&["sim", "--scenario", "garage", "--out", "x"]);
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && err.contains("warehouse-small") && err.contains("campus"), "{err}");
    let help = String::from_utf8_lossy(&emr_edge(&["sim", "--help"]).stdout).to_string();
    assert!(ALL.iter().all(|n| help.contains(n)), "{help}");
}

#[test]
fn the_edge_has_no_benchmark_command() {
    let out = emr_edge(&["--help"]);
    let help = String::from_utf8(out.stdout).unwrap();
    assert!(help.contains("odometry") && !help.lines().any(|l| l.trim_start().starts_with("bench")), "{help}");
}
