//! `campus`: an outdoor 200 m × 200 m campus on rolling ground.
//!
//! A 3 × 3 grid of 12 m wide roads (centre lines x, y ∈ {−60, 0, 60}, from −90 to 90) frames four
//! inner blocks of buildings (an L-shaped library, towers, a long turned hall, a car park) and an
//! outer ring of smaller buildings and a park. Roads are lined with trees (trunk cylinder and
//! spherical canopy), lamp posts, hedges and parked cars. The ground is a sum of three gentle sine
//! waves (up to about ±4 m, slopes up to about 10 %), rendered as a 2 m triangle mesh that stays
//! within 6 mm of the analytic surface the robots drive on.

use super::{Builder, lanes, material, route};
use crate::noise::SplitMix;
use crate::trajectory::{Trajectory, TrajectoryConfig, TrajectoryError};
use crate::world::{Terrain, Wave, World};

/// Road centre lines (both axes).
const ROADS: [f64; 3] = [-60.0, 0.0, 60.0];
/// Roads run between these coordinates.
const ROAD_END: f64 = 90.0;
/// The rendered ground covers ±this, beyond the 100 m sensor range from any route.
const GROUND_EXTENT: f64 = 130.0;
/// Ground mesh cell, metres.
const GROUND_CELL: f64 = 2.0;
/// Corner radius of robot turns at intersections, metres.
const TURN: f64 = 8.0;

/// The rolling ground.
pub fn terrain() -> Terrain {
    Terrain::Hills(vec![
        Wave { amplitude: 2.5, kx: 0.035, ky: 0.012, phase: 0.3 },
        Wave { amplitude: 1.2, kx: -0.03, ky: 0.045, phase: 1.1 },
        Wave { amplitude: 0.25, kx: 0.11, ky: 0.07, phase: 2.0 },
    ])
}

/// The campus world.
pub fn world() -> World {
    let terrain = terrain();
    let mut c = Campus { b: Builder::default(), terrain: terrain.clone(), rng: SplitMix::new(0xCA4D_5EED) };
    c.buildings();
    c.car_park();
    c.street_furniture();
    c.park();
    let ground = terrain.render(-GROUND_EXTENT, GROUND_EXTENT, GROUND_CELL, material::GRASS);
    c.b.finish(terrain, ground)
}

/// Builder state: objects, the ground they stand on, and the layout generator.
struct Campus {
    b: Builder,
    terrain: Terrain,
    rng: SplitMix,
}

/// True when (x, y) is within `margin` of a road intersection.
fn near_crossing(x: f64, y: f64, margin: f64) -> bool {
    ROADS.iter().any(|&rx| (x - rx).abs() < margin) && ROADS.iter().any(|&ry| (y - ry).abs() < margin)
}

impl Campus {
    /// Ground height at (x, y).
    fn ground(&self, x: f64, y: f64) -> f64 {
        self.terrain.height(x, y)
    }

    /// A building of footprint `size` (x, y) centred at (x, y), turned by `yaw`, `height` above the
    /// lowest ground under it; its base is sunk 0.5 m so no gap shows on the slope.
    fn building(&mut self, x: f64, y: f64, size: [f64; 2], yaw: f64, height: f64) {
        let (c, s) = (yaw.cos(), yaw.sin());
        let mut low = f64::INFINITY;
        for i in 0..=4 {
            for j in 0..=4 {
                let (u, v) = ((i as f64 / 4.0 - 0.5) * size[0], (j as f64 / 4.0 - 0.5) * size[1]);
                low = low.min(self.ground(x + c * u - s * v, y + s * u + c * v));
            }
        }
        let base = low - 0.5;
        self.b.turned(x, y, base, [size[0], size[1], height + 0.5], yaw, material::FACADE);
    }

