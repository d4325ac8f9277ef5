//! Young maps of a fleet driving a campus whose streets look alike: the free-space check
//! ([`cloud::visibility`]) keeps look-alike placements out of every published global map, and the
//! true ones still come through. Every placement is checked against the simulator's truth.
//!
//! The fleet is the load bench's: the scenario's four robots plus four replays of them starting half
//! way through their runs, each sending a deskewed sweep at its true pose every half second, merged
//! after every few seconds of driving as the station does.

use std::sync::Arc;

use cloud::PointCloud;
use cloud::se3::pose_error;
use cloud::visibility::{RangeImage, View, Views};
use cloud::voxel::{VoxelMap, downsample};
use nalgebra::Isometry3;
use rayon::prelude::*;
use sim::{Scenario, SimConfig, Simulator};
use station::merge::{MergeConfig, MergeReport, Merger};

mod truth;
use truth::{truth, worst_error};

/// Keyframe voxel, metres (the outdoor odometry preset's, and the load bench's).
const KEYFRAME_VOXEL: f32 = 0.2;

/// One robot: its keyframes (pose in its own frame, deskewed sweep in the sensor frame) and where
/// its frame lies in the world.
struct Robot {
    keyframes: Vec<(Isometry3<f64>, PointCloud)>,
    frame: Isometry3<f64>,
}

/// Robot `index` of `scenario` from sweep `offset` on: `count` keyframes, one every `stride` sweeps.
fn robot(scenario: &Scenario, index: usize, offset: usize, count: usize, stride: usize) -> Robot {
    let sim = Simulator::new(scenario.clone(), index, SimConfig::default()).unwrap();
    let frame = sim.ground_truth(offset);
    let keyframes = (0..count)
        .into_par_iter()
        .map(|k| {
            let scan = sim.scan(offset + k * stride);
            let cloud = downsample(&sim.deskewed(&scan), KEYFRAME_VOXEL).unwrap();
            (frame.inverse() * scan.ground_truth, cloud)
        })
        .collect();
    Robot { keyframes, frame }
}

/// The campus fleet of the load bench: robots 0-3 from their start, 4-7 from half way through.
fn campus_fleet(count: usize, stride: usize) -> Vec<Robot> {
    let scenario = Scenario::by_name("campus").unwrap();
    let own = scenario.robots().len();
    (0..2 * own)
        .map(|i| {
            let sim = Simulator::new(scenario.clone(), i % own, SimConfig::default()).unwrap();
            let moving = (sim.trajectory().duration() / sim.config().sensor.period) as usize;
            robot(&scenario, i % own, (i / own) * moving / 2, count, stride)
        })
        .collect()
}

/// The map of a robot's first `n` keyframes, voxelised as the station's local maps are.
fn map_of(robot: &Robot, n: usize) -> PointCloud {
    let mut map = VoxelMap::new(KEYFRAME_VOXEL).unwrap();
    for (pose, cloud) in &robot.keyframes[..n] {
        let pose = pose.cast::<f32>();
        map.insert(cloud.points.iter().map(|p| pose * p));
    }
    map.cloud()
}

/// The views of a robot's first `n` keyframes.
fn views_of(robot: &Robot, n: usize, config: &MergeConfig) -> Arc<Views> {
    let views = robot.keyframes[..n]
        .iter()
        .map(|(pose, cloud)| View {
            pose: pose.cast::<f32>(),
            image: Arc::new(RangeImage::new(&cloud.points, &config.visibility)),
        })
        .collect();
    Arc::new(Views::new(views))
}

/// Grows every map by `step` keyframes at a time (with its views when `with_views`) and merges
/// until nothing is pending; returns the worst placement published on the way and the last report.
fn merge_as_they_drive(fleet: &[Robot], step: usize, with_views: bool) -> ((f64, f64), MergeReport) {
    let config = MergeConfig::outdoor();
    let frames = frames(fleet);
    let total = fleet[0].keyframes.len();
    let mut merger = Merger::new(config.clone()).unwrap();
    let mut worst = (0.0f64, 0.0f64);
    let mut last = None;
    for n in (step..=total).step_by(step) {
        for (id, robot) in fleet.iter().enumerate() {
            merger.grow(id, n as u64, map_of(robot, n));
            if with_views {
                merger.set_views(id, views_of(robot, n, &config));
            }
        }
        loop {
            let report = merger.merge().unwrap();
            let (t, r) = worst_error(&report, &frames);
            println!(
                "{n} keyframes, views {with_views}: merged {} of {}, pending {}, worst {t:.3} m {r:.2} deg",
                report.merged(),
                report.maps.len(),
                report.pending
            );
            worst = (worst.0.max(t), worst.1.max(r));
            let pending = report.pending;
            last = Some(report);
            if pending == 0 {
                break;
            }
        }
    }
    (worst, last.unwrap())
}

/// Each robot's frame in the world.
fn frames(fleet: &[Robot]) -> Vec<Isometry3<f64>> {
    fleet.iter().map(|r| r.frame).collect()
}

/// The pairs whose edge in `report` places them within 5 cm / 0.5° of the truth.
fn true_links(report: &MergeReport, fleet: &[Robot]) -> Vec<(usize, usize)> {
    let frames = frames(fleet);
    report
        .edges()
        .map(|e| (report.maps[e.a].id, report.maps[e.b].id, e))
        .filter(|(a, b, e)| {
            let error = pose_error(&e.transform, &truth(&frames, *a, *b));
            error.translation_m < 0.05 && error.rotation_deg < 0.5
        })
        .map(|(a, b, _)| (a, b))
        .collect()
}

#[test]
fn young_campus_maps_publish_no_look_alike_placement_with_their_views() {
    // 40 keyframes a robot, one every 5 sweeps (20 s at 2 m/s), merged every 8 keyframes.
    let fleet = campus_fleet(40, 5);
    let (blind, blind_report) = merge_as_they_drive(&fleet, 8, false);
    // Without the views the look-alike streets get in: what this test guards against.
    assert!(blind.0 > 1.0, "the unchecked merge placed every map within {:.3} m: nothing to guard", blind.0);
    let (seeing, report) = merge_as_they_drive(&fleet, 8, true);
    assert!(
        seeing.0 < 0.05 && seeing.1 < 0.5,
        "a published placement is {:.3} m / {:.2} deg off the truth",
        seeing.0,
        seeing.1
    );
    // ... and the true links still come through.
    let found = true_links(&report, &fleet);
    for link in true_links(&blind_report, &fleet) {
        assert!(found.contains(&link), "the true link {link:?} was lost to the check (found {found:?})");
    }
    assert!(!found.is_empty(), "no link at all");
}
