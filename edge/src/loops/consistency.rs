//! Whether verified loops agree with the odometry and with each other, before any enters the pose
//! graph (pairwise consistency maximisation, Mangelson et al., ICRA 2018, with a drift-bounded
//! test instead of a chi-squared one).
//!
//! A loop `Z` says where keyframe `b` is in keyframe `a`'s frame. Two checks:
//! - against the odometry: `Z⁻¹ · O(a, b)` must be near the identity, within what the odometry can
//!   have drifted over the path between them (eq. 1). It rejects a match with an identical-looking
//!   place several metres off, which is the aisles' trap;
//! - against another loop `Z'` from `a'` to `b'`: going round `a → a' → b' → b → a` along odometry,
//!   `Z'`, odometry and `Z⁻¹` must close (eq. 2), within the drift over the two short odometry legs.
//!   Loops into the same revisit close tightly; a false loop closes with none of the true ones.
//!
//! The loops that enter the graph are the largest set in which every pair agrees (a clique of the
//! consistency graph, found greedily), once it has at least `min_clique` members.

use cloud::se3::pose_error;
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

/// Bounds of the consistency tests.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ConsistencyConfig {
    /// Translation disagreement allowed without travel (m): registration error. Default 0.3 m.
    pub translation_m: f64,
    /// Translation disagreement allowed per metre travelled between the poses compared, added to
    /// `translation_m`. Default 0.02 (2 %, twice what the odometry drifts on KITTI).
    pub drift: f64,
    /// Rotation disagreement allowed without travel (deg). Default 2°.
    pub rotation_deg: f64,
    /// Rotation disagreement allowed per metre travelled (deg/m), added to `rotation_deg`.
    /// Default 0.02 °/m (2° per 100 m).
    pub rotation_drift_deg_per_m: f64,
    /// Loops enter the graph only in a consistent set at least this large. Default 1: the odometry
    /// test is the other member of every set (PCM's odometry consistency); on the simulated
    /// warehouses and aisles true loops use under 5 % of its allowance and false ones over 400 %,
    /// and a robot that revisits its start once at the end of its run has one loop to give.
    pub min_clique: usize,
}

impl Default for ConsistencyConfig {
    fn default() -> Self {
        ConsistencyConfig {
            translation_m: 0.3,
            drift: 0.02,
            rotation_deg: 2.0,
            rotation_drift_deg_per_m: 0.02,
            min_clique: 1,
        }
    }
}

impl ConsistencyConfig {
    /// Whether a disagreement `error` is within what `path_m` metres of odometry explain.
    pub fn explains(&self, error: &Isometry3<f64>, path_m: f64) -> bool {
        self.margin(error, path_m) <= 1.0
    }

    /// The translation disagreement allowed over `path_m` metres of odometry (m).
    pub fn translation_allowance_m(&self, path_m: f64) -> f64 {
        self.translation_m + self.drift * path_m
    }

    /// How much of the allowance `error` uses: its translation over the translation bound or its
    /// rotation over the rotation bound, whichever is larger (at most 1 when explained).
    pub fn margin(&self, error: &Isometry3<f64>, path_m: f64) -> f64 {
        let e = pose_error(error, &Isometry3::identity());
        let translation = e.translation_m / self.translation_allowance_m(path_m);
        let rotation = e.rotation_deg / (self.rotation_deg + self.rotation_drift_deg_per_m * path_m);
        translation.max(rotation)
    }
}

/// A verified loop as the tests see it: the keyframes' odometry poses and path positions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoopView {
    /// Odometry pose of the older keyframe `a`.
    pub odom_a: Isometry3<f64>,
    /// Odometry pose of the newer keyframe `b`.
    pub odom_b: Isometry3<f64>,
    /// Odometry path length at `a` and at `b` (m).
    pub path_a: f64,
    pub path_b: f64,
    /// The loop: pose of `b` in `a`'s frame.
    pub transform: Isometry3<f64>,
}

