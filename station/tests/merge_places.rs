//! Place recognition at the station: once maps are placed, a settling merge does not search a pair
//! whose keyframes never look alike, and no placement is lost by it (judged against the
//! simulator's truth).

use std::sync::Arc;

use cloud::PointCloud;
use cloud::scan_context::{Comparable, ScanContext, ScanContextConfig};
use nalgebra::Isometry3;
use sim::{Scenario, SimConfig, Simulator};
use station::merge::places::Places;
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
            let contexts: Vec<Arc<Comparable>> = frames
                .iter()
                .map(|&f| Arc::new(Comparable::new(&ScanContext::new(&sim.deskewed(&sim.scan(f)), &config))))
                .collect();
            let share = |k: usize| frames.len() * k / steps;
            Robot {
                // In the robot's frame at the start of its run, whichever piece.
                maps: (1..=steps).map(|k| sim.exact_map_of(&frames[..share(k)], 0.2).unwrap()).collect(),
                places: (1..=steps).map(|k| Arc::new(Places::new(contexts[..share(k)].to_vec()))).collect(),
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
