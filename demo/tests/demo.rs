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
