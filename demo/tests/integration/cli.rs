//! `emr-demo`'s command line: the demo's flags work with and without `run`; it has no benchmark.

use std::process::Command;

fn emr_demo(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_emr-demo")).args(args).output().unwrap();
    assert!(out.status.success(), "emr-demo {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn the_demo_flags_are_at_the_top_and_under_run() {
    for args in [&["--help"][..], &["run", "--help"]] {
        let help = emr_demo(args);
        for flag in ["--scenario", "--robots", "--frames", "--realtime", "--out", "warehouse-large", "out/demo"] {
            assert!(help.contains(flag), "{args:?} lacks {flag}:\n{help}");
        }
    }
}

#[test]
fn the_benchmarks_live_in_emr_eval() {
    let help = emr_demo(&["--help"]);
    assert!(!help.contains("bench") && !help.contains("report"), "{help}");
}

#[test]
fn a_busy_foxglove_port_is_an_error_naming_it() {
    let busy = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = busy.local_addr().unwrap().to_string();
    let out = tempfile::tempdir().unwrap();
    let args = ["--frames", "1", "--no-record", "--foxglove", &addr, "--out", out.path().to_str().unwrap()];
    let run = Command::new(env!("CARGO_BIN_EXE_emr-demo")).args(args).output().unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success());
    assert!(stderr.contains(&format!("cannot serve the Foxglove live view on {addr}")), "{stderr}");
    assert!(stderr.contains("--no-foxglove"), "{stderr}");
}
