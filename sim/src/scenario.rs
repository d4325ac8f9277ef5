//! Named scenarios: a world, the robots' trajectories through it, and the sequence length.
//!
//! Figures (path lengths in the plane; overlap of robots 0 and 1 as the IoU of the 1 m voxels of
//! their scanned maps, and the share of robot 1's path within 3 m of robot 0's; see the tests):
//!
//! | scenario | frames | robots | voxel IoU | shared path |
//! |---|---|---|---|---|
//! | `warehouse-small` | 1720 | 228 m loop (1.5 m/s cruise), 95 m one way (0.9 m/s) | 0.47 | 7 % |
//! | `warehouse-large` | 1562 | 210 m loop, 205 m one way | 0.90 | 94 % |
//! | `campus` | 1812 | 226 m, 226 m, 346 m loops, 293 m one way (2 m/s) | 0.25-0.43 pairwise | 16-51 % |
//! | `aisles` | 956 | 134 m, 68 m | 0 | 0 % |
//!
//! In `warehouse-small` the paths meet only at the fire-wall door, but a LiDAR sees far: much of
//! what each robot maps is seen through the door, hence the voxel overlap despite the paths.

use std::sync::Arc;

use crate::trajectory::{Trajectory, TrajectoryError};
use crate::world::World;
use crate::worlds::{aisles, campus, warehouse};

/// Frame rate the scenario lengths are counted in (all built-in sensors spin at 10 Hz).
pub const FRAME_RATE: f64 = 10.0;

/// The name and one-line description of a built-in scenario.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ScenarioInfo {
    /// Name used on the command line.
    pub name: &'static str,
    /// What it is for, in one line.
    pub description: &'static str,
}

/// The built-in scenarios.
pub const CATALOG: [ScenarioInfo; 4] = [
    ScenarioInfo {
        name: "warehouse-small",
        description: "40x30 m warehouse, 2 robots, small overlap: robot 1 loops the west hall twice \
                      and returns to its start (230 m), robot 2 crosses the east hall once (95 m)",
    },
    ScenarioInfo {
        name: "warehouse-large",
        description: "same warehouse, 2 robots covering both halls (large overlap): robot 1 \
                      loops back to its start (210 m), robot 2 goes one way (205 m)",
    },
    ScenarioInfo {
        name: "campus",
        description: "200x200 m outdoor campus on rolling ground, 4 robots at 2 m/s: loops round \
                      three blocks sharing roads (226-346 m) and a 293 m one-way crossing",
    },
    ScenarioInfo {
        name: "aisles",
        description: "two sealed halls of identical rack rows, one robot in each: the same local \
                      look, no place in common (a merge must refuse them)",
    },
];

/// A scenario name that is not in the catalog.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown scenario {name:?}; the scenarios are: {}", scenario_names().join(", "))]
pub struct UnknownScenario {
    /// The name asked for.
    pub name: String,
}

/// The names of the built-in scenarios.
pub fn scenario_names() -> Vec<&'static str> {
    CATALOG.iter().map(|s| s.name).collect()
}

/// A world with robots moving through it on a common clock starting at t = 0.
#[derive(Clone, Debug)]
pub struct Scenario {
    name: String,
    description: String,
    world: Arc<World>,
    robots: Vec<Trajectory>,
    frames: usize,
}

impl Scenario {
    /// A built-in scenario by name.
    pub fn by_name(name: &str) -> Result<Scenario, UnknownScenario> {
        let info = CATALOG.iter().find(|s| s.name == name).ok_or_else(|| UnknownScenario { name: name.to_owned() })?;
        let (world, robots) = match info.name {
            "warehouse-small" => {
                let w = warehouse::world();
                let r = warehouse::small_overlap(w.terrain());
                (w, r)
            }
            "warehouse-large" => {
                let w = warehouse::world();
                let r = warehouse::large_overlap(w.terrain());
                (w, r)
            }
            "campus" => {
                let w = campus::world();
                let r = campus::robots(w.terrain());
                (w, r)
            }
            _ => {
                let w = aisles::world();
                let r = aisles::robots(w.terrain());
                (w, r)
            }
        };
        Ok(Scenario::new(info.name, info.description, Arc::new(world), robots))
    }

    /// `campus-car`: the campus world with one car driving its roads at `speed` m/s (see
    /// [`campus::car`]); an invalid speed is a [`TrajectoryError`].
    pub fn campus_car(speed: f64) -> Result<Scenario, TrajectoryError> {
        let world = campus::world();
        let car = campus::car(world.terrain(), speed)?;
        let description = format!("the campus roads driven by a car at {speed} m/s");
        Ok(Scenario::new("campus-car", &description, Arc::new(world), vec![car]))
    }

    /// A custom scenario; its length is the time the slowest robot needs to finish, at
    /// [`FRAME_RATE`].
    pub fn new(name: &str, description: &str, world: Arc<World>, robots: Vec<Trajectory>) -> Scenario {
        let longest = robots.iter().map(Trajectory::duration).fold(0.0, f64::max);
        let frames = (longest * FRAME_RATE).ceil() as usize + 1;
        Scenario { name: name.to_owned(), description: description.to_owned(), world, robots, frames }
    }

    /// The scenario's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// One-line description.
    pub fn description(&self) -> &str {
        &self.description
    }

    /// The world.
    pub fn world(&self) -> &World {
        &self.world
    }

    /// The robots' trajectories, robot 0 first.
    pub fn robots(&self) -> &[Trajectory] {
        &self.robots
    }

    /// Sequence length in frames at [`FRAME_RATE`]: until the last robot has stopped (robots that
    /// finish earlier stay parked at their last waypoint).
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The same scenario with a different length (frames at [`FRAME_RATE`]).
    pub fn with_frames(mut self, frames: usize) -> Scenario {
        self.frames = frames;
        self
    }
}
