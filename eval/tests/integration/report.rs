//! `emr-eval report` on one short scenario: the four systems are in report.md and report.json, the
//! MR systems close no loop, and every figure is the one its run wrote in its own summary.json.

use std::path::Path;
use std::process::Command;

use serde_json::Value;

fn read_json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn the_report_holds_the_four_systems_and_their_runs_figures() {
    let out = tempfile::tempdir().unwrap();
    let dir = out.path().to_str().unwrap();
    let run = Command::new(env!("CARGO_BIN_EXE_emr-eval"))
        .args(["report", "--out", dir, "--scenario", "warehouse-small", "--frames", "30"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "emr-eval report failed:\n{stderr}");
    // Progress went to stderr, run by run.
    assert!(stderr.contains("warehouse-small, EMR-FLOAM: done"), "{stderr}");

    let md = std::fs::read_to_string(out.path().join("report.md")).unwrap();
    let report = read_json(&out.path().join("report.json"));
    let rows = report["rows"].as_array().unwrap();
    let names: Vec<&str> = rows.iter().map(|r| r["system"]["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["MR-ALOAM", "MR-FLOAM", "EMR-ALOAM", "EMR-FLOAM"]);
    for row in rows {
        let name = row["system"]["name"].as_str().unwrap();
        assert!(md.contains(&format!("| warehouse-small | {name} |")), "report.md lacks {name}:\n{md}");
        assert_eq!(row["system"]["loops"], name.starts_with("EMR"));
        assert_eq!(row["system"]["method"], if name.contains("ALOAM") { "aloam" } else { "floam" });
        if name.starts_with("MR") {
            assert_eq!(row["loops"], 0, "{name} closed loops");
        }
        // The run's own results, as the demo wrote them.
        let summary = read_json(&Path::new(row["out"].as_str().unwrap()).join("summary.json"));
        assert_eq!(row["map_points"], summary["global_map_points"], "{name}");
        assert_eq!(row["merges"], summary["timing"]["merges"], "{name}");
        let merges = summary["timing"]["merge_ms"].as_array().unwrap();
        assert_eq!(&row["last_merge_ms"], merges.last().unwrap(), "{name}");
        let robots = row["robots"].as_array().unwrap();
        let theirs = summary["robots"].as_array().unwrap();
        assert_eq!(robots.len(), 2, "warehouse-small has two robots");
        assert_eq!(robots.len(), theirs.len());
        let mut loops = 0;
        for (mine, theirs) in robots.iter().zip(theirs) {
            assert_eq!(mine["robot"], theirs["robot"]);
            assert_eq!(mine["scans"], 30);
            assert_eq!(mine["scans"], theirs["scans"]);
            assert_eq!(mine["loops"], theirs["loops"]);
            assert_eq!(mine["odometry_ate_m"], theirs["odometry_ate"]["aligned"]["rmse_m"], "{name}");
            assert_eq!(mine["loop_closed_ate_m"], theirs["loop_closed_ate"]["aligned"]["rmse_m"], "{name}");
            assert_eq!(mine["global_ate_m"], theirs["global_ate_unaligned"]["rmse_m"], "{name}");
            assert!(mine["median_scan_ms"].as_f64().unwrap() > 0.0);
            loops += mine["loops"].as_u64().unwrap();
        }
        assert_eq!(row["loops"], loops);
    }
}
