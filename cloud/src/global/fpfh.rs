//! Step 4 — Fast Point Feature Histograms (Rusu, Blodow & Beetz, ICRA 2009).
//!
//! For a pair of oriented points the Darboux frame `u = n_s`, `v = (p_t − p_s)/d × u`, `w = u × v`
//! gives three angles: `α = v·n_t`, `φ = u·(p_t − p_s)/d` and `θ = atan2(w·n_t, u·n_t)` (PCL's
//! `computePairFeatures`, which picks as source the point whose normal is closer to the joining
//! line, so that the pair is ordered the same way from either end). The Simplified PFH of a point,
//! SPFH(p), bins the three angles of `p` with each neighbour within the radius into 11 bins each
//! (33 in all, each sub-histogram summing to 100). The FPFH adds the neighbours' SPFHs weighted by
//! inverse distance:
//!
//! `FPFH(p) = SPFH(p) + 1/k Σ_k (1/ω_k) SPFH(p_k)`,
//!
//! with ω_k the distance between `p` and `p_k` (the paper's weight; PCL and Open3D use its square,
//! which on voxel-downsampled maps lets the one or two closest neighbours dominate) and the weighted
//! sum renormalised per sub-histogram to 100, as Open3D does. Descriptors are computed only at the keypoints, but over the
//! whole downsampled cloud: the SPFH of every point within the radius of a keypoint is needed.
//! Both passes run in parallel with rayon.

use nalgebra::{Point3, Vector3};
use rayon::prelude::*;

use super::error::FeatureError;
use super::normals::Surfels;

/// Bins per angle.
pub const BINS_PER_FEATURE: usize = 11;
/// Length of a descriptor: three angles × 11 bins.
pub const FPFH_LEN: usize = 3 * BINS_PER_FEATURE;
/// One FPFH descriptor.
pub type Fpfh = [f32; FPFH_LEN];

/// Settings of step 4.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FpfhConfig {
    /// Support radius, metres (default 2.0 = 5 × voxel, Open3D's tutorial ratio).
    pub radius: f32,
    /// At most this many nearest neighbours within the radius (default 100, as Open3D's tutorial).
    pub max_neighbours: usize,
    /// Keypoints with fewer neighbours (self excluded) get no descriptor (default 5).
    pub min_neighbours: usize,
}

impl Default for FpfhConfig {
    fn default() -> Self {
        Self { radius: 2.0, max_neighbours: 100, min_neighbours: 5 }
    }
}

impl FpfhConfig {
    /// Checks the radius and counts.
    pub fn validate(&self) -> Result<(), FeatureError> {
        if !(self.radius > 0.0 && self.radius.is_finite()) || self.max_neighbours < 2 {
            return Err(FeatureError::InvalidConfig("fpfh needs a positive radius and max_neighbours >= 2"));
        }
        Ok(())
    }
}

/// The angles `(θ, α, φ)` of an oriented point pair, or `None` when the frame is undefined.
pub fn pair_features(p1: &Point3<f32>, n1: &Vector3<f32>, p2: &Point3<f32>, n2: &Vector3<f32>) -> Option<[f32; 3]> {
    let dp = p2 - p1;
    let d = dp.norm();
    // A zero normal marks a point without one.
    if d <= f32::EPSILON || *n1 == Vector3::zeros() || *n2 == Vector3::zeros() {
        return None;
    }
    let (a1, a2) = (n1.dot(&dp) / d, n2.dot(&dp) / d);
    // The source is the point whose normal makes the smaller angle with the joining line.
    let (u, n_t, dp, phi) = if a1.abs() >= a2.abs() { (n1, n2, dp, a1) } else { (n2, n1, -dp, -a2) };
    let v = dp.cross(u);
    let v_norm = v.norm();
    if v_norm <= f32::EPSILON * d {
        return None;
    }
    let v = v / v_norm;
    let w = u.cross(&v);
    let alpha = v.dot(n_t);
    let theta = w.dot(n_t).atan2(u.dot(n_t));
    Some([theta, alpha, phi])
}

/// The bin of each angle: θ ∈ [−π, π], α and φ ∈ [−1, 1].
fn bins(f: &[f32; 3]) -> [usize; 3] {
    let bin = |x: f32| ((x * BINS_PER_FEATURE as f32).floor().max(0.0) as usize).min(BINS_PER_FEATURE - 1);
    [
        bin((f[0] + std::f32::consts::PI) / std::f32::consts::TAU),
        BINS_PER_FEATURE + bin((f[1] + 1.0) * 0.5),
        2 * BINS_PER_FEATURE + bin((f[2] + 1.0) * 0.5),
    ]
}

