//! A featureless corridor: the pose problem loses the axis of the corridor. The odometry must flag
//! those scans and keep the motion prior along that axis instead of drifting.

use cloud::trajectory::ate;
use edge::odometry::{Odometry, OdometryConfig};
use nalgebra::{Isometry3, Point2};
use sim::trajectory::{Trajectory, TrajectoryConfig};
use sim::world::Terrain;
use sim::{Scenario, SimConfig, Simulator};

/// Runs the odometry down the corridor; returns (truth, estimate, degenerate scans).
fn run(degeneracy_ratio: f64) -> (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>, usize) {
    let world = sim::worlds::corridor::world();
    let config = TrajectoryConfig { stop_at_end: false, ..TrajectoryConfig::default() };
    let path =
        Trajectory::new(&[Point2::new(0.0, 0.0), Point2::new(60.0, 0.0)], false, &Terrain::Flat(0.0), &config).unwrap();
    let scenario = Scenario::new("corridor", "featureless corridor", world, vec![path]).with_frames(380);
    let mut sensor = sim::sensor::SensorModel::vlp16();
    // A 25 m range: the closed end drops out of sight after ~25 m and the corridor axis is lost.
    sensor.max_range = 25.0;
    let sim = Simulator::new(scenario, 0, SimConfig { sensor, ..SimConfig::default() }).unwrap();
    let mut odometry_config = OdometryConfig::indoor();
    odometry_config.solver.degeneracy_ratio = degeneracy_ratio;
    let mut odometry = Odometry::new(odometry_config).unwrap();
    let first = sim.ground_truth(0).inverse();
    let (mut gt, mut est, mut degenerate) = (Vec::new(), Vec::new(), 0);
    for f in 0..sim.frames() {
        let scan = sim.scan(f);
        let frame = odometry.register(&scan.cloud, scan.stamp).unwrap();
        degenerate += usize::from(frame.degenerate);
        gt.push(first * scan.ground_truth);
        est.push(frame.pose);
    }
    (gt, est, degenerate)
}

#[test]
fn a_featureless_corridor_is_flagged_and_the_prior_is_kept() {
    let (gt, with, flagged) = run(OdometryConfig::indoor().solver.degeneracy_ratio);
    let (_, without, _) = run(0.0);
    let travelled = gt.last().unwrap().translation.x;
    let err = |est: &[Isometry3<f64>]| {
        (est.last().unwrap().translation.vector - gt.last().unwrap().translation.vector).norm()
    };
    let a = ate(&gt, &with, false).unwrap();
    let b = ate(&gt, &without, false).unwrap();
    eprintln!(
        "corridor, {travelled:.1} m: {flagged} of {} scans flagged; final error {:.3} m with the prior kept, {:.3} m without; ATE {:.3} / {:.3} m",
        gt.len(),
        err(&with),
        err(&without),
        a.rmse,
        b.rmse
    );
    // Past ~25 m from the closed end every scan is degenerate along the corridor.
    assert!(flagged > 100, "{flagged} scans flagged");
    // The robot cruises at constant speed there, so the constant-velocity prior is right: keeping it
    // ends within a few percent of the distance, where solving blindly along the axis does not.
    assert!(err(&with) < 0.03 * travelled, "final error {:.3} m over {travelled:.1} m", err(&with));
    assert!(a.rmse < b.rmse, "ATE {:.3} with the prior kept vs {:.3} without", a.rmse, b.rmse);
}
