//! A featureless corridor: the pose problem loses the axis of the corridor. The odometry must flag
//! those scans and keep the motion prior along that axis instead of drifting.

use cloud::trajectory::ate;
use edge::odometry::{Odometry, OdometryConfig};
use nalgebra::{Isometry3, Point2};
use sim::trajectory::{Trajectory, TrajectoryConfig};
use sim::world::Terrain;
use sim::{Scenario, SimConfig, Simulator};

/// Runs the odometry down the corridor with the sensors' noise drawn from `seed`; returns (truth,
/// estimate, degenerate scans).
fn run(degeneracy_ratio: f64, seed: u64) -> (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>, usize) {
    let world = sim::worlds::corridor::world();
    let config = TrajectoryConfig { stop_at_end: false, ..TrajectoryConfig::default() };
    let path =
        Trajectory::new(&[Point2::new(0.0, 0.0), Point2::new(60.0, 0.0)], false, &Terrain::Flat(0.0), &config).unwrap();
    let scenario = Scenario::new("corridor", "featureless corridor", world, vec![path]).with_frames(380);
    let mut sensor = sim::sensor::SensorModel::vlp16();
    // A 25 m range: the closed end drops out of sight after ~25 m and the corridor axis is lost.
    sensor.max_range = 25.0;
    let sim = Simulator::new(scenario, 0, SimConfig { sensor, seed, ..SimConfig::default() }).unwrap();
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

/// Where the estimate ends, metres from the truth.
fn final_error(gt: &[Isometry3<f64>], est: &[Isometry3<f64>]) -> f64 {
    (est.last().unwrap().translation.vector - gt.last().unwrap().translation.vector).norm()
}

#[test]
fn a_featureless_corridor_is_flagged_and_the_prior_is_kept() {
    // The end drops out of sight with whatever velocity the last constrained scans measured, and
    // that velocity is carried on blind for 30 m: one draw of the noise can land near or far (this
    // test's single seed once passed with 0.9 m where the next seed gave 6.5 m). The figure is the
    // mean over four draws.
    let ratio = OdometryConfig::indoor().solver.degeneracy_ratio;
    let mut errors = Vec::new();
    let mut travelled = 0.0;
    for seed in 0..4 {
        let (gt, with, flagged) = run(ratio, seed);
        travelled = gt.last().unwrap().translation.x;
        let error = final_error(&gt, &with);
        eprintln!(
            "corridor, seed {seed}, {travelled:.1} m: {flagged} of {} scans flagged; final error {error:.3} m, ATE {:.3} m",
            gt.len(),
            ate(&gt, &with, false).unwrap().rmse
        );
        // Past ~25 m from the closed end every scan is degenerate along the corridor.
        assert!(flagged > 100, "seed {seed}: {flagged} scans flagged");
        errors.push(error);
        if seed == 0 {
            // Solving blindly along the axis instead of keeping the prior runs away.
            let (_, without, _) = run(0.0, seed);
            let (a, b) = (ate(&gt, &with, false).unwrap().rmse, ate(&gt, &without, false).unwrap().rmse);
            eprintln!("without the prior: final error {:.3} m, ATE {b:.3} m", final_error(&gt, &without));
            assert!(a < b, "ATE {a:.3} with the prior kept vs {b:.3} without");
        }
    }
    // The robot cruises at constant speed there, so the constant-velocity prior is right: keeping it
    // ends within a few percent of the distance.
    let mean = errors.iter().sum::<f64>() / errors.len() as f64;
    assert!(mean < 0.03 * travelled, "mean final error {mean:.3} m over {travelled:.1} m ({errors:.3?})");
}
