//! The joint pose graph's input from what the station holds: the merged robots' keyframes, decoded,
//! at their newest poses, and the placements of a global map.

use std::sync::Arc;

use cloud::PointCloud;
use nalgebra::Isometry3;
use proto::{GlobalMap, MergeStatus};
use rayon::prelude::*;

use super::ingest;
use super::merge_job::RobotSnapshot;
use crate::joint::RobotPath;

/// The merged robots of a global map, ready for [`crate::joint::solve`].
pub struct JointInput {
    /// Robot ids, one per path.
    pub robots: Vec<u32>,
    /// Their sessions, one per path.
    pub sessions: Vec<u64>,
    /// Per path, its keyframes' sequence numbers.
    pub seqs: Vec<Vec<u64>>,
    /// Each merged robot's keyframes and placement.
    pub paths: Vec<RobotPath>,
    /// Index of the map's reference robot in `paths`.
    pub reference: usize,
}

/// The robots `map` merged, from `fleet`; `None` when the reference robot is not among them. A
/// keyframe that no longer decodes is left out (it was checked when it arrived).
pub fn joint_input(fleet: &[RobotSnapshot], map: &GlobalMap) -> Option<JointInput> {
    let mut input = JointInput {
        robots: Vec::new(),
        sessions: Vec::new(),
        seqs: Vec::new(),
        paths: Vec::new(),
        reference: usize::MAX,
    };
    for placement in map.robots.iter().filter(|p| p.status() == MergeStatus::Merged) {
        let Some(snapshot) = fleet.iter().find(|s| s.robot == placement.robot && s.session == placement.session) else {
            continue;
        };
        let Some(Ok(transform)) = placement.transform.as_ref().map(Isometry3::try_from) else { continue };
        let decoded: Vec<(u64, Isometry3<f64>, Arc<PointCloud>)> = snapshot
            .keyframes
            .par_iter()
            .filter_map(|kf| Some((kf.seq, kf.pose, Arc::new(ingest::held_keyframe(&kf.bytes).ok()?.cloud))))
            .collect();
        input.seqs.push(decoded.iter().map(|d| d.0).collect());
        let (poses, clouds) = decoded.into_iter().map(|(_, pose, cloud)| (pose, cloud)).unzip();
        if placement.robot == map.reference_robot && placement.session == map.reference_session {
            input.reference = input.paths.len();
        }
        input.robots.push(placement.robot);
        input.sessions.push(placement.session);
        input.paths.push(RobotPath { placement: transform, poses, clouds });
    }
    (input.reference < input.paths.len()).then_some(input)
}
