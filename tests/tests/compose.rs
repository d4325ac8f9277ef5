//! The compose fleet, built and run here: `deploy/up.sh` builds the images without a registry
//! (FROM scratch, from the binaries this test run built and the cached `zenohd`) and starts
//! `docker-compose.yml`; the host fetches the global map with `emr-station save` on
//! 127.0.0.1:7447 until both robots are merged; the station's container is killed and started
//! again (it serves the same revision from its volume, the robots go on); `docker compose down -v`.
//!
//! Also checked, the usual container faults: the certificates written by the unprivileged user into
//! the volume, no container restarting, the station's health check passing, every container
//! stopping promptly on `docker stop` (SIGTERM reaches the process).
//!
//! Needs a Docker engine with compose (`.ci/run` checks). One compose project at a time: the ports
//! 127.0.0.1:7447 and 7448 are the compose file's.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use serde_json::Value;
use tests::{binary, scratch, zenohd};

const PROJECT: &str = "emr-compose-test";
const TIMEOUT: Duration = Duration::from_secs(900);

/// The compose project; `down -v` when dropped, whatever happened.
struct Fleet {
    root: PathBuf,
}

impl Fleet {
    fn up() -> Fleet {
        let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
        let fleet = Fleet { root };
        fleet.down(); // a crashed earlier run may have left it up
        let bin_dir = binary("emr-edge").parent().unwrap().to_owned();
        let out = Command::new("bash")
            .arg(fleet.root.join("deploy/up.sh"))
            .current_dir(&fleet.root)
            .env("EMR_BIN_DIR", &bin_dir)
            .env("EMR_ZENOHD", zenohd())
            .env("COMPOSE_PROJECT_NAME", PROJECT)
            .output()
            .expect("run deploy/up.sh");
        assert!(out.status.success(), "deploy/up.sh failed:\n{}", text(&out));
        println!(
            "{}",
            String::from_utf8_lossy(&out.stderr)
                .lines()
                .filter(|l| l.starts_with("built"))
                .collect::<Vec<_>>()
                .join("\n")
        );
        fleet
    }

    fn compose(&self, args: &[&str]) -> Output {
        let (program, mut full) = compose_command();
        full.extend(args.iter().map(|s| s.to_string()));
        Command::new(program)
            .args(&full)
            .current_dir(&self.root)
            .env("COMPOSE_PROJECT_NAME", PROJECT)
            .output()
            .expect("run docker compose")
    }