/// Eq. (1): `Z⁻¹ · a⁻¹ b`, the loop against the odometry, over the path from `a` to `b`: the share of
/// the allowance it uses (agreement when at most 1).
pub fn odometry_margin(l: &LoopView, config: &ConsistencyConfig) -> f64 {
    let odometry = l.odom_a.inverse() * l.odom_b;
    config.margin(&(l.transform.inverse() * odometry), (l.path_b - l.path_a).abs())
}

/// Eq. (1) before any fit: whether a loop from `a` to `b` that starts at `initial` and moves at most
/// `reach_m` can agree with the odometry. The loop's translation `t` is then within `reach_m` of
/// `initial`'s, and eq. (1)'s translation error is `|t_O - t| >= |t_O - t_initial| - reach_m`
/// (`t_O` the odometry's): when that exceeds the allowance no fit within reach passes, whatever it
/// finds.
pub fn reachable(
    odom_a: &Isometry3<f64>,
    odom_b: &Isometry3<f64>,
    path_m: f64,
    initial: &Isometry3<f64>,
    reach_m: f64,
    config: &ConsistencyConfig,
) -> bool {
    let odometry = odom_a.inverse() * odom_b;
    let gap = (odometry.translation.vector - initial.translation.vector).norm();
    gap - reach_m <= config.translation_allowance_m(path_m)
}

/// Eq. (2): `Z₁⁻¹ · (a₁⁻¹ a₂) · Z₂ · (b₂⁻¹ b₁)`, the cycle through two loops, over the odometry legs
/// `a₁ → a₂` and `b₂ → b₁`.
pub fn agree(l1: &LoopView, l2: &LoopView, config: &ConsistencyConfig) -> bool {
    let cycle =
        l1.transform.inverse() * (l1.odom_a.inverse() * l2.odom_a) * l2.transform * (l2.odom_b.inverse() * l1.odom_b);
    let legs = (l1.path_a - l2.path_a).abs() + (l1.path_b - l2.path_b).abs();
    config.explains(&cycle, legs)
}

