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
