//! `emr-edge convert` of real LiDAR packet captures against the points the vendors' reference
//! decoders give (velodyne-decoder 3.0.0, ouster-sdk 1.0.1; `../shared/data/lidar_packets`).

use std::path::{Path, PathBuf};
use std::process::Command;

use cloud::formats::read_cloud;

/// A capture and how its reference files are laid out.
struct Capture {
    name: &'static str,
    /// f32 values per reference record, and which of them is the ring.
    record: usize,
    ring_at: usize,
}

const VELODYNE: usize = 6;
const OUSTER: usize = 4;

fn packets(name: &str) -> PathBuf {
    testkit::shared_data("lidar_packets").join(name)
}

/// A scan as points per ring.
type Rings = Vec<Vec<[f32; 3]>>;

fn reference_scans(capture: &Capture) -> Vec<Rings> {
    let dir = packets(&format!("{}_reference", capture.name));
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
    files.sort();
    files
        .iter()
        .map(|file| {
            let bytes = std::fs::read(file).unwrap();
            let values: Vec<f32> = bytes.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
            let mut rings: Rings = Vec::new();
            for record in values.chunks_exact(capture.record) {
                let ring = record[capture.ring_at] as usize;
                rings.resize(rings.len().max(ring + 1), Vec::new());
                rings[ring].push([record[0], record[1], record[2]]);
            }
            rings
        })
        .collect()
}

fn converted_scans(out: &Path) -> Vec<Rings> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(out.join("velodyne")).unwrap().map(|e| e.unwrap().path()).collect();
    files.sort();
    files
        .iter()
        .map(|file| {
            let cloud = read_cloud(file).unwrap().cloud;
            let ring = cloud.ring.as_ref().expect("decoded packets carry rings");
            assert!(
                cloud.time.is_some() && cloud.intensity.is_some(),
                "{}: times and intensities kept",
                file.display()
            );
            let mut rings: Rings = Vec::new();
            for (p, &r) in cloud.points.iter().zip(ring) {
                rings.resize(rings.len().max(usize::from(r) + 1), Vec::new());
                rings[usize::from(r)].push([p.x, p.y, p.z]);
            }
            rings
        })
        .collect()
}

/// For every reference point, the distance to the nearest converted point of the same ring.
fn distances(ours: &Rings, reference: &Rings) -> Vec<f32> {
    let mut out = Vec::new();
    for (ring, points) in reference.iter().enumerate() {
        let candidates = ours.get(ring).map(Vec::as_slice).unwrap_or_default();
        for p in points {
            let nearest = candidates
                .iter()
                .map(|q| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt())
                .fold(f32::INFINITY, f32::min);
            out.push(nearest);
        }
    }
    out
}

/// The partial scans `convert` reports ("N scans cover only part of a rotation"), 0 if none.
fn partial_scans(stdout: &str) -> usize {
    stdout
        .lines()
        .find_map(|l| l.split_once(" scans cover only part of a rotation"))
        .map_or(0, |(n, _)| n.trim().parse().unwrap())
}

fn count(scan: &Rings) -> usize {
    scan.iter().map(Vec::len).sum()
}

/// Converts the capture with the CLI and checks every scan against the reference: the same scans,
/// point counts within 1 %, the 99th percentile of the point distance within 1 mm. The reference
/// decoders drop a capture's last rotation when it is cut short; ours keeps it and says so, so
/// ours may hold that one scan more, counted as partial.
fn converts_as_the_reference(capture: Capture) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("scans");
    let input = packets(&format!("{}.pcap", capture.name));
    let run = Command::new(env!("CARGO_BIN_EXE_emr-edge"))
        .args(["convert", &format!("pcap:{}", input.display()), "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let (ours, reference) = (converted_scans(&out), reference_scans(&capture));
    let stdout = String::from_utf8_lossy(&run.stdout);
    let partial = partial_scans(&stdout);
    assert!(
        ours.len() >= reference.len() && ours.len() - reference.len() <= partial.min(1),
        "{}: {} scans, reference {}, {partial} partial\n{stdout}",
        capture.name,
        ours.len(),
        reference.len()
    );
    for (i, (a, b)) in ours.iter().zip(&reference).enumerate() {
        let (na, nb) = (count(a), count(b));
        assert!(na.abs_diff(nb) as f64 <= 0.01 * nb as f64, "{} scan {i}: {na} points, reference {nb}", capture.name);
        let mut d = distances(a, b);
        d.sort_by(f32::total_cmp);
        let p99 = d[(d.len() * 99 / 100).min(d.len() - 1)];
        assert!(p99 <= 1e-3, "{} scan {i}: 99th percentile {:.2} mm", capture.name, p99 * 1e3);
    }
}

#[test]
fn an_ouster_os1_32_legacy_capture_converts_to_the_reference_points() {
    converts_as_the_reference(Capture { name: "os1-32-legacy", record: OUSTER, ring_at: 3 });
}

#[test]
fn an_ouster_os2_128_rng19_capture_converts_to_the_reference_points() {
    converts_as_the_reference(Capture { name: "os2-128-rng19", record: OUSTER, ring_at: 3 });
}

#[test]
fn a_vlp16_capture_converts_to_the_reference_points() {
    converts_as_the_reference(Capture { name: "vlp16", record: VELODYNE, ring_at: 5 });
}

#[test]
fn an_hdl32e_capture_converts_to_the_reference_points() {
    converts_as_the_reference(Capture { name: "hdl32e", record: VELODYNE, ring_at: 5 });
}
