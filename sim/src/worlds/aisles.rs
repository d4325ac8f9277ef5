//! `aisles`: two closed halls full of identical rack rows, for perceptual-aliasing tests.
//!
//! Every row is the same four-bay, double-deep rack with the same loads in every bay, so a view
//! down any aisle of either hall is the same view. The halls differ only globally: hall A
//! (34.4 m × 20.8 m, y 0–20.8) has two blocks of three rows and a cross aisle; hall B (24 m × 15 m,
//! y 23–38) has one block of two rows and a wide open end. A 2.2 m fire wall (y 20.8–23) without
//! openings separates them, so nothing seen from one hall is seen from the other.

use super::rack::{self, Load, Run, STANDARD, Slot};
use super::{Builder, material, route};
use crate::trajectory::{Trajectory, TrajectoryConfig};
use crate::world::{Terrain, World};

/// Ceiling height, metres.
const CEILING: f64 = 9.0;
/// Walls rise past the ceiling so no ray slips through the seam.
const WALL_TOP: f64 = 9.5;
/// Corner radius of robot turns, metres.
const TURN: f64 = 2.0;
/// Where hall B's floor space starts (north face of the fire wall).
pub const HALL_B_SOUTH: f64 = 23.0;
/// Where hall A's floor space ends (south face of the fire wall).
pub const HALL_A_NORTH: f64 = 20.8;

/// The same load in every bay: only the level and position decide it.
fn load(s: Slot) -> Option<Load> {
    let size = match (s.level, s.slot, s.deep) {
        (3, 1, _) => return None,
        (0, 0, _) => [1.1, 0.9, 1.1],
        (0, 1, _) => [0.9, 0.9, 0.7],
        (1, 0, 0) => [1.2, 1.0, 1.2],
        (1, _, _) => [1.0, 0.8, 0.9],
        (2, 1, 1) => return None,
        (2, _, _) => [1.2, 1.0, 0.6],
        _ => [0.8, 0.8, 1.0],
    };
    Some(Load { size, shift: 0.0, reflectivity: material::CARDBOARD })
}

/// Three (hall A) or two (hall B) identical rows starting at `x0` every 5.8 m from `y0`.
fn rows(b: &mut Builder, x0: f64, y0: f64, count: usize) {
    for i in 0..count {
        rack::row(b, &STANDARD, (x0, y0 + 5.8 * i as f64), Run::X, 4, 2, load);
    }
}

/// The two-hall world.
pub fn world() -> World {
    let mut b = Builder::default();
    b.plane(CEILING, material::CEILING);
    b.walls([0.0, 0.0], [34.4, HALL_A_NORTH], 0.4, WALL_TOP);
    b.walls([0.0, HALL_B_SOUTH], [24.0, 38.0], 0.4, WALL_TOP);
    b.block([-0.4, HALL_A_NORTH, 0.0], [34.8, HALL_B_SOUTH, WALL_TOP], material::WALL);
    rows(&mut b, 4.0, 3.4, 3);
    rows(&mut b, 19.2, 3.4, 3);
    rows(&mut b, 4.0, HALL_B_SOUTH + 3.4, 2);
    let terrain = Terrain::Flat(0.0);
    let ground = terrain.render(0.0, 0.0, 1.0, material::FLOOR);
    b.finish(terrain, ground)
}

/// Robot 0: serpentine through all four aisles of hall A.
#[rustfmt::skip]
fn hall_a() -> Vec<[f64; 2]> {
    vec![[2.0, 1.7], [32.4, 1.7], [32.4, 7.5], [2.0, 7.5], [2.0, 13.3], [32.4, 13.3], [32.4, 19.1], [2.0, 19.1]]
}

/// Robot 1: serpentine through the three aisles of hall B, then down its open end.
#[rustfmt::skip]
fn hall_b() -> Vec<[f64; 2]> {
    vec![[2.0, 24.7], [17.2, 24.7], [17.2, 30.5], [2.0, 30.5], [2.0, 36.3], [21.5, 36.3], [21.5, 25.5]]
}

/// One robot per hall.
pub fn robots(terrain: &Terrain) -> Vec<Trajectory> {
    let config = TrajectoryConfig::default();
    vec![route(&hall_a(), TURN, terrain, &config), route(&hall_b(), TURN, terrain, &config)]
}
