//! Which inter-robot edges agree with each other: pairwise consistency maximisation (PCM,
//! Mangelson et al., ICRA 2018).
//!
//! A registration that slid along a corridor or locked onto the next rack converges as firmly as
//! a true one, and a robust kernel only softens the pull of a wrong edge. Two edges between the
//! same two robots, `(a, j₁) → (b, k₁)` with `Z₁` and `(a, j₂) → (b, k₂)` with `Z₂`, each tell where
//! `(b, k₂)` lies in the frame of `(a, j₁)`, through the other robot's own odometry:
//!
//! ```text
//! Z₁ · Pᵦₖ₁⁻¹ Pᵦₖ₂   and   Pₐⱼ₁⁻¹ Pₐⱼ₂ · Z₂                                            (3)
//! ```
//!
//! They are consistent when the two differ by at most [`JointConfig::consistency_sigmas`]
//! deviations of that difference (two edges' and the two odometry stretches'), in translation and
//! in rotation. Per pair of robots the largest set of mutually consistent edges is kept (a clique
//! of the consistency graph, found greedily from each edge), if it holds at least
//! [`JointConfig::min_consistent`] edges: a single edge could be wrong with nothing to tell.

use cloud::se3::pose_error;
use nalgebra::Isometry3;

use super::{Constraint, JointConfig, RobotPath};

/// The edges of `constraints` kept: per pair of robots, the largest mutually consistent set.
pub fn consistent(paths: &[RobotPath], constraints: &[Constraint], config: &JointConfig) -> Vec<Constraint> {
    let mut pairs: Vec<(usize, usize)> = constraints.iter().map(|c| (c.target.robot, c.source.robot)).collect();
    pairs.sort_unstable();
    pairs.dedup();
    let mut kept = Vec::new();
    for pair in pairs {
        let group: Vec<&Constraint> = constraints.iter().filter(|c| (c.target.robot, c.source.robot) == pair).collect();
        let agree = |x: usize, y: usize| agree(paths, group[x], group[y], config);
        let clique = largest_clique(group.len(), agree);
        if clique.len() >= config.min_consistent {
            kept.extend(clique.into_iter().map(|i| group[i].clone()));
        }
    }
    kept
}

/// Whether two edges between the same robots agree by (3).
fn agree(paths: &[RobotPath], c1: &Constraint, c2: &Constraint, config: &JointConfig) -> bool {
    let (a, b) = (&paths[c1.target.robot], &paths[c1.source.robot]);
    let odometry_b = b.poses[c1.source.keyframe].inverse() * b.poses[c2.source.keyframe];
    let odometry_a = a.poses[c1.target.keyframe].inverse() * a.poses[c2.target.keyframe];
    let through_1 = c1.measurement * odometry_b;
    let through_2 = odometry_a * c2.measurement;
    let difference = pose_error(&through_1, &through_2);
    let (sigma_m, sigma_deg) = deviation(&odometry_a, &odometry_b, config);
    difference.translation_m <= config.consistency_sigmas * sigma_m
        && difference.rotation_deg <= config.consistency_sigmas * sigma_deg
}

/// Deviation of the difference (3): two edges' ([`JointConfig::consistency_sigma_m`]) and two
/// odometry stretches', independent.
fn deviation(odometry_a: &Isometry3<f64>, odometry_b: &Isometry3<f64>, config: &JointConfig) -> (f64, f64) {
    let ((ta, ra), (tb, rb)) = (config.odometry.sigmas(odometry_a), config.odometry.sigmas(odometry_b));
    let sigma_m = (2.0 * config.consistency_sigma_m.powi(2) + ta * ta + tb * tb).sqrt();
    let sigma_deg = (2.0 * config.consistency_sigma_deg.powi(2) + ra * ra + rb * rb).sqrt();
    (sigma_m, sigma_deg)
}

/// A largest set of vertices of `0..n` that all `agree` pairwise, found greedily: from each vertex,
/// add its consistent neighbours, most connected first, while they agree with all taken so far.
/// Exact maximum cliques are exponential; PCM's own heuristic is this one.
fn largest_clique(n: usize, agree: impl Fn(usize, usize) -> bool) -> Vec<usize> {
    let adjacent: Vec<Vec<bool>> = (0..n).map(|x| (0..n).map(|y| x != y && agree(x, y)).collect()).collect();
    let degree: Vec<usize> = adjacent.iter().map(|row| row.iter().filter(|&&a| a).count()).collect();
    let mut best: Vec<usize> = Vec::new();
    for seed in 0..n {
        if degree[seed] < best.len() {
            continue;
        }
        let mut candidates: Vec<usize> = (0..n).filter(|&y| adjacent[seed][y]).collect();
        candidates.sort_by_key(|&y| std::cmp::Reverse(degree[y]));
        let mut clique = vec![seed];
        for y in candidates {
            if clique.iter().all(|&x| adjacent[x][y]) {
                clique.push(y);
            }
        }
        if clique.len() > best.len() {
            best = clique;
        }
    }
    best.sort_unstable();
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_largest_clique_is_found_past_a_smaller_one() {
        // 0-3 agree with each other, 4-5 with each other and with 0 only.
        let group = |x: usize| if x < 4 { 0 } else { 1 };
        let agree = |x: usize, y: usize| group(x) == group(y) || (x.min(y) == 0 && x.max(y) >= 4);
        assert_eq!(largest_clique(6, agree), vec![0, 1, 2, 3]);
        assert_eq!(largest_clique(1, |_, _| false), vec![0]);
        assert!(largest_clique(0, |_, _| true).is_empty());
    }
}
