//! `deploy/systemd/emr-edge.service`: systemd accepts the unit as it is, with its hardening, and the
//! real `emr-edge` accepts the command line it starts.

use std::path::PathBuf;
use std::process::Command;

use tests::{binary, scratch};

fn unit() -> String {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../deploy/systemd/emr-edge.service");
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn systemd_verifies_the_unit_without_a_warning() {
    let dir = scratch();
    // verify checks that ExecStart's binary exists: point it at the one this run built.
    let text = unit().replace("/usr/local/bin/emr-edge", &binary("emr-edge").display().to_string());
    let path = dir.path().join("emr-edge.service");
    std::fs::write(&path, text).unwrap();
    let out = Command::new("systemd-analyze").arg("verify").arg(&path).output().expect("systemd-analyze (systemd)");
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    // Lines about the host's own units are not ours.
    let ours: Vec<&str> = said.lines().filter(|l| l.contains("emr-edge")).collect();
    assert!(out.status.success() && ours.is_empty(), "systemd-analyze verify: {said}");
    for key in [
        "DynamicUser=yes",
        "ProtectSystem=strict",
        "NoNewPrivileges=yes",
        "Restart=on-failure",
        "CapabilityBoundingSet=",
    ] {
        assert!(unit().lines().any(|l| l == key), "the unit lacks {key}");
    }
}

#[test]
fn emr_edge_accepts_the_units_command_line() {
    let unit = unit();
    // ExecStart= and its continuation lines (ending in a backslash).
    let mut exec = String::new();
    for line in unit.lines().skip_while(|l| !l.starts_with("ExecStart=")) {
        exec.push_str(line.trim_end_matches('\\'));
        exec.push(' ');
        if !line.ends_with('\\') {
            break;
        }
    }
    let exec = exec.strip_prefix("ExecStart=").unwrap().to_owned();
    let dir = scratch();
    let vars = [
        ("${EMR_FLEET}", "demo".to_owned()),
        ("${EMR_ROBOT}", "3".to_owned()),
        ("${EMR_SOURCE}", dir.path().join("no-such-recording.bag").display().to_string()),
        ("$EMR_ARGS", "--preset indoor".to_owned()),
        // systemd's, for StateDirectory=.
        ("${STATE_DIRECTORY}", dir.path().join("state").display().to_string()),
    ];
    let line = vars.iter().fold(exec, |l, (k, v)| l.replace(k, v));
    let mut words = line.split_whitespace();
    let program = words.next().unwrap();
    assert_eq!(program, "/usr/local/bin/emr-edge");
    let out = Command::new(binary("emr-edge")).args(words).output().expect("run emr-edge");
    let err = String::from_utf8_lossy(&out.stderr);
    // Every option is known: it stops on a missing input it names (the robot's zenoh file, here), not
    // on its arguments (clap's errors end in a usage line and exit 2).
    assert!(!out.status.success(), "emr-edge ran without its inputs");
    assert_ne!(out.status.code(), Some(2), "{err}");
    assert!(!err.contains("Usage:"), "{err}");
    assert!(err.contains("/etc/emr/robot-3.json5") || err.contains("no-such-recording.bag"), "{err}");
}
