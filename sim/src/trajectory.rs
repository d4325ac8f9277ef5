//! Ground-robot trajectories: a centripetal Catmull–Rom spline through 2-D waypoints, parametrised
//! by arc length, driven with a speed profile that respects acceleration, lateral acceleration and
//! yaw-rate limits, and lifted onto the terrain.
//!
//! Pose of the sensor at time t: the robot's body frame has z along the ground normal and x along
//! the path heading projected onto the ground plane; the sensor sits `mount_height` above the ground
//! along that normal, axes aligned with the body. Before the start the robot waits at its first
//! waypoint; after the end it stays parked at its last.

use nalgebra::{Isometry3, Matrix3, Point2, Point3, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3};

use crate::world::Terrain;

/// Arc-length grid step of the lookup tables, metres: fine enough that the speed profile's
/// piecewise-constant acceleration looks continuous to odometry.
const GRID_STEP: f64 = 0.05;

/// How a robot drives along its path.
#[derive(Clone, Debug, PartialEq)]
pub struct TrajectoryConfig {
    /// Speed on straight stretches, m/s. Default 1.5 (the odometry benchmark's speed).
    pub cruise_speed: f64,
    /// Largest tangential acceleration or braking, m/s². Default 0.5, a gentle warehouse robot.
    pub max_accel: f64,
    /// Largest centripetal acceleration in turns, m/s². Default 0.8: no sliding, no tipping.
    pub max_lateral_accel: f64,
    /// Largest yaw rate, rad/s. Default 0.8 (about 46°/s), a skid-steer robot's comfortable limit.
    pub max_yaw_rate: f64,
    /// Height of the sensor origin above the ground, metres. Default 0.7.
    pub mount_height: f64,
    /// Start from standstill (true) or already at the allowed speed. Default true.
    pub start_at_rest: bool,
    /// Brake to a stop at the last waypoint. Default true.
    pub stop_at_end: bool,
}

impl Default for TrajectoryConfig {
    fn default() -> Self {
        Self {
            cruise_speed: 1.5,
            max_accel: 0.5,
            max_lateral_accel: 0.8,
            max_yaw_rate: 0.8,
            mount_height: 0.7,
            start_at_rest: true,
            stop_at_end: true,
        }
    }
}

/// Why a trajectory cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TrajectoryError {
    /// A spline needs at least two distinct points.
    #[error("a path needs at least 2 waypoints, got {0}")]
    TooFewWaypoints(usize),
    /// Two consecutive waypoints coincide, so the direction between them is undefined.
    #[error("waypoints {0} and {next} coincide", next = .0 + 1)]
    RepeatedWaypoint(usize),
    /// A limit that is not a positive finite number.
    #[error("{0} must be positive and finite")]
    BadLimit(&'static str),
}

/// A cubic `c0 + c1 u + c2 u² + c3 u³` in the plane, u in [0, 1].
#[derive(Clone, Copy, Debug)]
struct Cubic([Vector2<f64>; 4]);

impl Cubic {
    /// Position, first and second derivative at `u`.
    fn eval(&self, u: f64) -> [Vector2<f64>; 3] {
        let [c0, c1, c2, c3] = self.0;
        [c0 + u * (c1 + u * (c2 + u * c3)), c1 + u * (2.0 * c2 + u * 3.0 * c3), 2.0 * c2 + 6.0 * u * c3]
    }
}

/// The centripetal Catmull–Rom segment from `p1` to `p2` (Yuksel et al. 2011) as a cubic Hermite
/// in u ∈ [0, 1]: knot spacing |Δp|^½ never gives cusps or self-intersections inside a segment.
fn catmull_rom(p0: Vector2<f64>, p1: Vector2<f64>, p2: Vector2<f64>, p3: Vector2<f64>) -> Cubic {
    let knot = |a: Vector2<f64>, b: Vector2<f64>| (b - a).norm().sqrt();
    let (t01, t12, t23) = (knot(p0, p1), knot(p1, p2), knot(p2, p3));
    let m1 = ((p1 - p0) / t01 - (p2 - p0) / (t01 + t12) + (p2 - p1) / t12) * t12;
    let m2 = ((p2 - p1) / t12 - (p3 - p1) / (t12 + t23) + (p3 - p2) / t23) * t12;
    Cubic([p1, m1, 3.0 * (p2 - p1) - 2.0 * m1 - m2, 2.0 * (p1 - p2) + m1 + m2])
}

