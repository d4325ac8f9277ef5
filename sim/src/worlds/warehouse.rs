//! `warehouse`: a 40 m × 30 m hall modelled on the EMR-FLOAM paper's Gazebo warehouse.
//!
//! A fire wall at x = 20 with a 6 m wide, 4.5 m high door (y 12–18) splits the floor into a west hall, whose
//! rack rows run east–west, and an east hall, whose rows run north–south, so the halls look
//! different and what one robot sees of the other hall is limited to the doorway. Racks are loaded
//! irregularly (sizes, gaps), the walls carry pilasters and dock doors, a steel roof structure sits
//! under a ceiling at 9 m, and pillars, forklifts, pallets and bins stand around.
//!
//! Lanes (robot paths run along their centres): west hall x = 2.0 and 17.5, y = 1.6, 6.1, 12.0,
//! 17.8, 22.8; east hall x = 22.1, 26.9, 32.8, 37.9, y = 2.0 and 23.0; through the door y = 13.2–16.8.

use super::rack::{self, Load, Run, STANDARD, Slot};
use super::{Builder, material, route};
use crate::noise::SplitMix;
use crate::trajectory::{Trajectory, TrajectoryConfig};
use crate::world::{Terrain, World};

/// Ceiling height, metres.
pub const CEILING: f64 = 9.0;
/// Walls rise past the ceiling so no ray slips through the seam.
const WALL_TOP: f64 = 9.5;
/// Corner radius of robot turns in the aisles, metres.
const TURN: f64 = 2.0;

/// The warehouse world.
pub fn world() -> World {
    let mut b = Builder::default();
    b.plane(CEILING, material::CEILING);
    shell(&mut b);
    roof(&mut b);
    let mut rng = SplitMix::new(0x57A2_E405);
    west_racks(&mut b, &mut rng);
    east_racks(&mut b, &mut rng);
    loose_objects(&mut b);
    let terrain = Terrain::Flat(0.0);
    let ground = terrain.render(0.0, 0.0, 1.0, material::FLOOR);
    b.finish(terrain, ground)
}

/// Outer walls with pilasters and dock doors, and the fire wall with its doorway.
fn shell(b: &mut Builder) {
    let t = 0.4;
    // North wall in pieces around three dock doors (x 25–28, 30–33, 35–38, 4.2 m high).
    b.block([-t, -t, 0.0], [40.0 + t, 0.0, WALL_TOP], material::WALL);
    b.block([-t, 0.0, 0.0], [0.0, 30.0, WALL_TOP], material::WALL);
    b.block([40.0, 0.0, 0.0], [40.0 + t, 30.0, WALL_TOP], material::WALL);
    let doors = [25.0, 30.0, 35.0];
    let mut x = -t;
    for d in doors {
        b.block([x, 30.0, 0.0], [d, 30.0 + t, WALL_TOP], material::WALL);
        b.block([d, 30.0, 4.2], [d + 3.0, 30.0 + t, WALL_TOP], material::WALL);
        // Roll-up door set back in the opening: a step in the wall's profile.
        b.block([d, 30.25, 0.0], [d + 3.0, 30.0 + t, 4.2], material::STEEL);
        x = d + 3.0;
    }
    b.block([x, 30.0, 0.0], [40.0 + t, 30.0 + t, WALL_TOP], material::WALL);
    // Pilasters every 6 m stand 0.3 m proud of the walls: cues along otherwise flat walls.
    for i in 1..7 {
        let x = 6.0 * i as f64 - 1.0;
        b.block([x - 0.2, 0.0, 0.0], [x + 0.2, 0.3, WALL_TOP], material::WALL);
        if !doors.iter().any(|d| (d - 0.3..d + 3.3).contains(&x)) {
            b.block([x - 0.2, 29.7, 0.0], [x + 0.2, 30.0, WALL_TOP], material::WALL);
        }
    }
    for i in 1..5 {
        let y = 6.0 * i as f64;
        b.block([0.0, y - 0.2, 0.0], [0.3, y + 0.2, WALL_TOP], material::WALL);
        b.block([39.7, y - 0.2, 0.0], [40.0, y + 0.2, WALL_TOP], material::WALL);
    }
    // The fire wall and its door (y 12-18, 4.5 m high).
    b.block([19.8, 0.0, 0.0], [20.2, 12.0, WALL_TOP], material::WALL);
    b.block([19.8, 18.0, 0.0], [20.2, 30.0, WALL_TOP], material::WALL);
    b.block([19.8, 12.0, 4.5], [20.2, 18.0, WALL_TOP], material::WALL);
}

