//! Place recognition at the station: once maps are placed, a settling merge does not search a pair
//! whose keyframes never look alike, and no placement is lost by it (judged against the
//! simulator's truth).

use std::sync::Arc;

use cloud::PointCloud;
use cloud::scan_context::{Comparable, ScanContext, ScanContextConfig};
use nalgebra::Isometry3;
use sim::{Scenario, SimConfig, Simulator};
use station::merge::places::{Place, Places};
use station::merge::{MergeConfig, MergeReport, Merger, PairRejection, PairVerdict};

mod truth;
use truth::merge_until_done;

/// One map: its cloud and places after each of `steps` equal shares of its sweeps (every
/// `stride`-th sweep of a piece of a robot's run a keyframe), its frame in the world, and its
/// keyframes' positions in the world.
struct Robot {
    maps: Vec<PointCloud>,
    places: Vec<Arc<Places>>,
    frame: Isometry3<f64>,
    positions: Vec<nalgebra::Point3<f64>>,
}

/// Each robot's run cut into `pieces` maps, as robots that drive the same roads at other times.
fn robots(name: &str, pieces: usize, steps: usize, stride: usize) -> Vec<Robot> {
    let scenario = Scenario::by_name(name).unwrap();
    (0..scenario.robots().len() * pieces)
        .map(|m| {
            let sim = Simulator::new(scenario.clone(), m / pieces, SimConfig::default()).unwrap();
            let all: Vec<usize> = (0..sim.frames()).step_by(stride).collect();
            let piece = m % pieces;
            let frames = &all[all.len() * piece / pieces..all.len() * (piece + 1) / pieces];
            let config = ScanContextConfig::default();
            let start = sim.pose_at(0.0).inverse();
            let places: Vec<Place> = frames
                .iter()
                .map(|&f| Place {
                    context: Arc::new(Comparable::new(&ScanContext::new(&sim.deskewed(&sim.scan(f)), &config))),
                    position: (start * sim.ground_truth(f)).translation.vector.cast::<f32>().into(),
                })
                .collect();
            let share = |k: usize| frames.len() * k / steps;
            Robot {
                // In the robot's frame at the start of its run, whichever piece.
                maps: (1..=steps).map(|k| sim.exact_map_of(&frames[..share(k)], 0.2).unwrap()).collect(),
                places: (1..=steps).map(|k| Arc::new(Places::new(places[..share(k)].to_vec()))).collect(),
                frame: sim.pose_at(0.0),
                positions: frames.iter().map(|&f| sim.ground_truth(f).translation.vector.into()).collect(),
            }
        })
        .collect()
}

/// Grows every map step by step, merging until nothing is pending, then settles; checks every
/// placement on the way. With each map's places when `with_places`.
fn merge(fleet: &[Robot], with_places: bool) -> (MergeReport, station::merge::merger::MergerStats) {
    let frames: Vec<Isometry3<f64>> = fleet.iter().map(|r| r.frame).collect();
    let mut merger = Merger::new(MergeConfig::outdoor()).unwrap();
    let steps = fleet[0].maps.len();
    let mut last = None;
    for step in 0..=steps {
        let settling = step == steps;
        if !settling {
            for (id, robot) in fleet.iter().enumerate() {
                merger.grow(id, step as u64, robot.maps[step].clone());
                merger.set_places(id, with_places.then(|| Arc::clone(&robot.places[step])));
            }
        }
        last = Some(merge_until_done(&mut merger, &frames, step, settling));
    }
    (last.unwrap(), merger.stats())
}

