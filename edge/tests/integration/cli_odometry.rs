//! `emr-edge odometry` and `emr-edge eval` as a user runs them.

use std::path::PathBuf;
use std::process::{Command, Output};

fn emr_edge(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_emr-edge")).args(args).output().expect("emr-edge runs")
}

fn kitti00() -> PathBuf {
    testkit::shared_data("kitti00")
}

#[test]
fn odometry_writes_poses_and_stats_for_every_scan() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let data = kitti00();
    let (data, out_s) = (data.to_str().unwrap(), out.to_str().unwrap());
    let run = emr_edge(&["odometry", data, "--out", out_s, "--preset", "outdoor", "--no-deskew", "--max-frames", "6"]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    // Not a terminal: no progress bar, nothing on stderr.
    assert!(run.stderr.is_empty(), "{}", String::from_utf8_lossy(&run.stderr));
    let kitti = std::fs::read_to_string(out.join("poses_kitti.txt")).unwrap();
    let tum = std::fs::read_to_string(out.join("poses_tum.txt")).unwrap();
    assert_eq!(kitti.lines().count(), 6);
    assert_eq!(tum.lines().count(), 6);
    let first: Vec<f64> = kitti.lines().next().unwrap().split_whitespace().map(|v| v.parse().unwrap()).collect();
    assert_eq!(first, vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    let stats: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("stats.json")).unwrap()).unwrap();
    assert_eq!(stats["frames"], 6);
    assert!(stats["ms_per_frame"]["median"].as_f64().unwrap() > 0.0);
    assert!(stats["peak_rss_mb"].as_f64().unwrap() > 1.0);
    assert!(
        stats["rss_mb"]["after_first_scan"].as_f64().unwrap() > 1.0 && stats["rss_mb"]["end"].as_f64().unwrap() > 1.0
    );
    // The trajectory it wrote evaluates against the reference within 5 cm.
    let gt = dir.path().join("gt.txt");
    let reference = std::fs::read_to_string(kitti00().join("poses_velodyne.txt")).unwrap();
    std::fs::write(&gt, reference.lines().take(6).collect::<Vec<_>>().join("\n")).unwrap();
    let eval =
        emr_edge(&["eval", "--gt", gt.to_str().unwrap(), "--est", out.join("poses_kitti.txt").to_str().unwrap()]);
    let text = String::from_utf8_lossy(&eval.stdout);
    let ate: f64 = text
        .lines()
        .find(|l| l.starts_with("ATE RMSE unaligned"))
        .unwrap()
        .split_whitespace()
        .nth(3)
        .unwrap()
        .parse()
        .unwrap();
    assert!(ate < 0.05, "{text}");
}

#[test]
fn eval_by_hand() {
    // Truth: 0, 1, 2 m along x. Estimate: errors 0, 0.3 m (y) and 0.4 m (z): RMSE sqrt(0.25 / 3).
    let dir = tempfile::tempdir().unwrap();
    let row = |x: f64, y: f64, z: f64| format!("1 0 0 {x} 0 1 0 {y} 0 0 1 {z}\n");
    std::fs::write(dir.path().join("gt.txt"), [row(0.0, 0.0, 0.0), row(1.0, 0.0, 0.0), row(2.0, 0.0, 0.0)].concat())
        .unwrap();
    std::fs::write(dir.path().join("est.txt"), [row(0.0, 0.0, 0.0), row(1.0, 0.3, 0.0), row(2.0, 0.0, 0.4)].concat())
        .unwrap();
    let gt = dir.path().join("gt.txt");
    let est = dir.path().join("est.txt");
    let run = emr_edge(&["eval", "--gt", gt.to_str().unwrap(), "--est", est.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&run.stdout);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    assert!(text.contains(&format!("ATE RMSE unaligned  {:.4} m", (0.25f64 / 3.0).sqrt())), "{text}");
    // Unequal lengths without timestamps: a clear error naming the counts.
    std::fs::write(dir.path().join("short.txt"), row(0.0, 0.0, 0.0)).unwrap();
    let run =
        emr_edge(&["eval", "--gt", gt.to_str().unwrap(), "--est", dir.path().join("short.txt").to_str().unwrap()]);
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("ground truth has 3 poses, estimate 1"));
}

