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
    let written = g2o::parse(&std::fs::read_to_string(&out).unwrap()).unwrap().graph;
    let error = written.error(&PoseGraphConfig::least_squares());
    assert!((error - printed).abs() < 1e-6, "file {error} vs printed {printed}");
    assert!(printed <= 517.925 * (1.0 + 1e-4), "{stdout}");
    let original = g2o::parse(&std::fs::read_to_string(&input).unwrap()).unwrap().graph;
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

#[test]
fn an_indefinite_information_matrix_is_optimised_and_warned_about_with_the_count() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("indefinite.g2o");
    // Two edges between two poses; the second's translation block [[1, 2], [2, 1]] is indefinite.
    let ok = "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 4 0 0 4 0 4";
    let bad = "1 2 0 0 0 0 1 0 0 0 0 1 0 0 0 4 0 0 4 0 4";
    let text = format!(
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 0.5 0 0 0 0 0 1\nFIX 0\n\
         EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {ok}\nEDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {bad}\n"
    );
    std::fs::write(&input, text).unwrap();
    let out = dir.path().join("out.g2o");
    let run = emr_edge(&["posegraph", input.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(stderr.contains("1 of 2 edges had an information matrix that is not positive semi-definite"), "{stderr}");
    assert!(stderr.contains("first on line 5"), "{stderr}");
    // Both edges say pose 1 is 1 m along x: the optimum puts it there.
    let written = g2o::parse(&std::fs::read_to_string(&out).unwrap()).unwrap().graph;
    assert!((written.poses()[1].translation.vector.x - 1.0).abs() < 1e-6, "{:?}", written.poses()[1]);
}
