//! Turning in place: a robot standing on one spot and spinning about its vertical axis, which a
//! [`Trajectory`](crate::Trajectory) cannot do (its heading follows its path). A simulator made
//! [`spinning`](crate::Simulator::spinning) fires its sweeps from this motion instead of the
//! robot's route.

use nalgebra::{Isometry3, Point2};

use crate::trajectory::ground_pose;
use crate::world::Terrain;

/// A robot turning on the spot at a constant yaw rate, already turning at t = 0.
#[derive(Clone, Debug, PartialEq)]
pub struct SpinInPlace {
    /// Where it stands, world x and y, metres.
    pub position: Point2<f64>,
    /// Heading at t = 0, radians from +x, counter-clockwise.
    pub heading: f64,
    /// Yaw rate, rad/s; positive turns left (counter-clockwise seen from above).
    pub rate: f64,
    /// Height of the sensor above the ground, metres.
    pub mount_height: f64,
}

impl SpinInPlace {
    /// Heading at time `t`, radians (not wrapped).
    pub fn heading(&self, t: f64) -> f64 {
        self.heading + self.rate * t
    }

    /// Sensor pose in the world frame at time `t`, with the frame conventions of
    /// [`Trajectory::pose`](crate::Trajectory::pose): on sloped ground the robot pitches and rolls
    /// with the slope while it turns.
    pub fn pose(&self, terrain: &Terrain, t: f64) -> Isometry3<f64> {
        ground_pose(terrain, self.position, self.heading(t), self.mount_height)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn the_heading_grows_at_the_rate_and_the_sensor_stays_put() {
        let spin = SpinInPlace { position: Point2::new(3.0, -2.0), heading: 0.5, rate: -1.5, mount_height: 0.7 };
        let terrain = Terrain::Flat(0.25);
        for t in [0.0, 0.1, 1.0, 7.3] {
            let pose = spin.pose(&terrain, t);
            assert!((pose.translation.vector - Vector3::new(3.0, -2.0, 0.95)).norm() < 1e-12, "t = {t}");
            let x = pose.rotation * Vector3::x();
            let expected = Vector3::new((0.5 - 1.5 * t).cos(), (0.5 - 1.5 * t).sin(), 0.0);
            assert!((x - expected).norm() < 1e-12, "t = {t}: {x}");
            assert!((pose.rotation * Vector3::z() - Vector3::z()).norm() < 1e-12);
        }
    }
}
