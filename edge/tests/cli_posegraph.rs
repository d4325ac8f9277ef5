//! `emr-edge posegraph` as a user runs it.

use std::process::{Command, Output};

use cloud::pose_graph::{PoseGraphConfig, g2o};

fn emr_edge(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_emr-edge")).args(args).output().expect("emr-edge runs")
}

/// The number after `label` on the line that starts with it.
fn figure(stdout: &str, label: &str) -> f64 {
    let line = stdout.lines().find(|l| l.starts_with(label)).unwrap_or_else(|| panic!("no {label:?} in {stdout}"));
    line[label.len()..].split_whitespace().next().unwrap().parse().unwrap()
}

#[test]
fn posegraph_writes_the_graph_whose_error_it_prints() {
    let dir = tempfile::tempdir().unwrap();
    let input = testkit::shared_data("posegraph/smallGrid3D.g2o");
    let out = dir.path().join("out.g2o");
    let run = emr_edge(&["posegraph", input.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    assert!(run.stderr.is_empty(), "{}", String::from_utf8_lossy(&run.stderr));
    let (initial, printed) = (figure(&stdout, "initial error"), figure(&stdout, "final error"));
    assert!((initial - 83894.3).abs() < 0.1, "{stdout}");
    assert!(figure(&stdout, "iterations") >= 1.0 && figure(&stdout, "optimiser") > 0.0, "{stdout}");
    // The written poses cost what was printed (six decimals), and the graph is the input's.
    let written = g2o::parse(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let error = written.error(&PoseGraphConfig::least_squares());
    assert!((error - printed).abs() < 1e-6, "file {error} vs printed {printed}");
    assert!(printed <= 517.925 * (1.0 + 1e-4), "{stdout}");
    let original = g2o::parse(&std::fs::read_to_string(&input).unwrap()).unwrap();
    assert_eq!((written.ids(), written.edges()), (original.ids(), original.edges()));
}

#[test]
fn posegraph_errors_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out.g2o");
    let stderr = |input: &std::path::Path, extra: &[&str]| {
        let mut args = vec!["posegraph", input.to_str().unwrap(), "--out", out.to_str().unwrap()];
        args.extend(extra);
        let run = emr_edge(&args);
        assert!(!run.status.success());
        String::from_utf8_lossy(&run.stderr).into_owned()
    };
    let missing = dir.path().join("missing.g2o");
    let text = stderr(&missing, &[]);
    assert!(text.contains(&format!("cannot read {}", missing.display())), "{text}");
    let bad = dir.path().join("bad.g2o");
    std::fs::write(&bad, "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 9 0 0 0 0 0 0 1\n").unwrap();
    let text = stderr(&bad, &[]);
    assert!(text.contains(&format!("{}: line 2: unknown vertex id 9", bad.display())), "{text}");
    let good = testkit::shared_data("posegraph/smallGrid3D.g2o");
    let text = stderr(&good, &["--kernel", "cauchy:-1"]);
    assert!(text.contains("invalid kernel"), "{text}");
}
