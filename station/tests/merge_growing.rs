//! Maps that grow as robots drive, merged after each step the way the station does: links are
//! tracked rather than searched again, searches are bounded per merge, and every placement
//! published on the way is checked against the simulator's truth.

use cloud::PointCloud;
use nalgebra::Isometry3;
use sim::{Scenario, SimConfig, Simulator};
use station::merge::merger::MergerStats;
use station::merge::{MapStatus, MergeConfig, MergeReport, Merger, Unmerged};

mod truth;
use truth::{merge_until_done, worst_error};

/// One robot's exact map after each of `steps` equal shares of its run, every `stride`-th sweep.
fn growing_maps(sim: &Simulator, steps: usize, stride: usize, voxel: f32) -> Vec<PointCloud> {
    let frames: Vec<usize> = (0..sim.frames()).step_by(stride).collect();
    (1..=steps).map(|k| sim.exact_map_of(&frames[..frames.len() * k / steps], voxel).unwrap()).collect()
}

/// A scenario's robots with their maps over time and the world pose of each map's frame.
struct Fleet {
    maps: Vec<Vec<PointCloud>>,
    frames: Vec<Isometry3<f64>>,
}

impl Fleet {
    /// Sets every robot's map to its map at `step`, as revision `revision`.
    fn grow_all(&self, merger: &mut Merger, revision: u64, step: usize) {
        for (id, maps) in self.maps.iter().enumerate() {
            merger.grow(id, revision, maps[step].clone());
        }
    }
}

fn fleet(name: &str, steps: usize, voxel: f32) -> Fleet {
    let scenario = Scenario::by_name(name).unwrap();
    let sims: Vec<Simulator> = (0..scenario.robots().len())
        .map(|r| Simulator::new(scenario.clone(), r, SimConfig::default()).unwrap())
        .collect();
    Fleet {
        maps: sims.iter().map(|s| growing_maps(s, steps, 10, voxel)).collect(),
        frames: sims.iter().map(|s| s.pose_at(0.0)).collect(),
    }
}

/// Grows every map step by step and merges after each step until nothing is pending; checks each
/// published placement on the way.
fn merge_as_they_grow(fleet: &Fleet, config: MergeConfig) -> (MergeReport, MergerStats) {
    let steps = fleet.maps[0].len();
    let mut merger = Merger::new(config).unwrap();
    let mut last = None;
    for step in 0..steps {
        fleet.grow_all(&mut merger, step as u64, step);
        last = Some(merge_until_done(&mut merger, &fleet.frames, step, false));
    }
    (last.unwrap(), merger.stats())
}

#[test]
fn campus_links_are_tracked_as_the_maps_grow() {
    let fleet = fleet("campus", 5, 0.2);
    let (report, stats) = merge_as_they_grow(&fleet, MergeConfig::outdoor());
    assert_eq!(report.merged(), 4, "all four campus robots in the end");
    // Once linked, a pair is followed by VGICP, not searched again at every refresh.
    assert!(stats.tracked > 0, "{stats:?}");
    let tracked_edges = report.edges().filter(|e| e.tracked).count();
    assert!(tracked_edges > 0, "the final graph holds tracked links");
}

#[test]
fn a_settled_merge_searches_again_what_was_tracked_or_grew() {
    let fleet = fleet("campus", 3, 0.2);
    let config = MergeConfig::outdoor();
    let mut merger = Merger::new(config.clone()).unwrap();
    for step in 0..3 {
        fleet.grow_all(&mut merger, step as u64, step);
        while merger.merge().unwrap().pending > 0 {}
    }
    // Each map grows by 5 % more (points 1 cm beside its own): too little for a streaming merge to
    // prepare it again, but a settling merge prepares every map that grew.
    for (id, maps) in fleet.maps.iter().enumerate() {
        let mut grown = maps[2].clone();
        let extra: Vec<_> =
            grown.points.iter().step_by(20).map(|p| p + nalgebra::Vector3::new(0.01, 0.0, 0.0)).collect();
        grown.points.extend(extra);
        merger.grow(id, 3, grown);
    }
    let streaming = merger.stats();
    merger.merge().unwrap();
    assert_eq!(merger.stats().preparations, streaming.preparations, "5 % growth waits for settling");
    let before = merger.stats();
    merger.settle();
    let mut settled = merger.merge().unwrap();
    // Four grown maps, two prepared per merge: the first settling merge leaves work.
    assert_eq!(merger.stats().preparations - before.preparations, config.max_refreshes, "{:?}", merger.stats());
    assert!(settled.pending > 0 && !settled.settled);
    while settled.pending > 0 {
        merger.settle();
        settled = merger.merge().unwrap();
    }
    assert!(settled.settled);
    assert_eq!(merger.stats().preparations - before.preparations, 4, "each grown map prepared once");
    assert!(merger.stats().pair_estimates > before.pair_estimates, "{before:?} -> {:?}", merger.stats());
    assert_eq!(settled.edges().filter(|e| e.tracked).count(), 0, "every edge searched on the final maps");
    assert_eq!(settled.merged(), 4);
    let (t, r) = worst_error(&settled, &fleet.frames);
    assert!(t < 0.05 && r < 0.5, "{t:.3} m / {r:.2} deg");
    // Settled and nothing changed since: nothing is searched again.
    let searched = merger.stats().pair_estimates;
    merger.merge().unwrap();
    assert_eq!(merger.stats().pair_estimates, searched);
}

