//! `emr-station` end to end on real scans: `align` (global, vgicp, gicp) and `merge` against the
//! reference transforms of ../shared/data.

use std::path::Path;
use std::process::Command;

use cloud::formats::read_transform;
use cloud::se3::{PoseError, pose_error};
use nalgebra::{Isometry3, Matrix4};
use testkit::shared_data as data;

const ROOT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/..");

/// Runs `emr-station` from the project root; panics with its stderr on failure.
fn station(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_emr-station")).args(args).current_dir(ROOT).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "emr-station {args:?} failed:\n{stderr}");
    String::from_utf8(out.stdout).unwrap()
}

/// The 4x4 transform printed on the first four lines, and the confidence line.
fn printed_transform(stdout: &str) -> (Isometry3<f64>, String) {
    let lines: Vec<&str> = stdout.lines().collect();
    let values: Vec<f64> =
        lines[..4].iter().flat_map(|l| l.split_whitespace().map(|v| v.parse::<f64>().unwrap())).collect();
    let m = Matrix4::from_row_slice(&values);
    (cloud::se3::from_matrix(&m).expect("a rigid transform"), lines[4].to_owned())
}

fn within(e: PoseError, metres: f64, degrees: f64) -> bool {
    e.translation_m < metres && e.rotation_deg < degrees
}

#[test]
fn align_global_recovers_the_kitti_reverse_revisit() {
    let (s, t) = (data("kitti08_revisit/001500.bin"), data("kitti08_revisit/000720.bin"));
    let stdout = station(&["align", s.to_str().unwrap(), t.to_str().unwrap(), "--method", "global"]);
    let (transform, confidence) = printed_transform(&stdout);
    let truth = read_transform(&data("kitti08_revisit/T_000720_001500.txt")).unwrap();
    let e = pose_error(&transform, &truth);
    println!("{stdout}error {e:?}");
    assert!(within(e, 0.2, 1.0), "{e:?}");
    assert!(confidence.starts_with("confidence 0."), "{confidence}");
}

#[test]
fn align_vgicp_and_gicp_refine_the_gicp_pair_from_identity() {
    let (s, t) = (data("gicp_pair/source.ply"), data("gicp_pair/target.ply"));
    let truth = read_transform(&data("gicp_pair/T_target_source.txt")).unwrap();
    for method in ["vgicp", "gicp"] {
        let stdout = station(&["align", s.to_str().unwrap(), t.to_str().unwrap(), "--method", method]);
        let e = pose_error(&printed_transform(&stdout).0, &truth);
        println!("{method}: {e:?}");
        // The reference is good to a few tenths of a degree: only the translation is tight.
        assert!(within(e, 0.02, 1.0), "{method}: {e:?}");
    }
}

#[test]
fn align_reads_a_kitti_line_as_init_and_writes_the_moved_source() {
    let dir = tempfile::tempdir().unwrap();
    let (s, t) = (data("gicp_pair/source.ply"), data("gicp_pair/target.ply"));
    let truth = read_transform(&data("gicp_pair/T_target_source.txt")).unwrap();
    // A KITTI 3x4 line 30 cm and 2 degrees off the reference.
    let init = truth * Isometry3::new(nalgebra::Vector3::new(0.3, 0.0, 0.0), nalgebra::Vector3::z() * 0.035);
    let row = cloud::se3::to_kitti_row(&init).map(|v| v.to_string()).join(" ");
    let init_path = dir.path().join("init.txt");
    std::fs::write(&init_path, row + "\n").unwrap();
    let out = dir.path().join("moved.ply");
    let stdout = station(&[
        "align",
        s.to_str().unwrap(),
        t.to_str().unwrap(),
        "--method",
        "gicp",
        "--init",
        init_path.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let (transform, _) = printed_transform(&stdout);
    let e = pose_error(&transform, &truth);
    assert!(within(e, 0.02, 1.0), "{e:?}");
    let source = cloud::formats::read_cloud(&s).unwrap().cloud;
    let moved = cloud::formats::read_cloud(&out).unwrap().cloud;
    assert_eq!(moved.len(), source.len());
    let expected = transform.cast::<f32>() * source.points[0];
    assert!((moved.points[0] - expected).norm() < 1e-4);
}

/// Reads `transforms.json`; returns the document.
fn transforms(dir: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("transforms.json")).unwrap()).unwrap()
}