/// A planar spline through waypoints. The global parameter is the centripetal knot value
/// (cumulative |Δp|^½), in which Catmull–Rom is C¹: the tangent is continuous across waypoints,
/// which the arc-length table's Hermite interpolation relies on.
#[derive(Clone, Debug)]
struct Spline {
    segments: Vec<Cubic>,
    /// Knot value at the start of each segment, and at the end.
    knots: Vec<f64>,
}

impl Spline {
    /// Through `points`; closed splines also join the last point back to the first.
    fn through(points: &[Vector2<f64>], closed: bool) -> Spline {
        let n = points.len();
        let at = |i: isize| -> Vector2<f64> {
            if closed {
                points[i.rem_euclid(n as isize) as usize]
            } else if i < 0 {
                2.0 * points[0] - points[1] // phantom ends continue the first and last legs
            } else if i as usize >= n {
                2.0 * points[n - 1] - points[n - 2]
            } else {
                points[i as usize]
            }
        };
        let count = if closed { n } else { n - 1 } as isize;
        let segments = (0..count).map(|i| catmull_rom(at(i - 1), at(i), at(i + 1), at(i + 2))).collect();
        let mut knots = vec![0.0];
        for i in 0..count {
            knots.push(knots[i as usize] + (at(i + 1) - at(i)).norm().sqrt());
        }
        Spline { segments, knots }
    }

    /// Last knot value.
    fn end(&self) -> f64 {
        *self.knots.last().unwrap_or(&0.0)
    }

    /// Position, first and second derivative at parameter `u` (clamped to the spline).
    fn eval(&self, u: f64) -> [Vector2<f64>; 3] {
        let last = self.segments.len() - 1;
        let i = self.knots.partition_point(|&k| k <= u).clamp(1, last + 1) - 1;
        let span = self.knots[i + 1] - self.knots[i];
        let [p, d, dd] = self.segments[i].eval(((u - self.knots[i]) / span).clamp(0.0, 1.0));
        [p, d / span, dd / (span * span)]
    }

    /// Arc length from `a` to `b` (within one segment): 5-point Gauss–Legendre, exact to ~1e-10 m
    /// on the short intervals used.
    fn length(&self, a: f64, b: f64) -> f64 {
        const X: [f64; 5] =
            [0.0, -0.538_469_310_105_683, 0.538_469_310_105_683, -0.906_179_845_938_664, 0.906_179_845_938_664];
        const W: [f64; 5] = [
            0.568_888_888_888_889,
            0.478_628_670_499_366,
            0.478_628_670_499_366,
            0.236_926_885_056_189,
            0.236_926_885_056_189,
        ];
        let (mid, half) = ((a + b) / 2.0, (b - a) / 2.0);
        half * X.iter().zip(W).map(|(x, w)| w * self.eval(mid + half * x)[1].norm()).sum::<f64>()
    }
}

/// Signed curvature of a planar curve from its first two derivatives.
fn curvature([_, d1, d2]: [Vector2<f64>; 3]) -> f64 {
    (d1.x * d2.y - d1.y * d2.x) / d1.norm().powi(3)
}

/// A robot's ground-truth motion.
#[derive(Clone, Debug)]
pub struct Trajectory {
    waypoints: Vec<Point2<f64>>,
    closed: bool,
    spline: Spline,
    /// Arc-length grid step (≤ [`GRID_STEP`], dividing the length evenly).
    ds: f64,
    /// Spline parameter at each grid node.
    u: Vec<f64>,
    /// d(parameter)/d(arc length) at each grid node, for Hermite interpolation between nodes.
    du: Vec<f64>,
    /// Speed at each grid node, m/s (v² is linear in s between nodes: constant acceleration).
    speed: Vec<f64>,
    /// Time at which each grid node is reached, s.
    time: Vec<f64>,
    terrain: Terrain,
    mount_height: f64,
}