/// Steel roof girders across the hall and purlins along it, under the ceiling.
fn roof(b: &mut Builder) {
    for i in 0..7 {
        let x = 2.5 + 6.0 * i as f64;
        b.block([x - 0.15, 0.0, 8.3], [x + 0.15, 30.0, 8.9], material::STEEL);
    }
    for y in [7.5, 15.0, 22.5] {
        b.block([0.0, y - 0.1, 8.7], [40.0, y + 0.1, 8.9], material::STEEL);
    }
}

/// A random load: mostly present, of varied size and wrapping.
fn random_load(rng: &mut SplitMix, empty: f64) -> Option<Load> {
    if rng.chance(empty) {
        return None;
    }
    let size = [rng.range(0.6, 1.25), rng.range(0.6, 1.0), rng.range(0.3, 1.2)];
    let reflectivity = if rng.chance(0.3) { material::WRAP } else { material::CARDBOARD };
    Some(Load { size, shift: rng.range(-0.15, 0.15), reflectivity })
}

/// West hall: four rows along x (x 4.0–15.2), single or double deep, irregularly loaded.
fn west_racks(b: &mut Builder, rng: &mut SplitMix) {
    for (y0, deep, empty) in [(3.2, 1, 0.2), (7.8, 2, 0.3), (13.8, 2, 0.15), (19.4, 1, 0.4)] {
        rack::row(b, &STANDARD, (4.0, y0), Run::X, 4, deep, |_: Slot| random_load(rng, empty));
    }
    // A pillar stands in row 2 at a bay boundary, as building columns do.
    b.block([9.35, 8.75, 0.0], [9.85, 9.25, WALL_TOP], material::WALL);
}

/// East hall: three rows along y (y 4.0–20.8).
fn east_racks(b: &mut Builder, rng: &mut SplitMix) {
    for (x0, deep, empty) in [(24.0, 1, 0.25), (28.6, 2, 0.2), (34.6, 1, 0.35)] {
        rack::row(b, &STANDARD, (x0, 4.0), Run::Y, 6, deep, |_: Slot| random_load(rng, empty));
    }
    b.block([29.55, 12.15, 0.0], [30.05, 12.65, WALL_TOP], material::WALL);
}

/// A forklift: body, mast with raised forks, overhead guard on four posts.
fn forklift(b: &mut Builder, x: f64, y: f64, yaw: f64) {
    let (c, s) = (yaw.cos(), yaw.sin());
    let at = |u: f64, v: f64| (x + c * u - s * v, y + s * u + c * v);
    let (bx, by) = at(0.0, 0.0);
    b.turned(bx, by, 0.1, [2.3, 1.2, 1.2], yaw, material::YELLOW);
    let (mx, my) = at(1.3, 0.0);
    b.turned(mx, my, 0.05, [0.25, 1.0, 2.6], yaw, material::STEEL);
    let (fx, fy) = at(1.9, 0.0);
    b.turned(fx, fy, 0.6, [1.1, 0.9, 0.05], yaw, material::STEEL);
    for (u, v) in [(-0.5, -0.5), (-0.5, 0.5), (0.5, -0.5), (0.5, 0.5)] {
        let (px, py) = at(u, v);
        b.turned(px, py, 1.3, [0.06, 0.06, 0.9], yaw, material::STEEL);
    }
    let (gx, gy) = at(0.0, 0.0);
    b.turned(gx, gy, 2.2, [1.2, 1.15, 0.08], yaw, material::STEEL);
}

/// Pillars, forklifts, staged pallets, bins and crates in the open areas, clear of the lanes.
fn loose_objects(b: &mut Builder) {
    for (x, y) in [(10.0, 26.0), (30.0, 26.5)] {
        b.block([x - 0.25, y - 0.25, 0.0], [x + 0.25, y + 0.25, WALL_TOP], material::WALL);
    }
    forklift(b, 6.0, 27.2, 0.35);
    forklift(b, 34.0, 27.0, -1.3);
    // Staged pallets and stacks, some turned as they were dropped.
    for (x, y, h, yaw) in
        [(13.0, 27.5, 0.45, 0.0), (14.7, 27.2, 1.3, 0.2), (16.6, 26.4, 0.9, -0.5), (16.8, 28.4, 1.6, 0.05)]
    {
        b.turned(x, y, 0.0, [1.2, 1.0, h], yaw, material::WOOD);
    }
    for (x, y, h) in [(26.5, 28.3, 1.1), (27.8, 28.3, 0.7), (31.5, 28.2, 1.4), (37.0, 28.0, 1.0), (38.4, 28.2, 1.8)] {
        b.turned(x, y, 0.0, [1.2, 1.0, 0.15], 0.0, material::WOOD);
        b.turned(x, y, 0.15, [1.1, 0.9, h], 0.0, material::WRAP);
    }
    for (x, y) in [(2.0, 28.6), (2.7, 28.7), (2.3, 27.9), (10.0, 0.65), (10.7, 0.65)] {
        b.cylinder(x, y, 0.3, [0.0, 0.9], material::PLASTIC);
    }
    for (y, h) in [(9.0, 1.4), (10.4, 0.9), (15.5, 2.0)] {
        b.turned(39.3, y, 0.0, [0.8, 1.2, h], 0.0, material::CARDBOARD);
    }
    b.turned(24.5, 26.2, 0.0, [1.5, 1.5, 2.2], 0.6, material::CARDBOARD);
}

