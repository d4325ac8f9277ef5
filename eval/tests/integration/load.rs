//! `emr-eval load --json` on a small fleet: the binary's last line is one JSON object whose
//! figures add up. Speed is benchmarked, not tested: no timing is asserted.

use std::process::{Command, Output};

use serde_json::Value;

fn bench_load(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_emr-eval")).args(["load"]).args(args).output().unwrap()
}

/// `report[group][field]` as a number, failing with the report when absent.
fn number(report: &Value, path: &[&str]) -> f64 {
    path.iter().fold(report, |v, key| &v[key]).as_f64().unwrap_or_else(|| panic!("no number at {path:?} in {report}"))
}

#[test]
fn a_small_fleet_reports_every_keyframe_merged_with_its_latency() {
    let run = bench_load(&["--robots", "2", "--rate-hz", "5", "--seconds", "3", "--json", "--joint"]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "bench load failed:\n{stderr}");
    let stdout = String::from_utf8(run.stdout).unwrap();
    let last = stdout.lines().last().expect("a line on stdout");
    let report: Value = serde_json::from_str(last).unwrap_or_else(|e| panic!("{e}: {last}"));

    assert_eq!(number(&report, &["robots"]), 2.0);
    assert_eq!(number(&report, &["sent"]), 2.0 * 5.0 * 3.0, "{report}");
    assert_eq!(number(&report, &["received"]), number(&report, &["sent"]), "{report}");
    assert!(number(&report, &["merges"]) >= 1.0, "{report}");
    for group in ["merge_ms", "latency_ms"] {
        let [median, p95, max] = ["median", "p95", "max"].map(|q| number(&report, &[group, q]));
        assert!(0.0 <= median && median <= p95 && p95 <= max, "{group}: {report}");
    }
    // The bench waits until the station has published a map of everything it holds.
    assert_eq!(number(&report, &["unmapped"]), 0.0, "{report}");
    assert!(number(&report, &["queue_max"]) <= 1.0, "{report}");
    for when in ["start", "end", "peak"] {
        assert!(number(&report, &["rss_mb", when]) > 0.0, "{report}");
    }
    for field in ["mean_payload_bytes", "received_per_s", "max_backlog", "catch_up_s", "merged_robots"] {
        number(&report, &[field]);
    }
    // The final map is received too: when it merges every robot, a map that merged them all was seen.
    assert!(report.get("all_merged_s").is_some(), "all_merged_s, null when no map merged every robot: {report}");
    let all_merged = report["all_merged_s"].as_f64();
    if number(&report, &["merged_robots"]) == 2.0 {
        assert!(all_merged.is_some(), "{report}");
    }
    assert!(all_merged.is_none_or(|s| s > 0.0), "{report}");
    // The joint graph ran on the final map's merged robots: every keyframe of theirs is a pose.
    let merged = number(&report, &["merged_robots"]);
    assert_eq!(number(&report, &["joint", "robots"]), merged, "{report}");
    assert_eq!(number(&report, &["joint", "keyframes"]), merged * 5.0 * 3.0, "{report}");
    let (registered, kept, joined) = (
        number(&report, &["joint", "registered"]),
        number(&report, &["joint", "kept"]),
        number(&report, &["joint", "joined"]),
    );
    assert!(kept <= registered && 1.0 <= joined && joined <= merged, "{report}");
}

#[test]
fn a_load_without_robots_or_rate_is_a_clear_error() {
    for (flag, named) in [("--robots", "robots must be at least 1"), ("--rate-hz", "rate_hz must be a positive")] {
        let run = bench_load(&[flag, "0", "--json"]);
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(!run.status.success(), "{flag} 0 succeeded");
        assert!(stderr.contains(named), "{flag} 0:\n{stderr}");
        assert!(!stderr.contains("panicked"), "{flag} 0:\n{stderr}");
        assert!(run.stdout.is_empty(), "{flag} 0 printed {:?}", String::from_utf8_lossy(&run.stdout));
    }
}