#[test]
fn searches_are_bounded_per_merge_and_the_rest_wait() {
    let fleet = fleet("campus", 1, 0.2);
    let config = MergeConfig { max_searches: 2, ..MergeConfig::outdoor() };
    let mut merger = Merger::new(config).unwrap();
    fleet.grow_all(&mut merger, 0, 0);
    let first = merger.merge().unwrap();
    assert_eq!(merger.stats().pair_estimates, 2);
    assert_eq!(first.pending, 4, "six pairs, two searched");
    assert_eq!(first.pairs.iter().filter(|p| p.pending()).count(), 4);
    while merger.merge().unwrap().pending > 0 {}
    assert_eq!(merger.stats().pair_estimates, 6, "each pair searched once");
    assert_eq!(merger.stats().merges, 3, "two at a time");
    // Nothing changed: nothing to do.
    let idle = merger.merge().unwrap();
    assert_eq!((idle.pending, merger.stats().pair_estimates), (0, 6));
    assert_eq!(idle.merged(), 4);
    assert!(worst_error(&idle, &fleet.frames).0 < 0.05);
}

#[test]
fn a_map_that_barely_grew_is_not_prepared_again_but_its_points_are_in_the_global_map() {
    let fleet = fleet("campus", 1, 0.2);
    let mut merger = Merger::new(MergeConfig::outdoor()).unwrap();
    fleet.grow_all(&mut merger, 0, 0);
    let before = merger.merge().unwrap();
    let prepared = merger.stats().preparations;
    // Robot 0 gains a few points far from everything (under the refresh share).
    let mut grown = fleet.maps[0][0].clone();
    let extra: Vec<nalgebra::Point3<f32>> =
        (0..200).map(|i| nalgebra::Point3::new(500.0 + i as f32, 500.0, 0.0)).collect();
    grown.points.extend(&extra);
    merger.grow(0, 1, grown);
    let after = merger.merge().unwrap();
    assert_eq!(merger.stats().preparations, prepared, "not prepared again");
    assert_eq!(after.maps[0].points, before.maps[0].points + 200);
    let placed = after.maps[0].transform().cast::<f32>() * extra[0];
    assert!(after.global_map.points.iter().any(|p| (p - placed).norm() < 0.2), "the new points are published");
    // `update` says the map changed shape: prepared again.
    merger.update(0, 2, fleet.maps[0][0].clone());
    merger.merge().unwrap();
    assert_eq!(merger.stats().preparations, prepared + 1);
}

/// `map` with a share `share` more points, each beside one of its own (1 cm off).
fn thickened(map: &PointCloud, share: f64) -> PointCloud {
    let mut grown = map.clone();
    let stride = (1.0 / share).round() as usize;
    let extra: Vec<_> = map.points.iter().step_by(stride).map(|p| p + nalgebra::Vector3::new(0.01, 0.0, 0.0)).collect();
    grown.points.extend(extra);
    grown
}

/// A lone strip of floor, `rows` rows of 20 points 0.2 m apart: too small for features (a few rows
/// keep fewer than 50 points at 0.4 m), never placed.
fn floor_patch(rows: usize) -> PointCloud {
    let points = (0..rows * 20).map(|i| nalgebra::Point3::new((i % 20) as f32 * 0.2, (i / 20) as f32 * 0.2, 0.0));
    PointCloud::from_points(points.collect())
}