#[test]
fn odometry_errors_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let data = kitti00();
    let data = data.to_str().unwrap();
    let stderr = |args: &[&str]| {
        let run = emr_edge(args);
        assert!(!run.status.success());
        String::from_utf8_lossy(&run.stderr).into_owned()
    };
    let missing = dir.path().join("missing.toml");
    let out = dir.path().join("out");
    let (missing, out) = (missing.to_str().unwrap(), out.to_str().unwrap());
    let text = stderr(&["odometry", data, "--out", out, "--config", missing]);
    assert!(text.contains(&format!("cannot read {missing}")), "{text}");
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "[solver]\nno_such_key = 1\n").unwrap();
    let text = stderr(&["odometry", data, "--out", out, "--config", bad.to_str().unwrap()]);
    assert!(text.contains(&format!("{}: invalid configuration", bad.display())), "{text}");
    // An output directory that is a file.
    let file = dir.path().join("file");
    std::fs::write(&file, "").unwrap();
    let text = stderr(&["odometry", data, "--out", file.to_str().unwrap(), "--max-frames", "1"]);
    assert!(text.contains(&format!("cannot create {}", file.display())), "{text}");
}

#[test]
fn a_corrupt_scan_is_skipped_warned_and_counted() {
    // Four KITTI scans, the third cut to a size that is not a multiple of 16 bytes.
    let dir = tempfile::tempdir().unwrap();
    let scans = dir.path().join("velodyne");
    std::fs::create_dir(&scans).unwrap();
    for i in 0..4 {
        let name = format!("{i:06}.bin");
        let bytes = std::fs::read(kitti00().join("velodyne").join(&name)).unwrap();
        let keep = if i == 2 { bytes.len() - 5 } else { bytes.len() };
        std::fs::write(scans.join(&name), &bytes[..keep]).unwrap();
    }
    let out = dir.path().join("run");
    let args = ["odometry", dir.path().to_str().unwrap(), "--out", out.to_str().unwrap(), "--preset", "outdoor"];
    let run = emr_edge(&args);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    // Not a terminal, and still warned.
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(stderr.contains("skipped") && stderr.contains("000002.bin"), "{stderr}");
    let stats: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("stats.json")).unwrap()).unwrap();
    assert_eq!(stats["frames"], 3);
    let skipped = stats["skipped_scans"].as_array().unwrap();
    assert_eq!(skipped.len(), 1, "{skipped:?}");
    let reason = skipped[0]["reason"].as_str().unwrap();
    assert!(reason.contains("000002.bin") && reason.contains("multiple of 16"), "{reason}");
}

#[test]
fn loop_closure_files_are_written_by_default_and_not_with_no_loops() {
    let dir = tempfile::tempdir().unwrap();
    let data = kitti00();
    let (with, without) = (dir.path().join("emr"), dir.path().join("mr"));
    for (out, flag) in [(&with, None), (&without, Some("--no-loops"))] {
        let mut args = vec!["odometry", data.to_str().unwrap(), "--out", out.to_str().unwrap(), "--preset", "outdoor"];
        args.extend(["--no-deskew", "--max-frames", "8"]);
        args.extend(flag);
        let run = emr_edge(&args);
        assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    }
    // 8 scans over ~5 m revisit nothing: no loop, the optimised poses are the odometry's.
    let loops: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(with.join("loops.json")).unwrap()).unwrap();
    assert_eq!(loops["loops"], serde_json::json!([]));
    assert!(loops["rejected"].is_array());
    let read = |p: PathBuf| std::fs::read_to_string(p).unwrap();
    assert_eq!(read(with.join("poses_kitti.txt")), read(with.join("poses_odometry_kitti.txt")));
    assert_eq!(read(with.join("poses_kitti.txt")), read(without.join("poses_kitti.txt")));
    let stats: serde_json::Value = serde_json::from_str(&read(with.join("stats.json"))).unwrap();
    let keyframes = stats["loops"]["keyframes"].as_u64().unwrap();
    assert!(keyframes >= 2, "{stats}");
    // The graph: a vertex per keyframe, an odometry edge between consecutive ones.
    let graph = cloud::pose_graph::g2o::parse(&read(with.join("graph.g2o"))).unwrap().graph;
    assert_eq!((graph.poses().len() as u64, graph.edges().len() as u64), (keyframes, keyframes - 1));
    for file in ["loops.json", "graph.g2o", "poses_odometry_kitti.txt"] {
        assert!(!without.join(file).exists(), "{file} written with --no-loops");
    }
    assert!(
        serde_json::from_str::<serde_json::Value>(&read(without.join("stats.json"))).unwrap().get("loops").is_none()
    );
}