    /// The inner blocks' landmark buildings and the outer ring's smaller ones.
    fn buildings(&mut self) {
        // North-west: an L-shaped library and a turned pavilion.
        self.building(-33.0, 20.0, [26.0, 12.0], 0.0, 14.0);
        self.building(-40.0, 36.0, [12.0, 20.0], 0.0, 14.0);
        self.building(-22.0, 40.0, [12.0, 8.0], 0.35, 5.0);
        // North-east: two towers and a kiosk.
        self.building(22.0, 22.0, [16.0, 16.0], 0.0, 28.0);
        self.building(41.0, 38.0, [10.0, 16.0], 0.0, 18.0);
        self.building(40.0, 18.0, [5.0, 4.0], 0.8, 3.0);
        // South-east: a long hall turned against the grid.
        self.building(30.0, -30.0, [32.0, 12.0], 0.5, 10.0);
        // South-west: a small building beside the car park.
        self.building(-20.0, -44.0, [12.0, 8.0], 0.0, 6.0);
        // Outer ring: a row of houses north and south, labs east.
        for i in 0..6 {
            let x = -75.0 + 30.0 * i as f64;
            let (w, d, h) = (self.rng.range(10.0, 18.0), self.rng.range(8.0, 12.0), self.rng.range(5.0, 12.0));
            let yaw = self.rng.range(-0.2, 0.2);
            self.building(x, 82.0, [w, d], yaw, h);
            let h = self.rng.range(4.0, 9.0);
            self.building(x + 8.0, -84.0, [w * 0.8, d], -yaw, h);
        }
        for y in [-30.0, 30.0] {
            let h = self.rng.range(8.0, 16.0);
            self.building(84.0, y, [14.0, 30.0], 0.0, h);
        }
    }

    /// A parked car: body and glazed cabin, facing `yaw`.
    fn car(&mut self, x: f64, y: f64, yaw: f64) {
        let z = self.ground(x, y);
        let paint = material::CAR * self.rng.range(0.4, 1.2) as f32;
        self.b.turned(x, y, z + 0.3, [4.4, 1.8, 0.75], yaw, paint.min(1.0));
        let (bx, by) = (x - 0.3 * yaw.cos(), y - 0.3 * yaw.sin());
        self.b.turned(bx, by, z + 1.05, [2.4, 1.6, 0.5], yaw, material::GLASS);
    }

    /// The south-west block's car park: three rows of nose-in bays, about 70 % occupied.
    fn car_park(&mut self) {
        for row in 0..3 {
            let y = -16.0 - 9.0 * row as f64;
            for bay in 0..11 {
                let x = -46.0 + 2.8 * bay as f64;
                if self.rng.chance(0.7) {
                    let yaw = std::f64::consts::FRAC_PI_2 + self.rng.range(-0.08, 0.08);
                    self.car(x, y, yaw);
                }
            }
        }
    }

    /// Along every road: trees both sides, lamp posts, hedges and kerbside parked cars.
    fn street_furniture(&mut self) {
        for &r in &ROADS {
            let mut s = -ROAD_END;
            while s <= ROAD_END {
                for side in [-1.0, 1.0] {
                    self.roadside(r, s, side, true);
                    self.roadside(r, s, side, false);
                }
                s += 6.0;
            }
        }
    }

    /// The furniture at station `s` along the road at `r` (along x when `along_x`) on `side`.
    fn roadside(&mut self, r: f64, s: f64, side: f64, along_x: bool) {
        let at = |offset: f64| {
            if along_x { (s, r + side * offset) } else { (r + side * offset, s) }
        };
        let station = (s + ROAD_END) as i64;
        let (x, y) = at(8.5);
        if station % 12 == 0 && !near_crossing(x, y, 14.0) && self.rng.chance(0.8) {
            self.tree(x, y);
        }
        let (x, y) = at(7.0);
        if station % 30 == 6 && side > 0.0 && !near_crossing(x, y, 12.0) {
            let z = self.ground(x, y);
            self.b.cylinder(x, y, 0.08, [z - 0.2, z + 6.0], material::STEEL);
            self.b.turned(x, y, z + 6.0, [0.6, 0.3, 0.15], 0.0, material::STEEL);
        }
        let (x, y) = at(10.5);
        if station % 24 == 0 && !near_crossing(x, y, 16.0) && self.rng.chance(0.5) {
            let z = self.ground(x, y);
            let size = if along_x { [5.5, 0.8, 1.0] } else { [0.8, 5.5, 1.0] };
            self.b.turned(x, y, z - 0.3, size, 0.0, material::FOLIAGE);
        }
        let (x, y) = at(4.3);
        if !near_crossing(x, y, 16.0) && self.rng.chance(0.35) {
            let yaw = if along_x { 0.0 } else { std::f64::consts::FRAC_PI_2 } + self.rng.range(-0.04, 0.04);
            self.car(x, y, yaw);
        }
    }