/// Robot 0 of `warehouse-small`: twice round the west hall and back to its start, the second lap
/// with a short excursion through the door.
#[rustfmt::skip]
fn west_loop() -> Vec<[f64; 2]> {
    vec![
        // Lap 1: aisles 1-3 alternately west and east, the north lane, back down the east lane.
        [2.0, 1.6], [17.5, 1.6], [17.5, 6.1], [2.0, 6.1], [2.0, 12.0], [17.5, 12.0], [17.5, 17.8], [2.0, 17.8],
        [2.0, 22.8], [17.5, 22.8], [17.5, 1.6], [2.0, 1.6],
        // Lap 2: aisles 1-2 the other way, the north lane, through the door and back.
        [2.0, 6.1], [17.5, 6.1], [17.5, 12.0], [2.0, 12.0], [2.0, 22.8], [17.5, 22.8], [17.5, 16.8], [20.3, 16.8],
        [20.3, 13.2], [17.5, 13.2], [17.5, 1.6], [2.0, 1.6],
    ]
}

/// Robot 1 of `warehouse-small`: one serpentine through the east hall, never revisiting a place.
#[rustfmt::skip]
fn east_serpentine() -> Vec<[f64; 2]> {
    vec![[37.9, 2.0], [37.9, 23.0], [32.8, 23.0], [32.8, 2.0], [26.9, 2.0], [26.9, 23.0], [22.1, 23.0], [22.1, 2.0]]
}

/// Robot 0 of `warehouse-large`: a loop through both halls, back to its start.
#[rustfmt::skip]
fn grand_loop() -> Vec<[f64; 2]> {
    vec![
        [2.0, 1.6], [17.5, 1.6], [17.5, 6.1], [2.0, 6.1], [2.0, 12.0], [17.5, 12.0], [17.5, 15.0], [22.1, 15.0],
        [22.1, 2.0], [26.9, 2.0], [26.9, 23.0], [32.8, 23.0], [32.8, 2.0], [37.9, 2.0], [37.9, 23.0], [22.1, 23.0],
        [22.1, 17.0], [17.5, 17.0], [17.5, 22.8], [2.0, 22.8], [2.0, 1.6],
    ]
}

/// Robot 1 of `warehouse-large`: from the east hall through the doorway and down the west aisles.
#[rustfmt::skip]
fn east_to_west() -> Vec<[f64; 2]> {
    vec![
        [22.1, 11.0], [22.1, 2.0], [37.9, 2.0], [37.9, 23.0], [32.8, 23.0], [32.8, 2.0], [26.9, 2.0], [26.9, 23.0],
        [22.1, 23.0], [22.1, 16.0], [17.5, 16.0], [17.5, 22.8], [2.0, 22.8], [2.0, 17.8], [17.5, 17.8], [17.5, 12.0],
        [2.0, 12.0], [2.0, 6.1], [17.5, 6.1], [17.5, 1.6], [2.0, 1.6],
    ]
}

/// The robots of `warehouse-small`: a loop in the west hall, a slower one-way pass in the east.
pub fn small_overlap(terrain: &Terrain) -> Vec<Trajectory> {
    let slow = TrajectoryConfig { cruise_speed: 0.9, ..TrajectoryConfig::default() };
    vec![
        route(&west_loop(), TURN, terrain, &TrajectoryConfig::default()),
        route(&east_serpentine(), TURN, terrain, &slow),
    ]
}

/// The robots of `warehouse-large`: both cover most of both halls.
pub fn large_overlap(terrain: &Terrain) -> Vec<Trajectory> {
    let config = TrajectoryConfig::default();
    vec![route(&grand_loop(), TURN, terrain, &config), route(&east_to_west(), TURN, terrain, &config)]
}
