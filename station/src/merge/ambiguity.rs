//! Perceptual aliasing: is there a second, different transform that the features and the geometry
//! support almost as well as the chosen one?
//!
//! Repetitive places (identical rack rows, identical corridors) make the overlap and the inlier
//! ratio of a *wrong* transform look as good as those of a right one: two sealed halls of the same
//! racks align "perfectly" one row off. What gives them away is that the evidence is not unique:
//! the features support several distinct transforms. After the chosen model, RANSAC runs again on
//! the correspondences that disagree with it; the best such model, if it lies far from the chosen
//! one, is polished like the chosen one and compared with it twice:
//!
//! - by its RANSAC inliers (what the descriptors say);
//! - by its **upright support**, the share of source surfels on upright surfaces that land on a
//!   parallel target surface (what the geometry says). Floors and ceilings are left out: they
//!   coincide under any turn about the vertical and any horizontal shift of two ground-robot maps,
//!   so they cannot tell two hypotheses apart.
//!
//! The pair is ambiguous when the alternative is strong on *both* counts: the smaller of the two
//! shares exceeds the threshold. Measured on the simulated indoor pairs (inliers / upright support
//! of the alternative over the chosen transform's): the identical halls of `aisles` 0.77 / 0.70,
//! a chance alignment of `warehouse-small` 0.55 / 0.15 (a few matches between rack corners agree
//! by chance, the walls do not), a half-turn of `warehouse-large` 0.05 / 0.70 (the hall is nearly
//! symmetric, the descriptors are not fooled).

use cloud::global::{Features, Surfels, matching, polish, ransac};
use cloud::kdtree::gate_radius;
use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

use crate::pairwise::{EXCLUSION, PairwiseConfig};

/// The strongest hypothesis distinct from the chosen one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RunnerUp {
    /// Maps source points into the target frame (polished).
    pub transform: Isometry3<f64>,
    /// Its RANSAC inliers.
    pub inliers: usize,
    /// Its [`upright_support`] at the polished transform.
    pub upright_support: f64,
}

/// A surfel is upright when the vertical component of its unit normal is below this (the normal
/// is within 60° of horizontal: walls, rack faces, pillars; ground-robot maps are levelled to a
/// few degrees, even on rolling ground).
const UPRIGHT: f32 = 0.5;

/// Two surfels lie on parallel surfaces when their unit normals' dot product exceeds this in
/// magnitude (37°: normals of the same wall fitted in two maps differ by a few degrees).
const PARALLEL: f32 = 0.8;

/// The best RANSAC model on the correspondences that disagree with `chosen` and with every
/// transform of `refuted` (placements the free space showed wrong: no alternative), if one exists
/// and lies at least `min_distance` metres from `chosen` (at the source keypoints).
pub fn runner_up(
    source: &Features,
    target: &Features,
    (chosen, refuted): (&Isometry3<f64>, &[Isometry3<f64>]),
    min_distance: f64,
    config: &PairwiseConfig,
) -> Option<RunnerUp> {
    let matches = matching::reciprocal_matches(&source.descriptors, &target.descriptors, config.global.matching.k);
    let limit = EXCLUSION * config.global.ransac.inlier_distance;
    let disagrees =
        |s: &Point3<f64>, t: &Point3<f64>| std::iter::once(chosen).chain(refuted).all(|e| (e * s - t).norm() > limit);
    let (src, tgt): (Vec<Point3<f64>>, Vec<Point3<f64>>) = matches
        .iter()
        .map(|c| (source.keypoint(c.source).cast::<f64>(), target.keypoint(c.target).cast::<f64>()))
        .filter(|(s, t)| disagrees(s, t))
        .unzip();
    let model = ransac::ransac(&src, &tgt, &config.global.ransac)?;
    let keypoints = source.keypoint_positions();
    if mean_displacement(&keypoints, chosen, &model.transform) < min_distance {
        return None;
    }
    // Polished like the chosen transform, so that both are judged at their best.
    let transform = polish::polish(&source.surfels, &target.surfels, &model.transform, &config.global.polish);
    let upright_support =
        upright_support(&source.surfels, &target.surfels, &transform, config.confidence.overlap_distance);
    Some(RunnerUp { transform, inliers: model.inliers.len(), upright_support })
}

/// Share of the source's upright surfels (with a normal) that `transform` puts within `distance`
/// of a target surfel on a parallel surface; 0 when the source has no upright surfel.
pub fn upright_support(source: &Surfels, target: &Surfels, transform: &Isometry3<f64>, distance: f32) -> f64 {
    let t = transform.cast::<f32>();
    let (upright, supported) = (0..source.len())
        .into_par_iter()
        .filter(|&i| source.has_normal(i))
        .map(|i| (t * source.points[i], t.rotation * source.normals[i]))
        .filter(|(_, n)| n.z.abs() < UPRIGHT)
        .map(|(p, n)| {
            let on_target = target.tree.nearest_within(&[p.x, p.y, p.z], gate_radius(distance)).is_some_and(|nn| {
                nn.dist_sq <= distance * distance && n.dot(&target.normals[nn.index]).abs() > PARALLEL
            });
            (1usize, usize::from(on_target))
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    if upright == 0 { 0.0 } else { supported as f64 / upright as f64 }
}

/// Mean distance between where two transforms put the same points: how different they are on the
/// map itself (a rotation about a far-away origin is not "small").
pub fn mean_displacement(points: &[Point3<f32>], a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let sum: f64 = points.iter().map(|p| (a * p.cast::<f64>() - b * p.cast::<f64>()).norm()).sum();
    sum / points.len() as f64
}
