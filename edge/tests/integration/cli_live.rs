//! A live sensor end to end: `emr-edge sim --send` plays a simulated VLP-16's packets at the
//! sensor's pace to a loopback port, `emr-edge odometry udp:...` receives, decodes and registers
//! them, and the trajectory is judged against the simulator's ground truth beside the same run read
//! from files.

use std::net::UdpSocket;
use std::path::Path;
use std::process::{Command, Stdio};

use cloud::trajectory::{Trajectory, ate};

/// Sweeps sent: 5 s of a 10 Hz sensor. The last one never closes (a live stream has no end), so
/// the receiver takes one fewer.
const SWEEPS: usize = 50;

fn emr_edge() -> Command {
    Command::new(env!("CARGO_BIN_EXE_emr-edge"))
}

fn poses(path: &Path) -> Trajectory {
    Trajectory::parse_kitti(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn stats(dir: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("stats.json")).unwrap()).unwrap()
}

#[test]
fn a_simulated_vlp16_over_udp_tracks_as_the_same_run_from_files() {
    let dir = tempfile::tempdir().unwrap();
    let (live, files) = (dir.path().join("live"), dir.path().join("files"));
    let port = UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let frames = (SWEEPS - 1).to_string();
    let receiver = emr_edge()
        .args(["odometry", &format!("udp:127.0.0.1:{port}"), "--max-frames", &frames, "--no-loops"])
        .args(["--out", live.to_str().unwrap()])
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The receiver binds before it reads anything else; a sweep sent before that would be lost
    // whole and the count below would say so.
    std::thread::sleep(std::time::Duration::from_millis(500));
    let sent = emr_edge()
        .args(["sim", "--scenario", "warehouse-small", "--frames", &SWEEPS.to_string()])
        .args(["--send", &format!("127.0.0.1:{port}"), "--rate", "realtime"])
        .output()
        .unwrap();
    assert!(sent.status.success(), "{}", String::from_utf8_lossy(&sent.stderr));
    let received = receiver.wait_with_output().unwrap();
    assert!(received.status.success(), "{}", String::from_utf8_lossy(&received.stderr));

    let from_files = emr_edge()
        .args(["odometry", "sim:warehouse-small:1", "--max-frames", &frames, "--no-loops"])
        .args(["--out", files.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(from_files.status.success(), "{}", String::from_utf8_lossy(&from_files.stderr));

    // Every rotation sent is accounted for: registered, or dropped whole and counted.
    let live_stats = stats(&live);
    let losses = &live_stats["source_losses"];
    let registered = live_stats["frames"].as_u64().unwrap() as usize;
    let dropped = losses["dropped_scans"].as_u64().unwrap() as usize;
    assert_eq!(registered + dropped, SWEEPS - 1, "{live_stats}");
    assert_eq!(losses["partial_scans"], 0, "{losses}");
    if dropped > 0 || losses["packet_gaps"] != 0 {
        // A loaded machine may drop a whole scan (the odometry fell behind), which is counted
        // above; the trajectory then no longer pairs scan for scan with the truth.
        eprintln!("the live run lost data on this machine ({losses}); its accuracy is not compared");
        return;
    }
    let truth = poses(&files.join("poses_gt_kitti.txt"));
    let live_ate = ate(&truth.poses, &poses(&live.join("poses_kitti.txt")).poses, false).unwrap();
    let files_ate = ate(&truth.poses, &poses(&files.join("poses_kitti.txt")).poses, false).unwrap();
    assert!(
        (live_ate.rmse - files_ate.rmse).abs() < 0.01 && live_ate.rmse < 0.05,
        "ATE live {:.4} m, from files {:.4} m",
        live_ate.rmse,
        files_ate.rmse
    );
}
