//! The demo end to end on a short run: two edges and a station in one process over
//! loopback; the files it writes are checked against the simulator's truth.

use demo::DemoConfig;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_demo_writes_maps_trajectories_and_scores() {
    let out = tempfile::tempdir().unwrap();
    let frames = 100;
    let config = DemoConfig { frames: Some(frames), out: out.path().to_owned(), ..DemoConfig::new() };
    let report = demo::run(config, std::future::pending()).await.expect("demo runs");

    assert_eq!(report.robots.len(), 2);
    for r in &report.robots {
        assert_eq!(r.frames, frames);
        assert!(r.keyframes >= 5, "robot {}: {} keyframes", r.robot, r.keyframes);
        // Ten seconds of driving: the odometry is within centimetres of the truth.
        assert!(r.odometry_ate.0.rmse < 0.05, "robot {} aligned ATE {:.3} m", r.robot, r.odometry_ate.0.rmse);
        let placement = report.global_map.robots.iter().find(|p| p.robot == r.robot).expect("placement");
        assert_eq!(placement.keyframes, r.keyframes, "the map was built from every keyframe");
    }

    let ply = out.path().join("global_map.ply");
    let cloud = cloud::formats::read_cloud(&ply).expect("global map PLY").cloud;
    assert_eq!(cloud.len() as u64, report.global_map.cloud.as_ref().unwrap().points);
    for robot in [1, 2] {
        for kind in ["estimated", "ground_truth"] {
            let path = out.path().join(format!("robot{robot}_{kind}_tum.txt"));
            let text = std::fs::read_to_string(&path).unwrap();
            assert_eq!(text.lines().count(), frames, "{}", path.display());
        }
    }
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["robots"].as_array().unwrap().len(), 2);
    assert!(summary["timing"]["wall_s"].as_f64().unwrap() > 0.0);
    assert!(summary["robots"][0]["odometry_ate"]["aligned"]["rmse_m"].as_f64().is_some());
    let placements: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("placements.json")).unwrap()).unwrap();
    assert_eq!(placements["robots"].as_array().unwrap().len(), 2);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_robot_that_restarts_is_placed_in_both_sessions() {
    // Robot 1 stops after 200 scans and starts again 50 scans on, in a new odometry frame: the
    // station keeps both sessions, drops nothing and places each where the simulator says.
    let out = tempfile::tempdir().unwrap();
    let (frames, restart) = (500, demo::Restart { robot: 1, scan: 200 });
    let config =
        DemoConfig { frames: Some(frames), restart: Some(restart), out: out.path().to_owned(), ..DemoConfig::new() };
    let report = demo::run(config, std::future::pending()).await.expect("demo runs");
    assert_eq!(report.conflicts, 0, "keyframes dropped as conflicts");
    let robot = report.robots.iter().find(|r| r.robot == 1).expect("robot 1");
    let sessions: Vec<(u64, usize)> = robot.sessions.iter().map(|s| (s.session, s.frames)).collect();
    assert_eq!(sessions, vec![(0, 200), (1, frames - 200 - demo::RESTART_GAP)]);
    for s in &robot.sessions {
        assert!(s.keyframes > 10, "session {}: {} keyframes", s.session, s.keyframes);
        assert_eq!(s.in_map, s.keyframes, "session {}: not every keyframe in the map", s.session);
        let (m, deg) = s.placement_error.unwrap_or_else(|| panic!("session {} not merged", s.session));
        println!("robot 1 session {}: placed {:.1} cm / {deg:.3} deg from the truth", s.session, m * 100.0);
        assert!(m < 0.05 && deg < 0.2, "session {}: {:.1} cm / {deg:.3} deg off", s.session, m * 100.0);
    }
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("summary.json")).unwrap()).unwrap();
    let robot1 = summary["robots"].as_array().unwrap().iter().find(|r| r["robot"] == 1).unwrap();
    assert_eq!(robot1["sessions"].as_array().unwrap().len(), 2);
    assert_eq!(summary["station"]["conflicts"], 0);
}