/// SPFH of surfel `i` over `neighbours` (indices, `i` itself skipped): each sub-histogram sums to 100.
pub fn spfh(surfels: &Surfels, i: usize, neighbours: &[usize]) -> Fpfh {
    let mut h = [0.0f32; FPFH_LEN];
    let others = neighbours.iter().filter(|&&j| j != i && surfels.has_normal(j)).count();
    if others == 0 {
        return h;
    }
    let incr = 100.0 / others as f32;
    let (p, n) = (&surfels.points[i], &surfels.normals[i]);
    for &j in neighbours.iter().filter(|&&j| j != i) {
        if let Some(f) = pair_features(p, n, &surfels.points[j], &surfels.normals[j]) {
            for b in bins(&f) {
                h[b] += incr;
            }
        }
    }
    h
}

/// Step 4: the FPFH of each keypoint, or `None` for keypoints with too few neighbours.
pub fn fpfh_at(surfels: &Surfels, keypoints: &[usize], config: &FpfhConfig) -> Vec<Option<Fpfh>> {
    let neighbourhood = |i: usize| -> Vec<usize> {
        surfels.neighbours(i, config.radius, config.max_neighbours).iter().map(|q| q.index()).collect()
    };
    let keypoint_nn: Vec<Vec<usize>> = keypoints.par_iter().map(|&i| neighbourhood(i)).collect();
    // Only neighbours with a normal count towards the minimum.
    let described = |i: usize, nn: &[usize]| {
        surfels.has_normal(i)
            && nn.iter().filter(|&&j| j != i && surfels.has_normal(j)).count() >= config.min_neighbours
    };
    // The SPFH is needed at the keypoints and at every neighbour of one.
    let mut needed = vec![false; surfels.len()];
    for &j in keypoint_nn.iter().flatten().chain(keypoints) {
        needed[j] = true;
    }
    let needed: Vec<usize> = (0..surfels.len()).filter(|&j| needed[j]).collect();
    let mut slot = vec![usize::MAX; surfels.len()];
    for (s, &j) in needed.iter().enumerate() {
        slot[j] = s;
    }
    let spfhs: Vec<Fpfh> = needed.par_iter().map(|&j| spfh(surfels, j, &neighbourhood(j))).collect();
    keypoints
        .par_iter()
        .zip(&keypoint_nn)
        .map(|(&i, nn)| described(i, nn).then(|| weighted_sum(surfels, i, nn, |j| &spfhs[slot[j]])))
        .collect()
}

/// `SPFH(p) + renormalised Σ SPFH(p_k) / |p − p_k|` over the neighbours of surfel `i`.
fn weighted_sum<'a>(surfels: &Surfels, i: usize, nn: &[usize], spfh_of: impl Fn(usize) -> &'a Fpfh) -> Fpfh {
    let mut sum = [0.0f32; FPFH_LEN];
    let p = surfels.points[i];
    for &j in nn.iter().filter(|&&j| j != i) {
        let d2 = (surfels.points[j] - p).norm_squared();
        if d2 <= 0.0 {
            continue;
        }
        for (s, v) in sum.iter_mut().zip(spfh_of(j)) {
            *s += v / d2.sqrt();
        }
    }
    let own = spfh_of(i);
    let mut out = [0.0f32; FPFH_LEN];
    for f in 0..3 {
        let range = f * BINS_PER_FEATURE..(f + 1) * BINS_PER_FEATURE;
        let total: f32 = sum[range.clone()].iter().sum();
        let scale = if total > 0.0 { 100.0 / total } else { 0.0 };
        for b in range {
            out[b] = sum[b] * scale + own[b];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pair_features_are_symmetric_in_the_pair_order() {
        let (p1, n1) = (Point3::new(0.0, 0.0, 0.0), Vector3::new(0.0, 0.3, 1.0).normalize());
        let (p2, n2) = (Point3::new(1.0, 0.5, 0.2), Vector3::new(0.5, -0.2, 1.0).normalize());
        let a = pair_features(&p1, &n1, &p2, &n2).unwrap();
        let b = pair_features(&p2, &n2, &p1, &n1).unwrap();
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() < 1e-6, "{a:?} {b:?}");
        }
        assert!(pair_features(&p1, &n1, &p1, &n2).is_none());
    }

    #[test]
    fn bins_cover_the_ranges() {
        use std::f32::consts::PI;
        assert_eq!(bins(&[-PI, -1.0, -1.0]), [0, 11, 22]);
        assert_eq!(bins(&[PI, 1.0, 1.0]), [10, 21, 32]);
        assert_eq!(bins(&[0.0, 0.0, 0.0]), [5, 16, 27]);
    }
}