#[test]
fn odometry_records_the_run_for_foxglove() {
    let dir = tempfile::tempdir().unwrap();
    let (out, mcap_path) = (dir.path().join("run"), dir.path().join("run.mcap"));
    let (out_s, mcap_s) = (out.to_str().unwrap(), mcap_path.to_str().unwrap());
    let args = ["odometry", "sim:warehouse-small:1", "--out", out_s, "--max-frames", "40", "--record", mcap_s];
    let run = emr_edge(&[&args[..], &["--robot", "2"]].concat());
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let stats: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("stats.json")).unwrap()).unwrap();
    let bytes = std::fs::read(&mcap_path).unwrap();
    let mut counts = std::collections::BTreeMap::<String, (u64, String)>::new();
    for message in mcap::MessageStream::new(&bytes).expect("an MCAP file") {
        let channel = message.expect("a readable message").channel;
        let schema = channel.schema.as_ref().map_or(channel.message_encoding.clone(), |s| s.name.clone());
        counts.entry(channel.topic.clone()).or_insert((0, schema)).0 += 1;
    }
    let count = |topic: &str, schema: &str| {
        let (n, s) = counts.get(topic).unwrap_or_else(|| panic!("no {topic} in {counts:?}"));
        assert_eq!(s, schema, "{topic}");
        *n
    };
    assert_eq!(count("/tf", "foxglove.FrameTransforms"), stats["frames"].as_u64().unwrap(), "a frame per scan");
    let keyframes = stats["keyframes"].as_u64().unwrap();
    assert!(keyframes >= 2);
    assert_eq!(count("/robot2/keyframe", "foxglove.PointCloud"), keyframes, "every keyframe");
    assert_eq!(count("/robot2/status", "json"), keyframes, "a status per keyframe");
    assert!(count("/robot2/trajectory", "foxglove.PosesInFrame") >= 1);
    assert!(count("/robot2/loops", "foxglove.SceneUpdate") >= 1);
}

