//! `emr-eval`'s commands run from the workspace root on the real data of ../shared/data, as
//! docs/benchmarks.md runs them.

use std::process::Command;

fn emr_eval(args: &[&str]) -> String {
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
    let out = Command::new(env!("CARGO_BIN_EXE_emr-eval")).args(args).current_dir(root).output().unwrap();
    assert!(out.status.success(), "emr-eval {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn merge_defaults_to_the_kitti_revisit_and_meets_its_reference() {
    let stdout = emr_eval(&["merge", "--runs", "1"]);
    println!("{stdout}");
    assert!(stdout.contains("outcome: aligned"), "{stdout}");
    assert!(stdout.contains("error vs reference"), "{stdout}");
}

#[test]
fn every_benchmark_is_a_command_of_emr_eval() {
    let help = emr_eval(&["--help"]);
    for command in ["robustness", "load", "report", "merge", "codec", "gicp", "global", "posegraph", "loops", "sim"] {
        assert!(help.lines().any(|l| l.trim_start().starts_with(command)), "emr-eval lacks {command}:\n{help}");
    }
}
