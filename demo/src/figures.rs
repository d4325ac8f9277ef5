//! The demo's figures: the global map seen from above with each merged robot's trajectories, and
//! each robot's position error over the distance it travelled.

use std::collections::BTreeMap;

use cloud::PointCloud;
use cloud::alignment::umeyama;
use cloud::kdtree::KdTree;
use edge::node::NodeSummary;
use nalgebra::{Isometry3, Point3};
use pictures::{ErrorCurve, ErrorPlotConfig, PictureError, RobotLayer, TopDown, TopDownConfig};
use rayon::prelude::*;

use crate::{GlobalFrame, RobotResult, moved, truth_in_own_frame};

/// A PNG and the file name it goes under.
pub(crate) struct Figure {
    pub file: &'static str,
    pub png: Vec<u8>,
}

/// `top_down.png` and `error_over_distance.png`.
pub(crate) fn figures(
    scenario: &str,
    summaries: &BTreeMap<u32, NodeSummary>,
    map: &PointCloud,
    robots: &[RobotResult],
) -> Result<Vec<Figure>, PictureError> {
    let tracks: Vec<Option<Tracks>> =
        robots.iter().map(|r| r.frame.map(|f| Tracks::placed(&summaries[&r.robot], &f))).collect();
    Ok(vec![
        Figure { file: "top_down.png", png: top_down(scenario, map, robots, &tracks)? },
        Figure { file: "error_over_distance.png", png: error_over_distance(scenario, summaries, robots, &tracks)? },
    ])
}

/// A robot's positions, estimated and true, in one frame.
struct Tracks {
    estimated: Vec<[f64; 3]>,
    truth: Vec<[f64; 3]>,
}

impl Tracks {
    /// In the global frame: where the station placed the (loop-corrected) estimate, and the
    /// truth where the simulator puts it; as `global_ate` compares them.
    fn placed(s: &NodeSummary, frame: &GlobalFrame) -> Self {
        Tracks {
            estimated: positions(&moved(&s.corrected_poses(), &frame.placed)),
            truth: positions(&moved(&truth_in_own_frame(s), &frame.truth)),
        }
    }

    /// In the robot's own frame, the estimate fitted onto the truth (SE(3), as the aligned ATE).
    fn aligned(s: &NodeSummary) -> Self {
        let truth = positions(&truth_in_own_frame(s));
        let estimated = positions(&s.corrected_poses());
        let points = |v: &[[f64; 3]]| v.iter().map(|p| Point3::from(*p)).collect::<Vec<_>>();
        let n = truth.len().min(estimated.len());
        // Too few or collinear poses leave the fit undetermined: compare as estimated then.
        let fit = umeyama(&points(&estimated[..n]), &points(&truth[..n])).unwrap_or_else(|_| Isometry3::identity());
        let estimated = estimated.iter().map(|p| (fit * Point3::from(*p)).coords.into()).collect();
        Tracks { estimated, truth }
    }
}

fn positions(poses: &[Isometry3<f64>]) -> Vec<[f64; 3]> {
    poses.iter().map(|p| p.translation.vector.into()).collect()
}

/// The global map from above, each point in the colour of the robot whose placed trajectory
/// passes nearest to it (the global map does not say which robot saw a point), with every
/// merged robot's estimated and true trajectory. Unmerged robots are listed in the legend, not
/// drawn: they have no place in the global frame.
fn top_down(
    scenario: &str,
    map: &PointCloud,
    robots: &[RobotResult],
    tracks: &[Option<Tracks>],
) -> Result<Vec<u8>, PictureError> {
    let owners = nearest_track(map, tracks);
    let mut layers: Vec<RobotLayer> = robots
        .iter()
        .zip(tracks)
        .map(|(r, t)| match t {
            Some(t) => RobotLayer {
                label: format!("robot {}", r.robot),
                points: Vec::new(),
                estimated: t.estimated.clone(),
                truth: t.truth.clone(),
            },
            None => RobotLayer { label: format!("robot {}: unmerged", r.robot), ..RobotLayer::default() },
        })
        .collect();
    for (p, owner) in map.points.iter().zip(owners) {
        if let Some(i) = owner {
            layers[i].points.push([p.x, p.y, p.z]);
        }
    }
    let title = format!("{scenario}: global map and trajectories (dashed: truth), top view");
    Ok(pictures::top_down(&TopDown { title, robots: layers }, &TopDownConfig::default())?.png)
}

/// Per map point, the robot whose trajectory passes nearest in x-y (None when none is placed).
fn nearest_track(map: &PointCloud, tracks: &[Option<Tracks>]) -> Vec<Option<usize>> {
    let mut owner = Vec::new();
    let mut xy = Vec::new();
    for (i, t) in tracks.iter().enumerate() {
        for p in t.iter().flat_map(|t| &t.estimated) {
            owner.push(i);
            xy.push([p[0] as f32, p[1] as f32, 0.0]);
        }
    }
    if xy.is_empty() {
        return vec![None; map.len()];
    }
    let tree = KdTree::new(&xy);
    map.points.par_iter().map(|p| tree.nearest(&[p.x, p.y, 0.0]).map(|n| owner[n.index])).collect()
}

/// Per robot, its position error over the distance it travelled: in the global frame when
/// merged, else in its own frame after fitting the estimate onto the truth.
fn error_over_distance(
    scenario: &str,
    summaries: &BTreeMap<u32, NodeSummary>,
    robots: &[RobotResult],
    tracks: &[Option<Tracks>],
) -> Result<Vec<u8>, PictureError> {
    let curves: Vec<ErrorCurve> = robots
        .iter()
        .zip(tracks)
        .map(|(r, t)| match t {
            Some(t) => ErrorCurve::from_positions(format!("robot {}, global frame", r.robot), &t.truth, &t.estimated),
            None => {
                let t = Tracks::aligned(&summaries[&r.robot]);
                ErrorCurve::from_positions(format!("robot {}, unmerged: aligned", r.robot), &t.truth, &t.estimated)
            }
        })
        .collect();
    let title = format!("{scenario}: position error against the truth");
    Ok(pictures::error_over_distance(&title, &curves, &ErrorPlotConfig::default())?.png)
}