    fn must(&self, args: &[&str]) -> String {
        let out = self.compose(args);
        assert!(out.status.success(), "compose {args:?} failed:\n{}\n{}", text(&out), self.logs());
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    fn down(&self) {
        let _ = self.compose(&["down", "-v", "--remove-orphans", "--timeout", "20"]);
    }

    fn logs(&self) -> String {
        let out = self.compose(&["logs", "--no-color", "--tail", "30"]);
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// `docker inspect --format FORMAT` of a service's container.
    fn inspect(&self, service: &str, format: &str) -> String {
        let id = self.must(&["ps", "-a", "-q", service]).trim().to_owned();
        assert!(!id.is_empty(), "no container for {service}");
        let out = Command::new("docker").args(["inspect", "--format", format, &id]).output().expect("docker inspect");
        String::from_utf8_lossy(&out.stdout).trim().to_owned()
    }
}

impl Drop for Fleet {
    fn drop(&mut self) {
        if std::thread::panicking() {
            eprintln!("{}", self.logs());
        }
        self.down();
    }
}

/// `docker compose` if the plugin is there, else `docker-compose` (Debian's compose v1).
fn compose_command() -> (&'static str, Vec<String>) {
    let plugin = Command::new("docker").args(["compose", "version"]).output();
    if plugin.is_ok_and(|o| o.status.success()) {
        ("docker", vec!["compose".into()])
    } else {
        ("docker-compose", vec![])
    }
}

fn text(out: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

/// What `emr-station save` fetched from the host's loopback: the map's placements and its cloud.
struct Saved {
    placements: Value,
    cloud: Vec<u8>,
}

impl Saved {
    fn revision(&self) -> u64 {
        self.placements["revision"].as_u64().unwrap_or(0)
    }

    fn merged(&self) -> Vec<u64> {
        let robots = self.placements["robots"].as_array().cloned().unwrap_or_default();
        robots.iter().filter(|r| r["status"] == "merged").filter_map(|r| r["robot"].as_u64()).collect()
    }

    fn keyframes_of(&self, robot: u64) -> Option<u64> {
        let robots = self.placements["robots"].as_array()?;
        robots.iter().find(|r| r["robot"].as_u64() == Some(robot))?["keyframes"].as_u64()
    }

    fn keyframes(&self) -> u64 {
        let robots = self.placements["robots"].as_array().cloned().unwrap_or_default();
        robots.iter().filter_map(|r| r["keyframes"].as_u64()).sum()
    }
}

fn save(dir: &Path) -> Option<Saved> {
    let (ply, json) = (dir.join("map.ply"), dir.join("placements.json"));
    let out = Command::new(binary("emr-station"))
        .args(["save", "--fleet", "demo", "--timeout-s", "3", "--out"])
        .arg(&ply)
        .arg("--transforms")
        .arg(&json)
        .output()
        .expect("run emr-station save");
    if !out.status.success() {
        return None;
    }
    let placements = serde_json::from_str(&std::fs::read_to_string(&json).ok()?).ok()?;
    Some(Saved { placements, cloud: std::fs::read(&ply).ok()? })
}

/// Saves until `done` holds; panics with the containers' logs after `timeout`.
fn wait(fleet: &Fleet, dir: &Path, timeout: Duration, what: &str, done: impl Fn(&Saved) -> bool) -> Saved {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(s) = save(dir).filter(|s| done(s)) {
            return s;
        }
        assert!(Instant::now() < deadline, "no global map with {what} in {timeout:?}\n{}", fleet.logs());
        std::thread::sleep(Duration::from_secs(2));
    }
}

#[test]
fn the_compose_fleet_merges_survives_a_killed_station_and_stops_cleanly() {
    let started = Instant::now();
    let fleet = Fleet::up();
    let dir = scratch();
    println!("images built and fleet started in {:.0} s", started.elapsed().as_secs_f64());

    let merged = wait(&fleet, dir.path(), TIMEOUT, "both robots merged", |s| s.merged() == [1, 2]);
    println!(
        "both robots merged after {:.0} s: revision {}, {} keyframes",
        started.elapsed().as_secs_f64(),
        merged.revision(),
        merged.keyframes()
    );
    assert_eq!(fleet.inspect("certs", "{{.State.ExitCode}}"), "0", "the certificates were not written");
    for service in ["router", "station", "edge1", "edge2"] {
        let restarts = fleet.inspect(service, "{{.RestartCount}}");
        assert_eq!(restarts, "0", "{service} restarted {restarts} times\n{}", fleet.logs());
    }
    let health = wait_health(&fleet);
    assert_eq!(health, "healthy", "the station's health check: {health}\n{}", fleet.logs());
    the_tls_port_wants_a_fleet_certificate(&fleet, dir.path());

    // Hold the robots, let the station finish merging, and remember what it serves.
    fleet.must(&["pause", "edge1", "edge2"]);
    let before = wait_quiet(&fleet, dir.path());
    fleet.must(&["kill", "station"]);
    fleet.must(&["start", "station"]);
    let again = wait(&fleet, dir.path(), Duration::from_secs(60), "the station back", |_| true);
    println!(
        "station killed at revision {}, serves revision {} after its restart",
        before.revision(),
        again.revision()
    );
    assert_eq!(again.revision(), before.revision(), "a different revision after the restart");
    assert_eq!(again.placements, before.placements, "same revision, different placements after the restart");
    assert!(again.cloud == before.cloud, "same revision, different cloud after the restart");

    // The robots go on: the station takes their new keyframes.
    fleet.must(&["unpause", "edge1", "edge2"]);
    let later = wait(&fleet, dir.path(), Duration::from_secs(300), "the robots' new keyframes", |s| {
        s.revision() > before.revision() && s.keyframes() > before.keyframes() && s.merged() == [1, 2]
    });
    println!("robots went on: revision {}, {} keyframes", later.revision(), later.keyframes());

    // SIGTERM reaches every process: each exits 0 (below), not killed at the 20 s timeout. The
    // robots first: each says what it made as it exits, and the station must hold all of it (the
    // pause outlived their zenoh leases, the station was killed: what it missed, it fetched).
    let stopping = Instant::now();
    fleet.must(&["stop", "--timeout", "20", "edge1", "edge2"]);
    let robots_took = stopping.elapsed();
    let made: Vec<(u64, u64)> = [1, 2].iter().map(|&r| (r, keyframes_made(&fleet, r))).collect();
    let all = wait(&fleet, dir.path(), Duration::from_secs(120), "every keyframe the robots made", |s| {
        made.iter().all(|&(r, n)| s.keyframes_of(r) == Some(n))
    });
    println!("robots made {made:?} keyframes, the station holds them all at revision {}", all.revision());
    let stopping = Instant::now();
    fleet.must(&["stop", "--timeout", "20"]);
    let rest_took = stopping.elapsed();
    println!(
        "robots stopped in {:.1} s, station and router in {:.1} s",
        robots_took.as_secs_f64(),
        rest_took.as_secs_f64()
    );
    // A process that ignored SIGTERM would be killed at the 20 s timeout and exit 137: its exit code
    // tells, where the time it took would depend on the machine's load.
    for service in ["station", "edge1", "edge2"] {
        assert_eq!(fleet.inspect(service, "{{.State.ExitCode}}"), "0", "{service} did not exit cleanly on SIGTERM");
    }
}

/// The keyframes robot `r` says it made, from the line it logs as it exits.
fn keyframes_made(fleet: &Fleet, r: u64) -> u64 {
    let logs = fleet.must(&["logs", "--no-color", &format!("edge{r}")]);
    let prefix = format!("robot {r}: ");
    let line = logs.lines().rev().find_map(|l| l.split_once(&prefix).map(|(_, rest)| rest.to_owned()));
    let line = line.unwrap_or_else(|| panic!("edge{r} did not log its counts as it stopped\n{logs}"));
    // "{frames} scans, {keyframes} keyframes, ..."
    let count = line.split(", ").nth(1).and_then(|p| p.strip_suffix(" keyframes")).and_then(|n| n.parse().ok());
    count.unwrap_or_else(|| panic!("edge{r}'s last line: {line}"))
}

/// 127.0.0.1:7448 from the host: refused without a certificate, open to the station's (copied out
/// of the fleet volume).
fn the_tls_port_wants_a_fleet_certificate(fleet: &Fleet, dir: &Path) {
    let certs = fleet.must(&["ps", "-a", "-q", "certs"]).trim().to_owned();
    for file in ["ca.pem", "station.pem", "station.key"] {
        let from = format!("{certs}:/etc/emr/fleet/{file}");
        let out = Command::new("docker").args(["cp", &from]).arg(dir.join(file)).output().expect("docker cp");
        assert!(out.status.success(), "docker cp {from}: {}", text(&out));
    }
    let tls = |with_certificate: bool| {
        let mut link =
            serde_json::json!({ "root_ca_certificate": dir.join("ca.pem"), "enable_mtls": with_certificate });
        if with_certificate {
            link["connect_certificate"] = dir.join("station.pem").display().to_string().into();
            link["connect_private_key"] = dir.join("station.key").display().to_string().into();
        }
        let config = serde_json::json!({
            "mode": "client",
            "connect": { "endpoints": ["tls/127.0.0.1:7448"] },
            "scouting": { "multicast": { "enabled": false }, "gossip": { "enabled": false } },
            "transport": { "link": { "tls": link } },
        });
        let path = dir.join(format!("tls-{with_certificate}.json5"));
        std::fs::write(&path, config.to_string()).unwrap();
        Command::new(binary("emr-station"))
            .args(["save", "--fleet", "demo", "--timeout-s", "5", "--out"])
            .arg(dir.join("tls.ply"))
            .arg("--zenoh")
            .arg(&path)
            .output()
            .expect("run emr-station save")
    };
    let refused = tls(false);
    assert!(!refused.status.success(), "127.0.0.1:7448 let in a client without a certificate");
    let admitted = tls(true);
    assert!(admitted.status.success(), "the station's certificate on 127.0.0.1:7448: {}", text(&admitted));
}

/// The station's health once docker has run its check at least once.
fn wait_health(fleet: &Fleet) -> String {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let health = fleet.inspect("station", "{{.State.Health.Status}}");
        if health != "starting" || Instant::now() > deadline {
            return health;
        }
        std::thread::sleep(Duration::from_secs(2));
    }
}

/// The map once two saves 12 s apart (beyond the station's 10 s longest merge delay) agree.
fn wait_quiet(fleet: &Fleet, dir: &Path) -> Saved {
    let mut last = wait(fleet, dir, Duration::from_secs(60), "an answer", |_| true);
    for _ in 0..20 {
        std::thread::sleep(Duration::from_secs(12));
        let now = wait(fleet, dir, Duration::from_secs(60), "an answer", |_| true);
        if now.revision() == last.revision() {
            return now;
        }
        last = now;
    }
    panic!("the station kept merging with both robots paused\n{}", fleet.logs());
}
