//! Inter-robot edges: where two merged robots passed the same place, one's keyframe registered
//! onto the other's submap.
//!
//! For each keyframe `k` of robot `b` (those at least [`JointConfig::spacing`] apart along its
//! path) and each robot `a < b`, the keyframe `j` of `a` nearest to it in the global frame (by (1)
//! of [`super`]) within [`JointConfig::reach`] is the target: the keyframes `i` of `a` within
//! [`JointConfig::window`] of `j` along its path in the frame of `j`,
//!
//! ```text
//! Sⱼ = ∪ᵢ Pₐⱼ⁻¹ Pₐᵢ · cloudₐᵢ                                                        (2)
//! ```
//!
//! and VGICP registers `k`'s cloud onto it from `Xₐⱼ⁻¹ Xᵦₖ`. The result `T` is kept as the edge
//! `Z = T` from `(a, j)` to `(b, k)` when VGICP converged, at least [`JointConfig::min_overlap`]
//! of the keyframe's points found a correspondence, and `T` lies within
//! [`JointConfig::max_translation`] / [`JointConfig::max_rotation_deg`] of its start. Each unordered
//! pair of robots is searched once: an edge holds the same information either way round. Each
//! target's submap is built once for every keyframe registered onto it (a robot that stopped is
//! the nearest to everyone passing by).

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
    let mut candidates: Vec<(KeyframeRef, KeyframeRef)> = paths
        .iter()
        .enumerate()
        .flat_map(|(b, path)| {
            let positions = &positions;
            spread(path.poses.iter(), config.spacing, f64::INFINITY).into_iter().flat_map(move |k| {
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
    // Each target's submap once, for every keyframe registered onto it.
    candidates.sort_by_key(|(t, s)| (t.robot, t.keyframe, s.robot, s.keyframe));
    let by_target: Vec<&[(KeyframeRef, KeyframeRef)]> = candidates.chunk_by(|x, y| x.0 == y.0).collect();
    by_target
        .par_iter()
        .flat_map_iter(|group| {
            let target = group[0].0;
            let submap = submap(&paths[target.robot], target.keyframe, config);
            group.iter().filter_map(move |&(target, source)| {
                let cloud = &paths[source.robot].clouds[source.keyframe];
                let keyframe = gaussians(std::slice::from_ref(cloud), &[Isometry3::identity()], config)?;
                register(paths, &keyframe, submap.as_ref()?, target, source, config)
            })
        })
        .collect()
}

/// The submap (2) of keyframe `j` of robot `a`: the keyframes within [`JointConfig::window`] of it
/// along the path, at least [`JointConfig::spacing`] apart, in the frame of `j`.
fn submap(a: &RobotPath, j: usize, config: &JointConfig) -> Option<GaussianCloud> {
    let before = spread(a.poses[..=j].iter().rev(), config.spacing, config.window).into_iter().map(|i| j - i);
    let after = spread(a.poses[j..].iter(), config.spacing, config.window).into_iter().skip(1).map(|i| j + i);
    let window: Vec<usize> = before.rev().chain(after).collect();
    let into_j: Vec<Isometry3<f64>> = window.iter().map(|&i| a.poses[j].inverse() * a.poses[i]).collect();
    let clouds: Vec<Arc<PointCloud>> = window.iter().map(|&i| Arc::clone(&a.clouds[i])).collect();
    gaussians(&clouds, &into_j, config)
}

/// Steps along `poses` of the keyframes at least `spacing` apart along the path, the first
/// included, up to `length` of path from the first.
fn spread<'a>(poses: impl Iterator<Item = &'a Isometry3<f64>>, spacing: f64, length: f64) -> Vec<usize> {
    let (mut kept, mut path, mut since) = (vec![], 0.0, 0.0);
    let mut previous: Option<&Isometry3<f64>> = None;
    for (i, pose) in poses.enumerate() {
        if let Some(p) = previous {
            let step = (pose.translation.vector - p.translation.vector).norm();
            path += step;
            since += step;
            if path > length {
                break;
            }
        }
        if previous.is_none() || since >= spacing {
            kept.push(i);
            since = 0.0;
        }
        previous = Some(pose);
    }
    kept
}

/// The edge from `target`'s submap (2) to `source`, if it passes the checks.
fn register(
    paths: &[RobotPath],
    keyframe: &GaussianCloud,
    submap: &GaussianCloud,
    target: KeyframeRef,
    source: KeyframeRef,
    config: &JointConfig,
) -> Option<Constraint> {
    let start = paths[target.robot].placed(target.keyframe).inverse() * paths[source.robot].placed(source.keyframe);
    let result = align_gaussians(keyframe, submap, &start, JointConfig::METHOD, &config.registration).ok()?;
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