#[test]
fn placed_maps_whose_places_never_match_are_not_searched_again() {
    let fleet = robots("campus", 2, 2, 10);
    let (without, plain) = merge(&fleet, false);
    let (with, gated) = merge(&fleet, true);
    println!("without places {plain:?}\nwith places {gated:?}");
    assert_eq!(with.merged(), without.merged(), "no placement lost");
    let held: Vec<(usize, usize)> = with
        .pairs
        .iter()
        .filter(|p| matches!(p.verdict, PairVerdict::Rejected { reason: PairRejection::NoCandidate, .. }))
        .map(|p| (p.a, p.b))
        .collect();
    for &(a, b) in &held {
        assert!(with.maps[a].is_merged() && with.maps[b].is_merged(), "only pairs of placed maps are held back");
        // The truth: how close the two robots' keyframes ever came.
        let nearest = fleet[a]
            .positions
            .iter()
            .flat_map(|p| fleet[b].positions.iter().map(move |q| (p - q).norm()))
            .fold(f64::INFINITY, f64::min);
        println!("held back: robots {a} and {b}, keyframes at least {nearest:.1} m apart");
        // Scan Context tells places within a few metres; maps that passed that close are not held back.
        assert!(nearest > 10.0, "robots {a} and {b} passed within {nearest:.1} m of each other");
    }
    assert!(!held.is_empty(), "some placed maps never pass the same places");
    assert!(gated.unmatched >= held.len());
    assert!(gated.pair_estimates <= plain.pair_estimates, "{gated:?} against {plain:?}");
}

/// The places of `map` at `positions` (its frame): each keyframe's descriptor made of the map's
/// points within the descriptor's range around it, as a sensor there would see them.
fn places_of(map: &PointCloud, positions: &[nalgebra::Point3<f32>], config: &ScanContextConfig) -> Arc<Places> {
    let place = |&position: &nalgebra::Point3<f32>| {
        let reach = config.max_range as f32;
        let seen: Vec<_> =
            map.points.iter().map(|p| p - position.coords).filter(|p| p.coords.xy().norm() < reach).collect();
        let context = Arc::new(Comparable::new(&ScanContext::new(&PointCloud::from_points(seen), config)));
        Place { context, position }
    };
    Arc::new(Places::new(positions.iter().map(place).collect()))
}

#[test]
fn maps_that_share_a_small_part_are_linked_around_the_place_they_share() {
    // Two maps share a 40 m yard and each holds a 100 m one of its own (station/tests/merge.rs
    // searches the same pair directly): over the whole maps the link falls short; given the
    // places of two keyframes each (one in the shared yard, one in its own), the merger searches
    // around the pair that looks alike and places the second map, within 5 cm of the truth.
    let truth = testkit::pose_from_yaw_deg(70.0, [25.0, -40.0, 1.0]);
    let (target, source) = testkit::yards_sharing_one(&truth);
    let (target, source) = (PointCloud::from_points(target), PointCloud::from_points(source));
    let frames = [Isometry3::identity(), truth];
    let config = ScanContextConfig { max_range: 20.0, ..ScanContextConfig::default() };
    let at = |x: f32, y: f32| nalgebra::Point3::new(x, y, 1.0);
    let source_at = |p: nalgebra::Point3<f32>| truth.inverse().cast::<f32>() * p;
    let places = [
        places_of(&target, &[at(90.0, 0.0), at(20.0, 20.0)], &config),
        places_of(&source, &[source_at(at(-50.0, 0.0)), source_at(at(20.0, 20.0))], &config),
    ];
    let run = |with_places: bool| {
        let mut merger = Merger::new(MergeConfig::outdoor()).unwrap();
        for (id, (map, places)) in [&target, &source].into_iter().zip(&places).enumerate() {
            merger.grow(id, 0, map.clone());
            merger.set_places(id, with_places.then(|| Arc::clone(places)));
        }
        let report = merge_until_done(&mut merger, &frames, 0, true);
        (report.merged(), merger.stats())
    };
    let (alone, _) = run(false);
    assert_eq!(alone, 1, "the premise: the whole maps give no link");
    let (merged, stats) = run(true);
    println!("{stats:?}");
    assert_eq!(merged, 2);
    assert_eq!(stats.around, 1, "{stats:?}");
}

