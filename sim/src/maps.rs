//! Every robot's exact map of a scenario and the truth between them: what a map merge is checked
//! against, to the last bit, in tests and in comparisons with other merging pipelines.

use cloud::PointCloud;
use nalgebra::Isometry3;

use crate::{Scenario, SimConfig, SimError, Simulator};

/// Why the maps of a scenario could not be built.
#[derive(Debug, thiserror::Error)]
pub enum MapsError {
    /// A robot's simulator could not be set up.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// The voxel size is not positive.
    #[error(transparent)]
    Voxel(#[from] cloud::voxel::InvalidVoxelSize),
}

/// One map per robot of a scenario, each in its robot's frame at t = 0
/// ([`Simulator::exact_map`]), with the world pose of that frame.
#[derive(Clone, Debug)]
pub struct RobotMaps {
    /// Robot `r`'s map (0-based), in its frame at t = 0.
    pub maps: Vec<PointCloud>,
    /// World pose of each map's frame: robot `r`'s sensor pose at t = 0.
    pub frames: Vec<Isometry3<f64>>,
}

impl RobotMaps {
    /// The maps of every robot of `scenario` from every `stride`-th sweep, voxelised at `voxel`
    /// metres, with the default sensor (noise-free poses: the points keep the range noise).
    pub fn build(scenario: &Scenario, stride: usize, voxel: f32) -> Result<RobotMaps, MapsError> {
        let mut robot_maps = RobotMaps { maps: Vec::new(), frames: Vec::new() };
        for robot in 0..scenario.robots().len() {
            let sim = Simulator::new(scenario.clone(), robot, SimConfig::default())?;
            robot_maps.maps.push(sim.exact_map(stride, voxel)?);
            robot_maps.frames.push(sim.pose_at(0.0));
        }
        Ok(robot_maps)
    }

    /// `T0_a⁻¹ T0_b`: maps map `b`'s points into map `a`'s frame.
    pub fn truth(&self, a: usize, b: usize) -> Isometry3<f64> {
        self.frames[a].inverse() * self.frames[b]
    }
}