#[test]
fn the_seed_changes_the_simulated_noise_and_nothing_else() {
    let dir = tempfile::tempdir().unwrap();
    let run = |name: &str, seed: &str| {
        let out = dir.path().join(name);
        let args = ["odometry", "sim:warehouse-small:1", "--no-loops", "--max-frames", "8", "--seed", seed];
        let run = emr_edge(&[&args[..], &["--out", out.to_str().unwrap()]].concat());
        assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
        let read = |file: &str| std::fs::read_to_string(out.join(file)).unwrap();
        (read("poses_kitti.txt"), read("poses_gt_kitti.txt"))
    };
    let (first, truth) = run("a", "0");
    let (again, _) = run("b", "0");
    let (other, other_truth) = run("c", "7");
    assert_eq!(first, again, "one seed, one run");
    assert_eq!(truth, other_truth, "the robot drives the same path");
    assert_ne!(first, other, "another seed, other noise, other estimates");
    let bad = emr_edge(&["odometry", "sim:warehouse-small:1", "--seed", "one", "--out", dir.path().to_str().unwrap()]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--seed"), "{}", String::from_utf8_lossy(&bad.stderr));
}

/// The run's own figures against a reference: a run that did not track (an aligned ATE above 1 %
/// of the path) must say so in stats.json and on stderr; a run that tracked counts no scan it
/// could not fit.
fn health_against_the_reference(
    data: &str,
    reference: &std::path::Path,
    args: &[&str],
) -> (f64, serde_json::Value, String) {
    use cloud::trajectory::{Trajectory, ate};
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let mut all = vec!["odometry", data, "--out", out.to_str().unwrap(), "--no-loops"];
    all.extend(args);
    let run = emr_edge(&all);
    let stderr = String::from_utf8_lossy(&run.stderr).into_owned();
    assert!(run.status.success(), "{stderr}");
    let estimate = Trajectory::parse_kitti(&std::fs::read_to_string(out.join("poses_kitti.txt")).unwrap()).unwrap();
    let truth = Trajectory::parse_kitti(&std::fs::read_to_string(reference).unwrap()).unwrap();
    let error = ate(&truth.poses, &estimate.poses, true).unwrap().rmse / truth.length();
    let stats = serde_json::from_str(&std::fs::read_to_string(out.join("stats.json")).unwrap()).unwrap();
    (error, stats, stderr)
}

#[test]
fn a_solid_state_run_tracks_by_the_dense_fit_and_a_run_that_does_not_track_says_so() {
    // The handheld solid-state run (no rings, ~70 deg view) against FAST-LIO2's trajectory: no
    // scan lines, so each scan's voxel-shape fit is judged against the dense fit, which places
    // most of them; none is lost.
    let livox = testkit::shared_data("livox_hku2");
    let scans = livox.join("scans");
    let (error, stats, _) = health_against_the_reference(scans.to_str().unwrap(), &livox.join("odom_poses.txt"), &[]);
    println!("livox: aligned ATE {:.2} % of the path; {stats}", error * 100.0);
    let frames = stats["frames"].as_u64().unwrap();
    let dense = stats["dense_scans"].as_u64().unwrap();
    assert!(dense * 4 > frames * 3, "{dense} of {frames} scans placed by the dense fit: {stats}");
    assert_eq!((stats["unfitted_scans"].as_u64(), stats["recoveries"]["lost"].as_u64()), (Some(0), Some(0)), "{stats}");
    // The target, 1 % of the path (0.58 %; KISS-ICP 1.4 %; 61.6 % without the dense
    // fit and with the derived channels).
    assert!(error < 0.01, "livox: aligned ATE {:.2} % of the path", error * 100.0);

    // The same scans with their stamps beside them: FAST-LIO2's keyframes, kept by distance
    // walked, 0.1-6 s apart. Carrying the last motion over the time since it put the run 8.5 %
    // of its path off; the extrapolation that predicted better (by scan) keeps it in 1 %.
    let dir = tempfile::tempdir().unwrap();
    let stamped = dir.path().join("stamped");
    std::fs::create_dir(&stamped).unwrap();
    for entry in std::fs::read_dir(&scans).unwrap() {
        let entry = entry.unwrap();
        std::os::unix::fs::symlink(entry.path(), stamped.join(entry.file_name())).unwrap();
    }
    std::fs::copy(livox.join("times.txt"), stamped.join("times.txt")).unwrap();
    let (error, stats, _) = health_against_the_reference(stamped.to_str().unwrap(), &livox.join("odom_poses.txt"), &[]);
    println!("livox with stamps: aligned ATE {:.2} % of the path", error * 100.0);
    assert_eq!(stats["recoveries"]["lost"].as_u64(), Some(0), "{stats}");
    assert!(error < 0.01, "livox with stamps: aligned ATE {:.2} % of the path", error * 100.0);

    // Every 8th scan of it (1.6 m and up to 30 deg between scans, a 70 deg view): the fits do
    // not hold (aligned ATE 12 % of the path), and the run must say so.
    let thinned = dir.path().join("every8");
    std::fs::create_dir(&thinned).unwrap();
    let mut names: Vec<_> = std::fs::read_dir(&scans).unwrap().map(|e| e.unwrap().file_name()).collect();
    names.sort();
    let pick = |i: usize| i.is_multiple_of(8);
    for (i, name) in names.iter().enumerate().filter(|(i, _)| pick(*i)) {
        std::fs::copy(scans.join(name), thinned.join(format!("{:06}.pcd", i / 8))).unwrap();
    }
    let every8 = |file: &str| -> String {
        let text = std::fs::read_to_string(livox.join(file)).unwrap();
        text.lines().enumerate().filter(|(i, _)| pick(*i)).map(|(_, l)| format!("{l}\n")).collect()
    };
    std::fs::write(thinned.join("times.txt"), every8("times.txt")).unwrap();
    let reference = dir.path().join("every8_poses.txt");
    std::fs::write(&reference, every8("odom_poses.txt")).unwrap();
    let (error, stats, stderr) = health_against_the_reference(thinned.to_str().unwrap(), &reference, &[]);
    let unhealthy = stats["unfitted_scans"].as_u64().unwrap() + stats["recoveries"]["lost"].as_u64().unwrap();
    println!(
        "livox every 8th scan: aligned ATE {:.1} % of the path; unfitted {}, lost {}",
        error * 100.0,
        stats["unfitted_scans"],
        stats["recoveries"]["lost"]
    );
    if error > 0.01 {
        assert!(unhealthy > 0, "ATE {:.1} % of the path, reported healthy: {stats}", error * 100.0);
        assert!(stderr.contains("could not be fitted") || stderr.contains("were lost"), "{stderr}");
    }

    // The shared KITTI frames, where the odometry tracks: nothing unfitted, nothing lost.
    let kitti = kitti00();
    let (error, stats, _) = health_against_the_reference(
        kitti.to_str().unwrap(),
        &kitti.join("poses_velodyne.txt"),
        &["--preset", "outdoor", "--no-deskew"],
    );
    assert!(error < 0.01, "KITTI 00: aligned ATE {:.2} % of the path", error * 100.0);
    assert_eq!((stats["unfitted_scans"].as_u64(), stats["recoveries"]["lost"].as_u64()), (Some(0), Some(0)), "{stats}");
    assert_eq!(stats["dense_scans"].as_u64(), Some(0), "{stats}");
}