/// Merges `fleet`'s maps as they are at its first step, one search per round, until nothing is
/// pending; with each map's places when `with_places`. Per round, the maps merged.
fn merged_per_round(fleet: &[Robot], with_places: bool) -> Vec<usize> {
    let frames: Vec<Isometry3<f64>> = fleet.iter().map(|r| r.frame).collect();
    let mut merger = Merger::new(MergeConfig { max_searches: 1, ..MergeConfig::outdoor() }).unwrap();
    for (id, robot) in fleet.iter().enumerate() {
        merger.grow(id, 0, robot.maps[0].clone());
        merger.set_places(id, with_places.then(|| Arc::clone(&robot.places[0])));
    }
    let mut merged = Vec::new();
    loop {
        let report = merger.merge().unwrap();
        let (t, r) = truth::worst_error(&report, &frames);
        assert!(t < 0.05 && r < 0.5, "round {}: a placement {t:.3} m / {r:.2} deg off the truth", merged.len() + 1);
        merged.push(report.merged());
        if report.pending == 0 {
            return merged;
        }
    }
}

#[test]
fn searches_that_can_place_a_map_where_places_look_alike_go_first() {
    // Eight maps (each campus robot's run in two pieces), one search per round: in the order of
    // the pairs, most searches link nothing; searching first the pairs of a placed and an unplaced
    // map whose keyframes look alike places every map in a third fewer rounds at least (half as
    // many, measured).
    let fleet = robots("campus", 2, 1, 10);
    let plain = merged_per_round(&fleet, false);
    let ordered = merged_per_round(&fleet, true);
    println!("merged per round, in pair order: {plain:?}\nplaces first: {ordered:?}");
    let all = *plain.last().unwrap();
    assert_eq!(*ordered.last().unwrap(), all, "no placement lost");
    assert!(all > fleet.len() / 2, "most maps are placed: {plain:?}");
    let rounds_to_all = |merged: &[usize]| merged.iter().position(|&m| m == all).unwrap() + 1;
    assert!(
        rounds_to_all(&ordered) * 3 <= rounds_to_all(&plain) * 2,
        "every map placed in round {} with places, {} without",
        rounds_to_all(&ordered),
        rounds_to_all(&plain)
    );
}

#[test]
fn a_robots_previous_session_is_searched_first() {
    // Four maps, each campus robot's run in two pieces: pieces of one run are what a robot leaves
    // before and after a restart. Robot 1's pieces get ids 0 and 3, robot 2's 1 and 2; one search
    // per round. Told that 0 and 3 are sessions of one robot, the merger searches that pair
    // first, and its link is the first placement; in id order the first search is (0, 1).
    let fleet = robots("campus", 2, 1, 10);
    let ids = [0, 3, 1, 2];
    let frames: Vec<Isometry3<f64>> = {
        let mut by_id = vec![Isometry3::identity(); fleet.len()];
        for (robot, &id) in fleet.iter().zip(&ids) {
            by_id[id] = robot.frame;
        }
        by_id
    };
    let first_round = |related: bool| {
        let mut merger = Merger::new(MergeConfig { max_searches: 1, ..MergeConfig::outdoor() }).unwrap();
        for (robot, &id) in fleet.iter().zip(&ids) {
            merger.grow(id, 0, robot.maps[0].clone());
        }
        if related {
            merger.relate(3, 0);
        }
        let report = merger.merge().unwrap();
        let searched: Vec<(usize, usize)> =
            report.pairs.iter().filter(|p| p.verdict.edge().is_some()).map(|p| (p.a, p.b)).collect();
        let (t, r) = truth::worst_error(&report, &frames);
        assert!(t < 0.05 && r < 0.5, "a placement {t:.3} m / {r:.2} deg off the truth");
        let placed: Vec<usize> = report.maps.iter().filter(|m| m.is_merged()).map(|m| m.id).collect();
        (searched, placed)
    };
    let (plain_links, plain_placed) = first_round(false);
    let (links, placed) = first_round(true);
    println!("first round in id order: links {plain_links:?}, placed {plain_placed:?}; related: {links:?}, {placed:?}");
    assert_eq!(placed, vec![0, 3], "the related sessions placed first");
    assert_ne!(plain_placed, placed, "the premise: in id order another pair is searched first");
}
