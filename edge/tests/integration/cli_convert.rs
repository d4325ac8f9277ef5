//! `emr-edge convert`: any source to the KITTI layout.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn emr_edge(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_emr-edge")).args(args).output().expect("emr-edge runs")
}

fn kitti00() -> PathBuf {
    testkit::shared_data("kitti00")
}

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name)
}

#[test]
fn a_kitti_directory_converts_to_identical_scans_and_its_times() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("seq");
    let run = emr_edge(&["convert", kitti00().to_str().unwrap(), "--out", out.to_str().unwrap(), "--frames", "3"]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    for i in 0..3 {
        let name = format!("{i:06}.bin");
        assert_eq!(
            std::fs::read(out.join("velodyne").join(&name)).unwrap(),
            std::fs::read(kitti00().join("velodyne").join(&name)).unwrap()
        );
    }
    assert!(!out.join("velodyne/000003.bin").exists());
    // times.txt is relative to the first scan: KITTI's own times.txt starts at 0 too.
    let ours: Vec<f64> =
        std::fs::read_to_string(out.join("times.txt")).unwrap().lines().map(|l| l.parse().unwrap()).collect();
    let theirs: Vec<f64> = std::fs::read_to_string(kitti00().join("times.txt"))
        .unwrap()
        .lines()
        .take(3)
        .map(|l| l.trim().parse().unwrap())
        .collect();
    assert_eq!(ours.len(), 3);
    for (a, b) in ours.iter().zip(&theirs) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
}

#[test]
fn a_bag_topic_converts_to_the_points_it_holds() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("seq");
    let run = emr_edge(&[
        "convert",
        fixture("kitti3_lz4.bag").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--topic",
        "/velodyne_points",
    ]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    // The files hold exactly what the reader returns (itself checked against the fixture script's
    // expected values in recordings.rs), as KITTI records.
    let options = edge::recording::RecordingOptions { topic: Some("/velodyne_points".into()), ..Default::default() };
    let scans: Vec<_> =
        edge::recording::open(&fixture("kitti3_lz4.bag"), &options).unwrap().map(|s| s.unwrap()).collect();
    assert_eq!(scans.len(), 3);
    // As KITTI records where the scan has no rings or times, else as binary PCD, which keeps them.
    use cloud::formats::{FileFormat, PcdEncoding, encode};
    for (i, scan) in scans.iter().enumerate() {
        let channels = scan.cloud.ring.is_some() || scan.cloud.time.is_some();
        let format = if channels { FileFormat::Pcd(PcdEncoding::Binary) } else { FileFormat::KittiBin };
        let written = std::fs::read(out.join(format!("velodyne/{i:06}.{}", format.extension()))).unwrap();
        assert_eq!(written, encode(&scan.cloud, format), "scan {i}");
    }
}

#[test]
fn an_unknown_topic_lists_the_topics_present() {
    let dir = tempfile::tempdir().unwrap();
    let run = emr_edge(&[
        "convert",
        fixture("kitti3.bag").to_str().unwrap(),
        "--out",
        dir.path().to_str().unwrap(),
        "--topic",
        "/nope",
    ]);
    assert!(!run.status.success());
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(err.contains("/nope") && err.contains("/velodyne_points (sensor_msgs/PointCloud2)"), "{err}");
}

/// `--start-at N` leaves out the first N scans: what it writes is what a run from the start writes
/// from scan N on, and the poses start again at the identity (a robot that starts there).
#[test]
fn start_at_skips_the_first_scans_of_a_recording_and_of_the_simulator() {
    let dir = tempfile::tempdir().unwrap();
    let convert = |input: &str, name: &str, extra: &[&str]| {
        let out = dir.path().join(name);
        let mut args = vec!["convert", input, "--out", out.to_str().unwrap()];
        args.extend_from_slice(extra);
        let run = emr_edge(&args);
        assert!(run.status.success(), "{input} {extra:?}: {}", String::from_utf8_lossy(&run.stderr));
        out
    };
    let scan = |dir: &Path, i: usize| std::fs::read(dir.join("velodyne").join(format!("{i:06}.bin"))).unwrap();
    let kitti = kitti00();
    let later = convert(kitti.to_str().unwrap(), "kitti_later", &["--start-at", "2", "--frames", "2"]);
    assert_eq!(scan(&later, 0), std::fs::read(kitti.join("velodyne/000002.bin")).unwrap());
    assert_eq!(scan(&later, 1), std::fs::read(kitti.join("velodyne/000003.bin")).unwrap());
    assert!(!later.join("velodyne/000002.bin").exists());
    let all = convert("sim:warehouse-small:1", "sim_all", &["--frames", "6"]);
    let later = convert("sim:warehouse-small:1", "sim_later", &["--start-at", "4", "--frames", "2"]);
    for i in 0..2 {
        assert_eq!(scan(&later, i), scan(&all, 4 + i), "sweep {} of the simulator", 4 + i);
    }
    // The simulator's truth, re-based on the first sweep written: T_4^-1 T_5 from the full run.
    let poses = |dir: &Path| -> Vec<nalgebra::Isometry3<f64>> {
        std::fs::read_to_string(dir.join("poses.txt"))
            .unwrap()
            .lines()
            .map(|l| {
                let row: Vec<f64> = l.split_whitespace().map(|v| v.parse().unwrap()).collect();
                cloud::se3::from_kitti_row(&row.try_into().unwrap()).unwrap()
            })
            .collect()
    };
    let (all, later) = (poses(&all), poses(&later));
    let expected = all[4].inverse() * all[5];
    assert!((later[0].translation.vector.norm()) < 1e-6, "the first pose is the identity");
    assert!((later[1].translation.vector - expected.translation.vector).norm() < 1e-6);
    let beyond = emr_edge(&["convert", "sim:warehouse-small:1", "--start-at", "100000", "--out", "/nonexistent/x"]);
    assert!(!beyond.status.success());
    let said = String::from_utf8_lossy(&beyond.stderr);
    assert!(said.contains("--start-at 100000") && said.contains("sim:warehouse-small:1"), "{said}");
}
