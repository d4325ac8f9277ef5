//! `emr-demo`'s command line: the demo's flags work with and without `run`, and the load benchmark
//! sits under `bench`.

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
fn bench_load_keeps_its_flags() {
    let help = emr_demo(&["bench", "load", "--help"]);
    for flag in ["--robots", "--rate-hz", "--seconds", "--scenario", "campus"] {
        assert!(help.contains(flag), "lacks {flag}:\n{help}");
    }
}