#[test]
fn a_merged_map_is_prepared_again_at_doubling_an_unmerged_one_sooner() {
    let fleet = fleet("campus", 1, 0.2);
    let config = MergeConfig::outdoor();
    let mut merger = Merger::new(config.clone()).unwrap();
    fleet.grow_all(&mut merger, 0, 0);
    merger.grow(9, 0, floor_patch(4));
    while merger.merge().unwrap().pending > 0 {}
    let placed = merger.merge().unwrap();
    assert_eq!(placed.merged(), 4);
    assert!(matches!(placed.maps[4].status, MapStatus::Unmerged(Unmerged::Unusable(_))), "{:?}", placed.maps[4]);
    let before = merger.stats().preparations;
    // Every usable map is placed. Both grow by half: past `refresh_growth`, short of
    // `merged_refresh_growth`.
    assert!(config.refresh_growth < 0.5 && 0.5 < config.merged_refresh_growth);
    merger.grow(0, 1, thickened(&fleet.maps[0][0], 0.5));
    merger.grow(9, 1, floor_patch(6));
    let report = merger.merge().unwrap();
    assert_eq!(merger.stats().preparations - before, 1, "only the unmerged map is prepared again");
    assert!(report.maps[0].is_merged() && report.maps[0].points > placed.maps[0].points, "its new points are in");
    // Doubled: the merged map is prepared again too, and its placement holds.
    merger.grow(0, 2, thickened(&fleet.maps[0][0], 1.0));
    let doubled = merger.merge().unwrap();
    assert_eq!(merger.stats().preparations - before, 2);
    assert_eq!(doubled.merged(), 4);
    assert!(worst_error(&doubled, &fleet.frames).0 < 0.05);
}

#[test]
fn maps_are_composed_while_a_round_of_estimation_runs_elsewhere() {
    let fleet = fleet("campus", 2, 0.2);
    let mut merger = Merger::new(MergeConfig::outdoor()).unwrap();
    fleet.grow_all(&mut merger, 0, 0);
    merger.grow(9, 0, floor_patch(4));
    let before = merge_until_done(&mut merger, &fleet.frames, 0, false);
    assert!(before.merged() >= 2, "half-way, some campus robots are linked");
    // The robots drive on: every map doubles or so, and a round is planned on them.
    fleet.grow_all(&mut merger, 1, 1);
    let round = merger.plan().expect("grown maps need a round");
    assert!(merger.estimating() && merger.plan().is_none(), "one round at a time");
    // Meanwhile another map arrives (robot 1's, under another id) and the floor patch leaves.
    let mut frames = fleet.frames.clone();
    frames.push(fleet.frames[1]);
    merger.grow(4, 0, fleet.maps[1][1].clone());
    merger.remove(9);
    let during = merger.compose().unwrap();
    assert!(!during.settled);
    let status = |report: &MergeReport, id: usize| report.maps.iter().find(|m| m.id == id).unwrap().status.clone();
    assert_eq!(status(&during, 4), MapStatus::Unmerged(Unmerged::Waiting));
    // The grown maps are published at the placements already found, new points included.
    assert!(
        during.global_map.len() > before.global_map.len(),
        "{} -> {}",
        before.global_map.len(),
        during.global_map.len()
    );
    assert_eq!(during.merged(), before.merged(), "placements stand until a round is applied");
    let (t, r) = worst_error(&during, &frames);
    assert!(t < 0.05 && r < 0.5, "{t:.3} m / {r:.2} deg");
    // The round runs on another thread, without the merger, and is taken back.
    let round = std::thread::spawn(move || {
        let mut round = round;
        round.run();
        round
    })
    .join()
    .unwrap();
    assert!(round.timing().total > std::time::Duration::ZERO);
    merger.apply(round);
    assert!(!merger.estimating());
    // Rounds until none is needed: the new map is prepared and placed, the removed one stays gone.
    let mut rounds = 0;
    while let Some(mut round) = merger.plan() {
        round.run();
        merger.apply(round);
        rounds += 1;
        assert!(rounds < 20, "rounds do not converge");
    }
    merger.settle();
    while let Some(mut round) = merger.plan() {
        round.run();
        merger.apply(round);
    }
    let after = merger.compose().unwrap();
    assert!(after.settled, "nothing changed since the settling round");
    assert_eq!(after.maps.iter().map(|m| m.id).collect::<Vec<_>>(), vec![0, 1, 2, 3, 4]);
    assert_eq!(after.merged(), 5);
    let (t, r) = worst_error(&after, &frames);
    assert!(t < 0.05 && r < 0.5, "{t:.3} m / {r:.2} deg");
    // A change after it unsettles the map.
    merger.grow(0, 2, thickened(&fleet.maps[0][1], 0.05));
    assert!(!merger.compose().unwrap().settled);
}