impl Trajectory {
    /// The trajectory through `waypoints` (x, y) on `terrain`; a closed one returns to the first
    /// waypoint along the spline, heading smoothly into its start.
    pub fn new(
        waypoints: &[Point2<f64>],
        closed: bool,
        terrain: &Terrain,
        config: &TrajectoryConfig,
    ) -> Result<Trajectory, TrajectoryError> {
        check_config(config)?;
        if waypoints.len() < 2 {
            return Err(TrajectoryError::TooFewWaypoints(waypoints.len()));
        }
        let points: Vec<Vector2<f64>> = waypoints.iter().map(|p| p.coords).collect();
        let pairs = points.len() - usize::from(!closed);
        if let Some(i) = (0..pairs).find(|&i| (points[(i + 1) % points.len()] - points[i]).norm() < 1e-6) {
            return Err(TrajectoryError::RepeatedWaypoint(i));
        }
        let spline = Spline::through(&points, closed);
        let (ds, u, du) = arc_length_table(&spline);
        let speed = speed_profile(&spline, &u, ds, config);
        let time = node_times(&speed, ds);
        Ok(Trajectory {
            waypoints: waypoints.to_vec(),
            closed,
            spline,
            ds,
            u,
            du,
            speed,
            time,
            terrain: terrain.clone(),
            mount_height: config.mount_height,
        })
    }

    /// The waypoints the path goes through.
    pub fn waypoints(&self) -> &[Point2<f64>] {
        &self.waypoints
    }

    /// True when the path returns to its first waypoint.
    pub fn is_closed(&self) -> bool {
        self.closed
    }

    /// Path length in the plane, metres (the driven length on hills is slightly longer).
    pub fn length(&self) -> f64 {
        self.ds * (self.u.len() - 1) as f64
    }

    /// Seconds from the start to the end of the path.
    pub fn duration(&self) -> f64 {
        *self.time.last().unwrap_or(&0.0)
    }

    /// Horizontal speed at time `t`, m/s (0 outside the driven interval when starting/stopping at rest).
    pub fn speed(&self, t: f64) -> f64 {
        self.distance_and_speed(t).1
    }

    /// Arc length travelled and speed at time `t` (clamped to the driven interval).
    fn distance_and_speed(&self, t: f64) -> (f64, f64) {
        let t = t.clamp(0.0, self.duration());
        let j = self.time.partition_point(|&x| x <= t).clamp(1, self.time.len() - 1) - 1;
        let (v0, v1) = (self.speed[j], self.speed[j + 1]);
        let a = (v1 * v1 - v0 * v0) / (2.0 * self.ds);
        let tau = t - self.time[j];
        let s = (v0 * tau + 0.5 * a * tau * tau).clamp(0.0, self.ds);
        (j as f64 * self.ds + s, (v0 + a * tau).max(0.0))
    }

    /// Spline parameter at arc length `s`: cubic Hermite between grid nodes, with exact slopes.
    fn parameter(&self, s: f64) -> f64 {
        let last = self.u.len() - 2;
        let j = ((s / self.ds) as usize).min(last);
        let x = (s / self.ds - j as f64).clamp(0.0, 1.0);
        let (h00, h10, h01, h11) = hermite(x);
        h00 * self.u[j] + h10 * self.ds * self.du[j] + h01 * self.u[j + 1] + h11 * self.ds * self.du[j + 1]
    }

    /// Position (x, y) and heading (rad) of the robot after `s` metres.
    pub fn planar_at(&self, s: f64) -> (Point2<f64>, f64) {
        let [p, d, _] = self.spline.eval(self.parameter(s.clamp(0.0, self.length())));
        (Point2::from(p), d.y.atan2(d.x))
    }

    /// Points on the ground along the path every `step` metres (and at the end), for clearance checks.
    pub fn ground_samples(&self, step: f64) -> Vec<Point3<f64>> {
        let n = (self.length() / step).ceil() as usize;
        (0..=n)
            .map(|i| {
                let (p, _) = self.planar_at(i as f64 * self.length() / n as f64);
                Point3::new(p.x, p.y, self.terrain.height(p.x, p.y))
            })
            .collect()
    }