/// The largest set of loops that pairwise agree (greedy: by number of agreeing loops, most first,
/// each kept if it agrees with all kept so far; ties by index, so the result is deterministic);
/// empty when smaller than `min_clique`. Indices into `loops`, ascending.
pub fn largest_consistent_set(loops: &[LoopView], config: &ConsistencyConfig) -> Vec<usize> {
    let n = loops.len();
    let mut adjacent = vec![vec![false; n]; n];
    for i in 0..n {
        for j in i + 1..n {
            let a = agree(&loops[i], &loops[j], config);
            adjacent[i][j] = a;
            adjacent[j][i] = a;
        }
    }
    let degree: Vec<usize> = adjacent.iter().map(|row| row.iter().filter(|&&a| a).count()).collect();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by_key(|&i| (std::cmp::Reverse(degree[i]), i));
    let mut clique: Vec<usize> = Vec::new();
    for i in order {
        if clique.iter().all(|&j| adjacent[i][j]) {
            clique.push(i);
        }
    }
    if clique.len() < config.min_clique.max(1) {
        return Vec::new();
    }
    clique.sort_unstable();
    clique
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    /// A robot driving along x at 1 m per keyframe: keyframe `k` at (k, 0, 0), path k metres.
    fn odom(k: usize, drift_per_m: f64) -> (Isometry3<f64>, f64) {
        let x = k as f64;
        (Isometry3::translation(x, drift_per_m * x, 0.0), x)
    }

    /// A loop between keyframes `a` and `b` of a straight drive where the true relative pose is the
    /// true positions' difference; `offset` makes it wrong.
    fn view(a: usize, b: usize, drift_per_m: f64, offset: Vector3<f64>) -> LoopView {
        let ((odom_a, path_a), (odom_b, path_b)) = (odom(a, drift_per_m), odom(b, drift_per_m));
        let truth = Isometry3::translation((b - a) as f64, 0.0, 0.0);
        LoopView {
            odom_a,
            odom_b,
            path_a,
            path_b,
            transform: Isometry3::translation(offset.x, offset.y, offset.z) * truth,
        }
    }

    #[test]
    fn a_loop_within_the_drift_agrees_one_beyond_it_does_not() {
        let config = ConsistencyConfig::default();
        // 1 % drift over 100 m: 1 m off, within 0.3 + 2 m.
        assert!(odometry_margin(&view(0, 100, 0.01, Vector3::zeros()), &config) <= 1.0);
        // An aisle 5.8 m over: beyond 2.3 m.
        assert!(odometry_margin(&view(0, 100, 0.01, Vector3::new(0.0, 5.8, 0.0)), &config) > 1.0);
    }

    /// Fits within `reach` of the start (translation zero, rotation `rotation`): the start, and
    /// points at `reach / 2` and `reach` along the 26 directions to a cube's faces, edges and corners.
    fn fits_within(reach: f64, rotation: UnitQuaternion<f64>) -> Vec<Isometry3<f64>> {
        let axis = [-1.0, 0.0, 1.0];
        let directions = axis
            .into_iter()
            .flat_map(|x| axis.into_iter().flat_map(move |y| axis.into_iter().map(move |z| Vector3::new(x, y, z))))
            .filter(|d| d.norm() > 0.0);
        let mut fits = vec![Isometry3::from_parts(Default::default(), rotation)];
        for d in directions {
            for r in [reach / 2.0, reach] {
                fits.push(Isometry3::from_parts((d.normalize() * r).into(), rotation));
            }
        }
        fits
    }

    #[test]
    fn a_candidate_out_of_reach_could_pass_the_odometry_test_with_no_fit_within_reach() {
        let config = ConsistencyConfig::default();
        let (reach, path) = (4.0, 100.0);
        // The descriptor's yaw, which the odometry agrees with: only translation decides.
        let turn = UnitQuaternion::from_scaled_axis(Vector3::z() * 0.3);
        let initial = Isometry3::from_parts(Default::default(), turn);
        // Keyframes 100 m of path apart that the odometry puts `gap` metres apart sideways (a
        // place seen again from the next aisle). The allowance over 100 m is 2.3 m.
        for gap in [0.0, 2.0, 4.0, 6.2, 6.4, 8.0, 19.0] {
            let odom_a = Isometry3::identity();
            let odom_b = Isometry3::from_parts(Vector3::new(0.0, gap, 0.0).into(), turn);
            let reachable = reachable(&odom_a, &odom_b, path, &initial, reach, &config);
            assert_eq!(reachable, gap <= reach + 2.3, "gap {gap}");
            let margin = |transform| {
                odometry_margin(&LoopView { odom_a, odom_b, path_a: 0.0, path_b: path, transform }, &config)
            };
            let margins: Vec<f64> = fits_within(reach, turn).into_iter().map(margin).collect();
            // Unreachable: eq. (1) refuses every fit within reach, so deciding before the fit is
            // deciding as after it. Reachable: the fit that went towards the odometry's pose passes.
            let towards = Isometry3::from_parts(Vector3::new(0.0, gap.min(reach), 0.0).into(), turn);
            if reachable {
                assert!(margin(towards) <= 1.0, "gap {gap}: {}", margin(towards));
            } else {
                assert!(margins.iter().all(|&m| m > 1.0), "gap {gap}: {margins:?}");
            }
        }
    }

    #[test]
    fn a_false_loop_is_left_out_of_the_consistent_set() {
        let config = ConsistencyConfig::default();
        let mut loops: Vec<LoopView> = (0..5).map(|i| view(i, 200 + i, 0.01, Vector3::zeros())).collect();
        // A loop to the next aisle: agrees with nothing (the legs are a few metres).
        loops.push(view(10, 150, 0.01, Vector3::new(0.0, 5.8, 0.0)));
        assert_eq!(largest_consistent_set(&loops, &config), vec![0, 1, 2, 3, 4]);
        // One loop alone is enough by default, not when two are asked for.
        assert_eq!(largest_consistent_set(&loops[..1], &config), vec![0]);
        let two = ConsistencyConfig { min_clique: 2, ..config.clone() };
        assert!(largest_consistent_set(&loops[..1], &two).is_empty());
        assert!(largest_consistent_set(&[], &config).is_empty());
    }
}
