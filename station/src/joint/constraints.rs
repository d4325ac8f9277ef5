//! Inter-robot edges: where two merged robots passed the same place, one's keyframe registered
//! onto the other's submap.
//!
//! For each keyframe `k` of robot `b` (every [`JointConfig::stride`]-th) and each robot `a < b`,
//! the keyframe `j` of `a` nearest to it in the global frame (by (1) of [`super`]) within
//! [`JointConfig::reach`] is the target: keyframes `j - w ..= j + w` of `a`
//! ([`JointConfig::window`]) in the frame of `j`,
//!
//! ```text
//! Sⱼ = ∪ᵢ Pₐⱼ⁻¹ Pₐᵢ · cloudₐᵢ                                                        (2)
//! ```
//!
//! and VGICP registers `k`'s cloud onto it from `Xₐⱼ⁻¹ Xᵦₖ`. The result `T` is kept as the edge
//! `Z = T` from `(a, j)` to `(b, k)` when VGICP converged, at least [`JointConfig::min_overlap`]
//! of the keyframe's points found a correspondence, and `T` lies within
//! [`JointConfig::max_translation`] / [`JointConfig::max_rotation_deg`] of its start. Each unordered
//! pair of robots is searched once: an edge holds the same information either way round.

use std::sync::Arc;

use cloud::PointCloud;
use cloud::kdtree::{KdTree, gate_radius};
use cloud::registration::{GaussianCloud, MIN_POINTS, align_gaussians};
use cloud::se3::pose_error;
use cloud::voxel::downsample;
use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

use super::{JointConfig, RobotPath};

/// One keyframe of one robot (indices into the input).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct KeyframeRef {
    /// The robot's index.
    pub robot: usize,
    /// The keyframe's index in the robot's path.
    pub keyframe: usize,
}

/// An inter-robot edge.
#[derive(Clone, Debug, PartialEq)]
pub struct Constraint {
    /// The keyframe whose submap was the target (`(a, j)`).
    pub target: KeyframeRef,
    /// The keyframe registered onto it (`(b, k)`).
    pub source: KeyframeRef,
    /// `Z`: the registered pose of the source keyframe in the frame of the target keyframe.
    pub measurement: Isometry3<f64>,
    /// Share of the source's points with a correspondence.
    pub overlap: f64,
}

/// Every inter-robot edge of `paths`, registered in parallel.
pub fn find(paths: &[RobotPath], config: &JointConfig) -> Vec<Constraint> {
    let positions: Vec<KdTree> = paths
        .iter()
        .map(|p| {
            let at: Vec<Point3<f32>> =
                (0..p.poses.len()).map(|k| Point3::from(p.placed(k).translation.vector.cast::<f32>())).collect();
            KdTree::from_points(&at)
        })
        .collect();
    let candidates: Vec<(KeyframeRef, KeyframeRef)> = paths
        .iter()
        .enumerate()
        .flat_map(|(b, path)| {
            let positions = &positions;
            (0..path.poses.len()).step_by(config.stride).flat_map(move |k| {
                let at = path.placed(k).translation.vector.cast::<f32>();
                (0..b).filter_map(move |a| {
                    let near = positions[a].nearest_within(&[at.x, at.y, at.z], gate_radius(config.reach as f32))?;
                    (near.dist_sq <= (config.reach * config.reach) as f32).then_some((
                        KeyframeRef { robot: a, keyframe: near.index },
                        KeyframeRef { robot: b, keyframe: k },
                    ))
                })
            })
        })
        .collect();
    // Each source keyframe's Gaussians once, for every robot it is tried against.
    let mut by_source: Vec<(KeyframeRef, Vec<KeyframeRef>)> = Vec::new();
    for (target, source) in candidates {
        match by_source.last_mut() {
            Some((s, targets)) if *s == source => targets.push(target),
            _ => by_source.push((source, vec![target])),
        }
    }
    by_source
        .par_iter()
        .flat_map_iter(|(source, targets)| {
            let cloud = &paths[source.robot].clouds[source.keyframe];
            let keyframe = gaussians(std::slice::from_ref(cloud), &[Isometry3::identity()], config);
            targets.iter().filter_map(move |&target| register(paths, keyframe.as_ref()?, target, *source, config))
        })
        .collect()
}

/// The edge from `target`'s submap (2) to `source`, if it passes the checks.
fn register(
    paths: &[RobotPath],
    keyframe: &GaussianCloud,
    target: KeyframeRef,
    source: KeyframeRef,
    config: &JointConfig,
) -> Option<Constraint> {
    let a = &paths[target.robot];
    let j = target.keyframe;
    let window = j.saturating_sub(config.window)..=(j + config.window).min(a.poses.len() - 1);
    let into_j: Vec<Isometry3<f64>> = window.clone().map(|i| a.poses[j].inverse() * a.poses[i]).collect();
    let submap = gaussians(&a.clouds[window], &into_j, config)?;
    let start = a.placed(j).inverse() * paths[source.robot].placed(source.keyframe);
    let result = align_gaussians(keyframe, &submap, &start, JointConfig::METHOD, &config.registration).ok()?;
    let moved = pose_error(&result.transform, &start);
    let overlap = result.inliers as f64 / keyframe.len() as f64;
    let kept = result.converged
        && overlap >= config.min_overlap
        && moved.translation_m <= config.max_translation
        && moved.rotation_deg <= config.max_rotation_deg;
    kept.then_some(Constraint { target, source, measurement: result.transform, overlap })
}

/// The clouds moved by their poses, downsampled to [`JointConfig::voxel`], with covariances;
/// `None` when too few points remain to register.
fn gaussians(clouds: &[Arc<PointCloud>], poses: &[Isometry3<f64>], config: &JointConfig) -> Option<GaussianCloud> {
    let mut union = PointCloud::default();
    for (cloud, pose) in clouds.iter().zip(poses) {
        let pose = pose.cast::<f32>();
        union.points.extend(cloud.points.iter().filter(|p| p.coords.iter().all(|c| c.is_finite())).map(|p| pose * p));
    }
    let down = downsample(&union, config.voxel).ok()?;
    (down.len() >= MIN_POINTS.max(config.registration.neighbours))
        .then(|| GaussianCloud::new(&down.points, config.registration.neighbours))
}
