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
use station::merge::estimate::{Refinement, refine};
use station::merge::{MergeConfig, MergeReport, Merger, PreparedMap, track_pair};

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
    merge_as_they_drive_with(fleet, step, with_views, MergeConfig::outdoor())
}

/// [`merge_as_they_drive`] with `config`.
fn merge_as_they_drive_with(
    fleet: &[Robot],
    step: usize,
    with_views: bool,
    config: MergeConfig,
) -> ((f64, f64), MergeReport) {
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

#[test]
fn a_young_map_turned_upside_down_is_not_published() {
    // The load bench's robots 2 and 4 (campus robots 1 and 3 from their start), a keyframe every
    // sweep as the bench sends them, merged every 2 keyframes as they drive. At 14 keyframes
    // their ground fits itself with one map turned upside down about it (roll 180 deg, 20 RANSAC
    // inliers on the ground, every sampled surfel agreeing with the free space: the turned map
    // lies below the other's ground, where no ray went); the station published robot 4 153 m /
    // 180 deg off so, with guided RANSAC samples and with uniform ones.
    let scenario = Scenario::by_name("campus").unwrap();
    let fleet: Vec<Robot> = [1, 3].into_iter().map(|i| robot(&scenario, i, 0, 40, 1)).collect();
    let mut uniform = MergeConfig::outdoor();
    uniform.pairwise.global.ransac.guided_draws = 0;
    uniform.pairwise.global.ransac.max_iterations = 200_000;
    for config in [MergeConfig::outdoor(), uniform] {
        let unchecked = MergeConfig { max_tilt_deg: 180.0, ..config.clone() };
        let (blind, _) = merge_as_they_drive_with(&fleet, 2, true, unchecked);
        assert!(
            blind.1 > 90.0,
            "without the tilt check every placement is within {:.1} deg: nothing to guard",
            blind.1
        );
        let (worst, _) = merge_as_they_drive_with(&fleet, 2, true, config);
        assert!(
            worst.0 < 0.05 && worst.1 < 0.5,
            "a published placement is {:.3} m / {:.2} deg off the truth",
            worst.0,
            worst.1
        );
    }
}

/// Robot `index` of the indoor `scenario`'s whole run, a keyframe every `stride` sweeps, as the
/// station holds it: one map with its views.
fn indoor_robot(scenario: &Scenario, index: usize, stride: usize) -> Robot {
    let sim = Simulator::new(scenario.clone(), index, SimConfig::default()).unwrap();
    let sweeps = (sim.trajectory().duration() / sim.config().sensor.period) as usize;
    robot(scenario, index, 0, sweeps / stride, stride)
}

/// Merges whole robot maps (with their views when `with_views`) once.
fn merge_whole(fleet: &[Robot], config: &MergeConfig, with_views: bool) -> MergeReport {
    let mut merger = Merger::new(config.clone()).unwrap();
    for (id, robot) in fleet.iter().enumerate() {
        let n = robot.keyframes.len();
        merger.grow(id, n as u64, map_of(robot, n));
        if with_views {
            merger.set_views(id, views_of(robot, n, config));
        }
    }
    merger.merge().unwrap()
}

/// The first `n` keyframes of every robot.
fn first(fleet: &[Robot], n: usize) -> Vec<Robot> {
    fleet
        .iter()
        .map(|r| Robot { keyframes: r.keyframes[..n.min(r.keyframes.len())].to_vec(), frame: r.frame })
        .collect()
}

/// What a report concluded for its pairs, for the failure messages.
fn verdicts(report: &MergeReport) -> Vec<String> {
    report
        .pairs
        .iter()
        .map(|p| match p.verdict.edge() {
            Some(e) => format!("edge, {} inliers, acceptance {:?}", e.inliers, e.acceptance.map(|a| a.index())),
            None => format!("{:?}", p.verdict),
        })
        .collect()
}

/// Grows both maps of `fleet` by `step` keyframes at a time with their views and merges as a
/// station does, until nothing is pending; then settles. Returns the worst placement published,
/// whether any merge placed every map, and the settled report.
fn drive_and_settle(fleet: &[Robot], step: usize, config: &MergeConfig) -> ((f64, f64), bool, MergeReport) {
    let frames = frames(fleet);
    let mut merger = Merger::new(config.clone()).unwrap();
    let (mut worst, mut all_merged) = ((0.0f64, 0.0f64), false);
    let total = fleet.iter().map(|r| r.keyframes.len()).min().unwrap();
    let mut judge = |report: &MergeReport| {
        let (t, r) = worst_error(report, &frames);
        println!("merged {}, worst {t:.3} m {r:.2} deg; {:?}", report.merged(), verdicts(report));
        worst = (worst.0.max(t), worst.1.max(r));
        all_merged |= report.merged() == fleet.len();
    };
    let mut n = step;
    loop {
        for (id, robot) in first(fleet, n).iter().enumerate() {
            merger.grow(id, n as u64, map_of(robot, robot.keyframes.len()));
            merger.set_views(id, views_of(robot, robot.keyframes.len(), config));
        }
        loop {
            let report = merger.merge().unwrap();
            judge(&report);
            if report.pending == 0 {
                break;
            }
        }
        if n == total {
            break;
        }
        n = (n + step).min(total);
    }
    let settled = loop {
        merger.settle();
        let report = merger.merge().unwrap();
        judge(&report);
        if report.pending == 0 {
            break report;
        }
    };
    (worst, all_merged, settled)
}

#[test]
fn robots_sharing_only_a_door_are_found_past_the_look_alike_hall() {
    // warehouse-small: two halls of racks joined by one door, a robot in each. The best-supported
    // placement of the east robot's map is often the west hall itself (the halls look alike); what
    // the robots saw through the door refutes it, and the next distinct placement is the true one.
    let scenario = Scenario::by_name("warehouse-small").unwrap();
    let fleet: Vec<Robot> = (0..2).map(|i| indoor_robot(&scenario, i, 5)).collect();
    let total = fleet.iter().map(|r| r.keyframes.len()).min().unwrap();
    let config = MergeConfig::indoor();
    let blind = MergeConfig { max_alternatives: 0, ..config.clone() };
    let (bar_m, bar_deg) = (0.10, 0.5);
    let frames = frames(&fleet);
    // Each eighth of the east robot's run from a quarter on, merged from scratch: placements
    // published are right, and looking past a refuted placement finds the door more often.
    let (mut found, mut found_blind) = (0, 0);
    for n in (total / 4..total).step_by(total / 8) {
        let maps = first(&fleet, n);
        for (config, count) in [(&config, &mut found), (&blind, &mut found_blind)] {
            let report = merge_whole(&maps, config, true);
            let (t, r) = worst_error(&report, &frames);
            println!("{n} keyframes, alternatives {}: {:?}", config.max_alternatives, verdicts(&report));
            assert!(t < bar_m && r < bar_deg, "{n} keyframes: a placement {t:.3} m / {r:.2} deg off the truth");
            *count += usize::from(report.merged() == 2);
        }
    }
    assert!(found > found_blind, "the door was found {found} times, {found_blind} without the alternatives");
    // As a station merges them while they drive: the door's 15-25 inliers among thousands of
    // correspondences are there in some rounds only; once found the link is tracked, and kept
    // when a later search draws worse (the settling search after the last growth does).
    let (worst, _, settled) = drive_and_settle(&fleet, total / 8, &config);
    assert!(worst.0 < bar_m && worst.1 < bar_deg, "a placement {:.3} m / {:.2} deg off the truth", worst.0, worst.1);
    assert_eq!(settled.merged(), 2, "the door was lost or not found: {:?}", verdicts(&settled));
}

#[test]
fn a_tracked_door_holds_where_vgicp_does_not_narrow_the_gap() {
    // The east robot's map whole (it finished first), the west robot's growing in small steps from
    // the merge that found the door: each step follows the link from the last one, as a round does.
    // VGICP started at its own optimum moves a few millimetres and the gap between the maps changes
    // by a ten-thousandth either way; when a gap that did not narrow counted as a lost link, the
    // search that followed drew the look-alike hall and the east robot left the published map in
    // half the demo runs. And the gap must judge the refinement where the maps share
    // only a door: a point-to-point gap kept the link 7.5 cm from the truth (keyframes every 4th
    // sweep), a capped gap over all points 5.0 cm (every 6th), against VGICP's centimetre. Both
    // keyframe strides, so both samplings of the maps.
    let scenario = Scenario::by_name("warehouse-small").unwrap();
    let config = MergeConfig::indoor();
    for stride in [4, 6] {
        let fleet: Vec<Robot> = (0..2).map(|i| indoor_robot(&scenario, i, stride)).collect();
        let (west, east) = (fleet[0].keyframes.len(), fleet[1].keyframes.len());
        let prepare = |id: usize, n: usize| {
            PreparedMap::new(map_of(&fleet[id], n), Some(views_of(&fleet[id], n, &config)), &config)
        };
        // The west robot's map grows from a third of its run until a merge finds the door.
        let mut merger = Merger::new(config.clone()).unwrap();
        merger.grow(1, east as u64, map_of(&fleet[1], east));
        merger.set_views(1, views_of(&fleet[1], east, &config));
        let (mut start, mut found) = (west / 3, None);
        while found.is_none() && start < west {
            merger.grow(0, start as u64, map_of(&fleet[0], start));
            merger.set_views(0, views_of(&fleet[0], start, &config));
            found = merger.merge().unwrap().edges().next().cloned();
            start += west / 12;
        }
        let mut edge = found.unwrap_or_else(|| panic!("stride {stride}: the door not found"));
        let east_map = prepare(1, east);
        let true_link = truth(&frames(&fleet), 0, 1);
        let (mut held, steps) = (0, 16);
        for k in 1..=steps {
            let n = start + (west - start) * k / steps;
            let west_map = prepare(0, n);
            held += usize::from(refine(&east_map, &west_map, &edge.transform, &config) == Refinement::Held);
            edge = track_pair((0, &west_map), (1, &east_map), &edge, &config)
                .unwrap_or_else(|| panic!("stride {stride}: the link lost at {n} of {west} keyframes"));
            let e = pose_error(&edge.transform, &true_link);
            println!(
                "stride {stride}, {n} keyframes: {:.3} m {:.2} deg, confidence {:.3}",
                e.translation_m, e.rotation_deg, edge.confidence.score
            );
            // Maps from true poses: what is left is the refinement's, about a centimetre.
            assert!(
                e.translation_m < 0.03 && e.rotation_deg < 0.1,
                "stride {stride}, {n} keyframes: {e:?} off the truth"
            );
        }
        // What the test is about: steps where VGICP did not narrow the gap.
        println!("stride {stride}: held at {held} of {steps} steps");
        assert!(held > 0, "stride {stride}: VGICP narrowed the gap at every step; nothing held");
    }
}

#[test]
fn identical_halls_are_refused_by_what_the_robots_saw() {
    // aisles: two sealed halls of identical rack rows. Every check but the free space passes a
    // placement one hall onto the other (acceptance 0.91 at the truth's keyframes, 0.86-0.91 from
    // the odometry's): the bar sits above it.
    let scenario = Scenario::by_name("aisles").unwrap();
    let fleet: Vec<Robot> = (0..2).map(|i| indoor_robot(&scenario, i, 10)).collect();
    let config = MergeConfig::indoor();
    let blind = merge_whole(&fleet, &config, false);
    let (t, _) = worst_error(&blind, &frames(&fleet));
    assert!(t > 1.0, "without the views nothing is placed wrong ({t:.3} m): nothing to guard; {:?}", verdicts(&blind));
    let seeing = merge_whole(&fleet, &config, true);
    assert_eq!(seeing.merged(), 1, "a hall was placed onto the other: {:?}", verdicts(&seeing));
}