    /// Ground-truth pose of the sensor in the world frame at time `t` (seconds from the start).
    pub fn pose(&self, t: f64) -> Isometry3<f64> {
        let (s, _) = self.distance_and_speed(t);
        let (p, heading) = self.planar_at(s);
        ground_pose(&self.terrain, p, heading, self.mount_height)
    }
}

/// The sensor pose of a robot standing at `p` on `terrain` with `heading` (rad): body z along the
/// ground normal, x along the heading projected onto the ground plane (the robot pitches and rolls
/// with the slope), the sensor `mount_height` above the ground along the normal.
pub(crate) fn ground_pose(terrain: &Terrain, p: Point2<f64>, heading: f64, mount_height: f64) -> Isometry3<f64> {
    let normal = terrain.normal(p.x, p.y).into_inner();
    let forward = Vector3::new(heading.cos(), heading.sin(), 0.0);
    let x = (forward - normal * forward.dot(&normal)).normalize();
    let y = normal.cross(&x);
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, normal]));
    let ground = Point3::new(p.x, p.y, terrain.height(p.x, p.y));
    let origin = ground + normal * mount_height;
    Isometry3::from_parts(Translation3::from(origin.coords), UnitQuaternion::from_rotation_matrix(&rotation))
}

/// Rejects limits that would make the speed profile meaningless.
fn check_config(c: &TrajectoryConfig) -> Result<(), TrajectoryError> {
    let limits = [
        ("cruise_speed", c.cruise_speed),
        ("max_accel", c.max_accel),
        ("max_lateral_accel", c.max_lateral_accel),
        ("max_yaw_rate", c.max_yaw_rate),
    ];
    match limits.into_iter().find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
        Some((name, _)) => Err(TrajectoryError::BadLimit(name)),
        None if !c.mount_height.is_finite() => Err(TrajectoryError::BadLimit("mount_height")),
        None => Ok(()),
    }
}

/// The cubic Hermite basis functions at x ∈ [0, 1].
fn hermite(x: f64) -> (f64, f64, f64, f64) {
    let (x2, x3) = (x * x, x * x * x);
    (2.0 * x3 - 3.0 * x2 + 1.0, x3 - 2.0 * x2 + x, -2.0 * x3 + 3.0 * x2, x3 - x2)
}

/// Uniform arc-length grid over the spline: step, and parameter and its slope at each node.
fn arc_length_table(spline: &Spline) -> (f64, Vec<f64>, Vec<f64>) {
    // Dense cumulative length at sub-knots (32 per segment), then Newton inversion per grid node.
    const SUB: usize = 32;
    let mut knots: Vec<f64> = spline
        .knots
        .windows(2)
        .flat_map(|w| (0..SUB).map(move |k| w[0] + (w[1] - w[0]) * k as f64 / SUB as f64))
        .collect();
    knots.push(spline.end());
    let mut cumulative = vec![0.0];
    for w in knots.windows(2) {
        cumulative.push(cumulative.last().unwrap_or(&0.0) + spline.length(w[0], w[1]));
    }
    let total = *cumulative.last().unwrap_or(&0.0);
    let n = ((total / GRID_STEP).ceil() as usize).max(2);
    let ds = total / n as f64;
    let mut u = Vec::with_capacity(n + 1);
    for j in 0..=n {
        let s = j as f64 * ds;
        let k = cumulative.partition_point(|&c| c <= s).clamp(1, knots.len() - 1) - 1;
        let mut x = knots[k];
        for _ in 0..4 {
            let err = cumulative[k] + spline.length(knots[k], x) - s;
            x = (x - err / spline.eval(x)[1].norm()).clamp(knots[k], knots[k + 1]);
        }
        u.push(x);
    }
    let du = u.iter().map(|&x| 1.0 / spline.eval(x)[1].norm()).collect();
    (ds, u, du)
}