fn json_transform(v: &serde_json::Value) -> Isometry3<f64> {
    let rows: Vec<f64> =
        v.as_array().unwrap().iter().flat_map(|r| r.as_array().unwrap().iter().map(|x| x.as_f64().unwrap())).collect();
    cloud::se3::from_matrix(&Matrix4::from_row_slice(&rows)).unwrap()
}

#[test]
fn merge_writes_the_global_map_and_transforms_json() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (data("kitti08_revisit/001500.bin"), data("kitti08_revisit/000720.bin"));
    let truth = read_transform(&data("kitti08_revisit/T_000720_001500.txt")).unwrap(); // maps a into b
    let out = dir.path().join("merged");
    let stdout = station(&[
        "merge",
        a.to_str().unwrap(),
        b.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--reference",
        "1",
    ]);
    println!("{stdout}");
    let doc = transforms(&out);
    let maps = doc["maps"].as_array().unwrap();
    assert_eq!(maps.len(), 2);
    assert_eq!(maps[0]["input"], a.display().to_string());
    assert!(maps.iter().all(|m| m["status"] == "merged"));
    // Map 1 is the reference; map 0's transform maps its points into map 1's frame.
    assert_eq!(json_transform(&maps[1]["transform"]), Isometry3::identity());
    assert_eq!(maps[1]["confidence"], 1.0);
    let e = pose_error(&json_transform(&maps[0]["transform"]), &truth);
    assert!(within(e, 0.2, 1.0), "{e:?}");
    // The edge maps b into a: the inverse of the reference.
    let edge = &doc["edges"][0];
    assert_eq!((edge["a"].as_u64(), edge["b"].as_u64()), (Some(0), Some(1)));
    assert!(edge["inliers"].as_u64().unwrap() >= 15);
    let e = pose_error(&json_transform(&edge["transform"]), &truth.inverse());
    assert!(within(e, 0.2, 1.0), "{e:?}");
    assert!(doc["timing_ms"]["total"].as_f64().unwrap() > 0.0);
    let global = cloud::formats::read_cloud(&out.join("global_map.ply")).unwrap().cloud;
    assert!(global.len() > 10_000, "{} points", global.len());
    assert_top_view_shows_both_maps(&out.join("top_down.png"));
}

/// The top view decodes at the default size and many pixels carry each input's colour.
fn assert_top_view_shows_both_maps(path: &Path) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().expect("PNG header");
    let mut rgb = vec![0; reader.output_buffer_size().expect("buffer size")];
    let info = reader.next_frame(&mut rgb).expect("PNG data");
    let config = pictures::TopDownConfig::default();
    assert_eq!((info.width, info.height, info.color_type), (config.width, config.height, png::ColorType::Rgb));
    for i in 0..2 {
        let colour = config.palette.colour(i);
        let n = rgb.chunks_exact(3).filter(|p| pictures::Rgb(p[0], p[1], p[2]).is_tint_of(colour)).count();
        // Two KITTI scans, 120k points each, over a ~1000 x 900 px plot.
        assert!(n > 5_000, "input {i}: {n} pixels in its colour");
    }
}

#[test]
fn merge_reports_an_unusable_map_as_unmerged() {
    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty.bin");
    std::fs::write(&empty, []).unwrap();
    let a = data("kitti08_revisit/000720.bin");
    let stdout =
        station(&["merge", a.to_str().unwrap(), empty.to_str().unwrap(), "--out", dir.path().to_str().unwrap()]);
    assert!(stdout.contains("unmerged (unusable map"), "{stdout}");
    let doc = transforms(dir.path());
    assert_eq!(doc["maps"][0]["status"], "merged");
    assert_eq!(doc["maps"][1]["status"], "unmerged");
    assert_eq!(doc["maps"][1]["confidence"], 0.0);
    assert_eq!(json_transform(&doc["maps"][1]["transform"]), Isometry3::identity());
    assert!(doc["edges"].as_array().unwrap().is_empty());
}

#[test]
fn the_station_has_no_benchmark_command() {
    let help = station(&["--help"]);
    assert!(!help.lines().any(|l| l.trim_start().starts_with("bench")), "{help}");
}
