//! `emr-eval load --joint`: the station's joint pose graph ([`station::joint`]) run on what a
//! loaded station held at the end, timed and measured against the truth.
//!
//! The load bench's keyframes are at their true poses, so each robot's map is undistorted and the
//! rigid merge's error is its placement alone; the joint graph should bring every joined robot's
//! keyframes to the truth ((1) of [`station::joint`] moves them from that placement).

use std::collections::BTreeMap;
use std::time::Instant;

use cloud::se3::pose_error;
use cloud::trajectory::ate;
use nalgebra::Isometry3;
use proto::GlobalMap;
use serde::Serialize;
use station::joint::{self, Constraint, JointConfig, JointError, KeyframeRef};

use cloud::stats::Spread;
use station::service::joint_input::{JointInput, joint_input};
use station::service::merge_job::RobotSnapshot;

/// What the joint graph made of a loaded fleet.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct JointLoad {
    /// From the station's final snapshots to the optimised poses (decoding the keyframes, finding
    /// and checking the inter-robot edges, optimising), milliseconds.
    pub ms: f64,
    /// Of which finding and registering the inter-robot edges, milliseconds.
    pub edges_ms: f64,
    /// ... keeping those that agree, milliseconds.
    pub consistency_ms: f64,
    /// ... and building and optimising the graph, milliseconds.
    pub optimise_ms: f64,
    /// Merged robots given to the graph.
    pub robots: usize,
    /// Their keyframes: the graph's poses.
    pub keyframes: usize,
    /// Inter-robot edges whose registration passed its checks.
    pub registered: usize,
    /// Those that agreed with each other: the graph's inter-robot edges.
    pub kept: usize,
    /// Robots the kept edges link to the reference (the reference included).
    pub joined: usize,
    /// RMSE of the keyframe positions of the merged robots but the reference against the truth,
    /// as the rigid merge places them, metres (`None` without such robots).
    pub rigid_rmse_m: Option<f64>,
    /// The same with the joint graph's poses, metres.
    pub joint_rmse_m: Option<f64>,
    /// How far the kept inter-robot edges' measurements lie from the truth, metres (`None`
    /// without kept edges).
    pub edge_error_m: Option<Spread>,
    /// ... and degrees.
    pub edge_error_deg: Option<Spread>,
}

/// Runs the joint graph on `fleet` as `map` merged it; `frames` are each robot's frame in the world
/// (its keyframe poses are relative to it). `None` when the map's reference is not among the merged.
pub fn measure(
    fleet: &[RobotSnapshot],
    map: &GlobalMap,
    frames: &BTreeMap<u32, Isometry3<f64>>,
    config: &JointConfig,
) -> Result<Option<JointLoad>, JointError> {
    let started = Instant::now();
    let Some(input) = joint_input(fleet, map) else { return Ok(None) };
    let solution = joint::solve(&input.paths, input.reference, config)?;
    let ms = started.elapsed().as_secs_f64() * 1e3;
    let truth = truth(&input, frames);
    let (edge_metres, edge_degrees) = edge_errors(&solution.constraints, &truth);
    let rigid = |r: usize, k: usize| input.paths[r].placed(k);
    let optimised = |r: usize, k: usize| solution.poses[r][k];
    Ok(Some(JointLoad {
        ms,
        edges_ms: solution.timing.edges.as_secs_f64() * 1e3,
        consistency_ms: solution.timing.consistency.as_secs_f64() * 1e3,
        optimise_ms: solution.timing.optimise.as_secs_f64() * 1e3,
        robots: input.paths.len(),
        keyframes: input.paths.iter().map(|p| p.poses.len()).sum(),
        registered: solution.registered,
        kept: solution.constraints.len(),
        joined: solution.joined.iter().filter(|&&j| j).count(),
        rigid_rmse_m: rmse(&input, &truth, rigid),
        joint_rmse_m: rmse(&input, &truth, optimised),
        edge_error_m: Spread::of_some(&edge_metres),
        edge_error_deg: Spread::of_some(&edge_degrees),
    }))
}

/// Per path, the world's `reference`-frame pose of each keyframe (`None` for a robot whose frame is
/// unknown).
fn truth(input: &JointInput, frames: &BTreeMap<u32, Isometry3<f64>>) -> Vec<Option<Vec<Isometry3<f64>>>> {
    let reference = frames.get(&input.robots[input.reference]);
    input
        .robots
        .iter()
        .zip(&input.paths)
        .map(|(robot, path)| {
            let into_reference = reference?.inverse() * frames.get(robot)?;
            Some(path.poses.iter().map(|p| into_reference * p).collect())
        })
        .collect()
}

/// Per kept edge, how far its measurement lies from the truth, metres and degrees.
fn edge_errors(constraints: &[Constraint], truth: &[Option<Vec<Isometry3<f64>>>]) -> (Vec<f64>, Vec<f64>) {
    constraints
        .iter()
        .filter_map(|c| {
            let at = |k: &KeyframeRef| truth[k.robot].as_ref().map(|t| t[k.keyframe]);
            let relative = at(&c.target)?.inverse() * at(&c.source)?;
            let e = pose_error(&c.measurement, &relative);
            tracing::debug!(
                "edge {}:{} -> {}:{} {:.1} m apart, overlap {:.2}: {:.3} m / {:.2} deg from the truth",
                c.target.robot,
                c.target.keyframe,
                c.source.robot,
                c.source.keyframe,
                relative.translation.vector.norm(),
                c.overlap,
                e.translation_m,
                e.rotation_deg
            );
            Some((e.translation_m, e.rotation_deg))
        })
        .unzip()
}

/// RMSE of the positions `pose(r, k)` against the truth over every robot but the reference
/// (unaligned ATE, [`ate`]).
fn rmse(
    input: &JointInput,
    truth: &[Option<Vec<Isometry3<f64>>>],
    pose: impl Fn(usize, usize) -> Isometry3<f64>,
) -> Option<f64> {
    let (truth, estimate): (Vec<Isometry3<f64>>, Vec<Isometry3<f64>>) = (0..input.paths.len())
        .filter(|&r| r != input.reference)
        .filter_map(|r| Some((r, truth[r].as_ref()?)))
        .flat_map(|(r, truth)| truth.iter().enumerate().map(move |(k, t)| (*t, (r, k))))
        .map(|(t, (r, k))| (t, pose(r, k)))
        .unzip();
    ate(&truth, &estimate, false).ok().map(|a| a.rmse)
}