/// Speed at each grid node: the curvature limits (yaw rate ω = vκ, lateral acceleration v²κ), then
/// forward and backward passes bounding |dv²/ds| by 2·max_accel.
fn speed_profile(spline: &Spline, u: &[f64], ds: f64, c: &TrajectoryConfig) -> Vec<f64> {
    let n = u.len();
    // Curvature at nodes and half-way between, so a node's limit covers its neighbourhood.
    let kappa_at = |x: f64| curvature(spline.eval(x)).abs();
    let mut limit: Vec<f64> = (0..n)
        .map(|j| {
            let around = [u[j.saturating_sub(1)], u[j], u[(j + 1).min(n - 1)]];
            let k = kappa_at(u[j]).max(kappa_at((around[0] + u[j]) / 2.0)).max(kappa_at((u[j] + around[2]) / 2.0));
            c.cruise_speed.min(c.max_yaw_rate / k).min((c.max_lateral_accel / k).sqrt())
        })
        .collect();
    if c.start_at_rest {
        limit[0] = 0.0;
    }
    if c.stop_at_end {
        limit[n - 1] = 0.0;
    }
    let step = 2.0 * c.max_accel * ds;
    for j in 1..n {
        limit[j] = limit[j].min((limit[j - 1].powi(2) + step).sqrt());
    }
    for j in (0..n - 1).rev() {
        limit[j] = limit[j].min((limit[j + 1].powi(2) + step).sqrt());
    }
    limit
}

/// Time at each node when v² varies linearly between nodes: Δt = 2·ds / (v₀ + v₁).
fn node_times(speed: &[f64], ds: f64) -> Vec<f64> {
    let mut time = vec![0.0];
    for w in speed.windows(2) {
        // Both zero only on a path of a single grid step, which arc_length_table never makes.
        time.push(time.last().unwrap_or(&0.0) + 2.0 * ds / (w[0] + w[1]).max(1e-9));
    }
    time
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square() -> Vec<Point2<f64>> {
        vec![Point2::new(0.0, 0.0), Point2::new(20.0, 0.0), Point2::new(20.0, 20.0), Point2::new(0.0, 20.0)]
    }

    #[test]
    fn arc_length_parametrisation_has_unit_speed() {
        // Segments of very different lengths: the parametrisation must not kink at waypoints.
        let p = [
            Point2::new(0.0, 0.0),
            Point2::new(1.0, 0.0),
            Point2::new(11.0, 0.5),
            Point2::new(11.5, 3.0),
            Point2::new(30.0, 3.0),
        ];
        let t = Trajectory::new(&p, false, &Terrain::Flat(0.0), &TrajectoryConfig::default()).unwrap();
        let h = 1e-4;
        for i in 1..2000 {
            let s = t.length() * i as f64 / 2000.0;
            let (a, _) = t.planar_at(s - h);
            let (b, _) = t.planar_at(s + h);
            let speed = (b - a).norm() / (2.0 * h);
            // Where the curvature jumps at a waypoint the Hermite table ripples by a few 1e-4.
            assert!((speed - 1.0).abs() < 1e-3, "|dp/ds| = {speed} at s = {s}");
        }
    }

    #[test]
    fn closed_path_passes_its_waypoints_and_returns() {
        let t = Trajectory::new(&square(), true, &Terrain::Flat(0.0), &TrajectoryConfig::default()).unwrap();
        let start = t.pose(0.0).translation.vector;
        let end = t.pose(t.duration()).translation.vector;
        assert!((start - end).norm() < 1e-6);
        assert!((start - Vector3::new(0.0, 0.0, 0.7)).norm() < 1e-9);
        assert_eq!(t.speed(0.0), 0.0);
    }

    #[test]
    fn repeated_waypoints_are_rejected() {
        let p = [Point2::new(0.0, 0.0), Point2::new(0.0, 0.0)];
        let err = Trajectory::new(&p, false, &Terrain::Flat(0.0), &TrajectoryConfig::default()).unwrap_err();
        assert_eq!(err, TrajectoryError::RepeatedWaypoint(0));
    }
}
