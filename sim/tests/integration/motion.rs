//! The motions and sensors the odometry robustness matrix needs: sensor rates, turning
//! in place, a car on the campus roads, against their exact definitions.

use std::f64::consts::PI;

use nalgebra::{Point2, Vector3};
use sim::{Scenario, SensorModel, SimConfig, Simulator, SpinInPlace};

/// Heading of a pose's x axis in the plane.
fn heading(pose: &nalgebra::Isometry3<f64>) -> f64 {
    let x = pose.rotation * Vector3::x();
    x.y.atan2(x.x)
}

fn wrap(a: f64) -> f64 {
    (a + PI).rem_euclid(2.0 * PI) - PI
}

#[test]
fn a_sensor_rate_sets_stamps_ground_truth_and_length() {
    let scenario = Scenario::by_name("warehouse-small").unwrap();
    let config = SimConfig { sensor: SensorModel::vlp16().at_rate(2.0), ..SimConfig::default() };
    let sim = Simulator::new(scenario.clone(), 0, config).unwrap();
    // The scenario's 1720 frames at 10 Hz are 172 s: 344 sweeps at 2 Hz.
    assert_eq!(scenario.frames(), 1720);
    assert_eq!(sim.frames(), 344);
    assert_eq!(sim.stamp(3), 1.5);
    assert_eq!(sim.ground_truth(3), sim.trajectory().pose(2.0));
    // A 2 Hz sweep takes 0.5 s: its last column fires just before the sweep end.
    let scan = sim.scan(100);
    let last = scan.cloud.time.as_ref().unwrap().iter().copied().fold(0.0, f32::max);
    assert!(last > 0.49 && last < 0.5, "last firing {last} s");
}

#[test]
fn spinning_in_place_turns_the_ground_truth_at_the_asked_rate() {
    let rate = 180f64.to_radians();
    let spin = SpinInPlace { position: Point2::new(10.0, 12.0), heading: 0.3, rate, mount_height: 0.7 };
    let sim =
        Simulator::new(Scenario::by_name("warehouse-small").unwrap(), 0, SimConfig::default()).unwrap().spinning(spin);
    for frame in [0, 1, 7, 50] {
        let truth = sim.ground_truth(frame);
        // The floor is flat at z = 0: the sensor stays 0.7 m above the spot and only turns.
        assert!((truth.translation.vector - Vector3::new(10.0, 12.0, 0.7)).norm() < 1e-12);
        let expected = wrap(0.3 + rate * 0.1 * (frame + 1) as f64);
        assert!(wrap(heading(&truth) - expected).abs() < 1e-12, "frame {frame}");
        // 18 degrees from one sweep end to the next, about the vertical only.
        let step = sim.ground_truth(frame).inverse() * sim.ground_truth(frame + 1);
        assert!((step.rotation.angle() - 18f64.to_radians()).abs() < 1e-12);
        assert!((step.rotation.axis().unwrap().into_inner() - Vector3::z()).norm() < 1e-9);
        assert!(step.translation.vector.norm() < 1e-12);
    }
    // The sweep itself is skewed by the turn: a column fires from the pose at its own time.
    let scan = sim.scan(4);
    assert!(!scan.cloud.is_empty());
    let mid = sim.ground_truth(4).inverse() * sim.pose_at(scan.stamp + 0.05);
    assert!((mid.rotation.scaled_axis() - Vector3::new(0.0, 0.0, -rate * 0.05)).norm() < 1e-12);
}

#[test]
fn a_car_on_the_campus_starts_at_speed_and_slows_for_corners() {
    for speed in [10.0, 20.0] {
        let scenario = Scenario::campus_car(speed).unwrap();
        let car = &scenario.robots()[0];
        assert_eq!(scenario.robots().len(), 1);
        // Not at rest at the first sweep: no prior motion to start from.
        assert!((car.speed(0.0) - speed).abs() < 1e-9, "{speed}: {}", car.speed(0.0));
        // Straight east along the north road at full speed for the first second (2 % for the
        // sensor mast tilting with the slope).
        let (a, b) = (car.pose(0.0).translation.vector, car.pose(1.0).translation.vector);
        assert!(((b - a).xy().norm() - speed).abs() < 0.02 * speed, "{speed}: {}", (b - a).xy().norm());
        assert!((b - a).y.abs() < 0.02 * speed, "{speed}: {}", b - a);
        // The 8 m corners: 6 m/s² lateral and 1 rad/s yaw allow at most sqrt(6 · 8) ≈ 6.9 m/s.
        let slowest =
            (0..(car.duration() * 10.0) as usize).map(|i| car.speed(i as f64 / 10.0)).fold(f64::MAX, f64::min);
        assert!(slowest < 7.0, "{speed}: slowest {slowest}");
        // It does not stop at the end either.
        assert!(car.speed(car.duration() - 1e-6) > 5.0);
        let top = (0..(car.duration() * 10.0) as usize).map(|i| car.speed(i as f64 / 10.0)).fold(0.0, f64::max);
        assert!(top <= speed + 1e-9, "{speed}: top {top}");
    }
}

#[test]
fn invalid_car_speeds_are_refused() {
    assert!(Scenario::campus_car(0.0).is_err());
    assert!(Scenario::campus_car(f64::NAN).is_err());
}