    /// A tree: trunk cylinder and a spherical canopy well above sensor height.
    fn tree(&mut self, x: f64, y: f64) {
        let z = self.ground(x, y);
        let trunk = self.rng.range(2.6, 3.6);
        let radius = self.rng.range(1.4, 2.4);
        self.b.cylinder(x, y, self.rng.range(0.12, 0.3), [z - 0.3, z + trunk + 0.5], material::BARK);
        self.b.sphere([x, y, z + trunk + radius * 0.8], radius, material::FOLIAGE);
    }

    /// A park in the west of the outer ring: scattered trees and a few benches.
    fn park(&mut self) {
        for _ in 0..45 {
            let (x, y) = (self.rng.range(-100.0, -70.0), self.rng.range(-50.0, 50.0));
            if (y - 0.0).abs() > 9.0 {
                self.tree(x, y);
            }
        }
        for y in [-20.0, 15.0, 35.0] {
            let z = self.ground(-72.0, y);
            self.b.turned(-72.0, y, z, [0.6, 1.8, 0.45], 0.0, material::WOOD);
        }
    }
}

/// Robot 0: once round the north-west block (240 m).
#[rustfmt::skip]
fn north_west() -> Vec<[f64; 2]> {
    vec![[-30.0, 0.0], [0.0, 0.0], [0.0, 60.0], [-60.0, 60.0], [-60.0, 0.0], [-30.0, 0.0]]
}

/// Robot 1: once round the north-east block, sharing the road x = 0 with robot 0.
#[rustfmt::skip]
fn north_east() -> Vec<[f64; 2]> {
    vec![[60.0, 30.0], [60.0, 60.0], [0.0, 60.0], [0.0, 0.0], [60.0, 0.0], [60.0, 30.0]]
}

/// Robot 2: once round the two southern blocks, sharing the road y = 0 with robots 0 and 1.
#[rustfmt::skip]
fn south() -> Vec<[f64; 2]> {
    vec![[-60.0, -30.0], [-60.0, -60.0], [60.0, -60.0], [60.0, 0.0], [-60.0, 0.0], [-60.0, -30.0]]
}

/// Robot 3: one way from the west end of the north road to the east end of the south road.
fn crossing() -> Vec<[f64; 2]> {
    vec![[-90.0, 60.0], [60.0, 60.0], [60.0, -60.0], [90.0, -60.0]]
}

/// The four campus robots: outdoor robots at 2 m/s with the sensor 1 m above the ground.
pub fn robots(terrain: &Terrain) -> Vec<Trajectory> {
    let config = TrajectoryConfig { cruise_speed: 2.0, mount_height: 1.0, ..TrajectoryConfig::default() };
    [north_west(), north_east(), south(), crossing()].iter().map(|c| route(c, TURN, terrain, &config)).collect()
}

/// How a car drives the campus roads at `speed` (m/s) on the straights: already at speed at t = 0
/// and not stopping at the end; 3 m/s² braking and acceleration, corners at up to 6 m/s² lateral
/// acceleration and 1 rad/s yaw rate (about 7 m/s round the 8 m corners); the sensor on the roof,
/// 1.73 m up (KITTI's).
pub fn car_config(speed: f64) -> TrajectoryConfig {
    TrajectoryConfig {
        cruise_speed: speed,
        max_accel: 3.0,
        max_lateral_accel: 6.0,
        max_yaw_rate: 1.0,
        mount_height: 1.73,
        start_at_rest: false,
        stop_at_end: false,
    }
}

/// A car on robot 3's crossing (150 m west to east, 120 m south, 30 m east) driven as
/// [`car_config`] says.
pub fn car(terrain: &Terrain, speed: f64) -> Result<Trajectory, TrajectoryError> {
    Trajectory::new(&lanes(&crossing(), TURN), false, terrain, &car_config(speed))
}
