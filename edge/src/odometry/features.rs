//! Feature extraction (F-LOAM section III-A): per-ring smoothness, sectors, edge and plane points.

use cloud::PointCloud;
use cloud::voxel::VoxelKey;
use nalgebra::Point3;
use rustc_hash::FxHashSet;

use super::FeatureConfig;
pub use super::feature_points::{Feature, Features};

/// One ring's points in firing order, with what feature selection needs per point.
struct Ring {
    id: u16,
    points: Vec<Point3<f32>>,
    phases: Vec<f32>,
    smoothness: Vec<f32>,
    /// Points excluded from selection: unreliable (occlusion boundary, grazing beam) or suppressed.
    blocked: Vec<bool>,
    /// Points next to a surface seen at a grazing angle, excluded from edges only.
    loose: Vec<bool>,
}

/// Splits a scan into rings, each ordered by measurement time, dropping points outside the range crop.
fn rings(scan: &PointCloud, ring_ids: &[u16], times: &[f32], period: f32, config: &FeatureConfig) -> Vec<Ring> {
    let rings_n = ring_ids.iter().copied().max().map_or(0, |m| m as usize + 1);
    let mut order: Vec<Vec<usize>> = vec![Vec::new(); rings_n];
    for (i, p) in scan.points.iter().enumerate() {
        let r = p.coords.norm();
        if r >= config.min_range && r <= config.max_range {
            order[ring_ids[i] as usize].push(i);
        }
    }
    order
        .into_iter()
        .enumerate()
        .map(|(id, mut idx)| {
            idx.sort_by(|&a, &b| times[a].total_cmp(&times[b]));
            Ring {
                id: id as u16,
                points: idx.iter().map(|&i| scan.points[i]).collect(),
                phases: idx.iter().map(|&i| (times[i] / period).clamp(0.0, 1.0)).collect(),
                smoothness: vec![0.0; idx.len()],
                blocked: vec![false; idx.len()],
                loose: vec![false; idx.len()],
            }
        })
        .collect()
}

/// Eq. 1: σ_i = ‖Σ_{j ∈ S} (p_j − p_i)‖² over the `k` neighbours on each side along the ring.
fn compute_smoothness(ring: &mut Ring, k: usize) {
    let p = &ring.points;
    for i in k..p.len().saturating_sub(k) {
        let sum = (1..=k).fold(nalgebra::Vector3::zeros(), |acc, j| acc + (p[i - j] - p[i]) + (p[i + j] - p[i]));
        ring.smoothness[i] = sum.norm_squared();
    }
}

/// LOAM's reliability checks: points on the far side of an occlusion boundary (they vanish as the
/// viewpoint moves) and points on surfaces nearly parallel to the beam (their spacing explodes).
fn block_unreliable(ring: &mut Ring, k: usize, config: &FeatureConfig) {
    let p = &ring.points;
    let n = p.len();
    let sin_min = config.edge_min_incidence_deg.to_radians().sin();
    // Whether the pair (i - 1, i) is a grazing surface, and whether it is point i's own silhouette
    // (the far-side gap of an occlusion boundary whose near side is i), carried from the last pair.
    let mut grazing_prev = k > 0 && k < n && grazing(&p[k - 1], &p[k], sin_min);
    let mut silhouette_prev = false;
    for i in k..n.saturating_sub(k + 1) {
        let (mut silhouette_next, mut next_silhouette_prev) = (false, false);
        let (d0, d1) = (p[i].coords.norm(), p[i + 1].coords.norm());
        let gap = (p[i + 1] - p[i]).norm_squared();
        if gap > config.occlusion_gap * config.occlusion_gap {
            // Compare directions: a boundary only when the two beams are adjacent but depths differ.
            let (near, far, far_is_next) = if d0 > d1 { (p[i + 1], p[i], false) } else { (p[i], p[i + 1], true) };
            let (dn, df) = (near.coords.norm(), far.coords.norm());
            let angular = (far.coords * (dn / df) - near.coords).norm() / dn;
            if angular < config.occlusion_angle {
                let range = if far_is_next { i + 1..=(i + k + 1).min(n - 1) } else { i.saturating_sub(k)..=i };
                // A silhouette when the background goes on behind the jump; on a surface seen at a
                // grazing angle every step is such a jump, and the next one is as deep.
                let beyond = if far_is_next { i + 2 } else { i.wrapping_sub(1) };
                let background = p.get(beyond).is_some_and(|b| (b.coords.norm() - df).abs() <= config.occlusion_gap);
                if far_is_next {
                    silhouette_next = background;
                } else {
                    next_silhouette_prev = background;
                }
                ring.blocked[range].iter_mut().for_each(|b| *b = true);
                if !config.silhouette_edges {
                    ring.blocked[if far_is_next { i } else { i + 1 }] = true;
                }
            }
        }
        let prev = (p[i] - p[i - 1]).norm_squared();
        let next = (p[i + 1] - p[i]).norm_squared();
        let limit = config.parallel_beam_ratio * d0 * d0;
        if prev > limit && next > limit {
            ring.blocked[i] = true;
        }
        // A bend next to a surface seen at a grazing angle: the samples on that surface lie a gap
        // apart, so where the bend is along it is known only to the gap, and the sharpest point
        // there marks where a sample fell, not a corner. As the viewpoint moves the samples slide
        // along the surface, and such "edges" pull the pose with them. The far side of the
        // point's own silhouette is background, not its surface, and is not judged.
        let grazing_next = grazing(&p[i], &p[i + 1], sin_min);
        if (grazing_prev && !silhouette_prev) || (grazing_next && !silhouette_next) {
            ring.loose[i] = true;
        }
        (grazing_prev, silhouette_prev) = (grazing_next, next_silhouette_prev);
    }
}

/// True when two consecutive samples of a ring lie on a surface seen at an angle γ from the beam
/// with sin γ below `sin_min`: two beams α apart hit a surface at range r a gap g = r α / sin γ
/// apart, whatever the sensor's azimuth step.
fn grazing(a: &Point3<f32>, b: &Point3<f32>, sin_min: f32) -> bool {
    if sin_min <= 0.0 {
        return false;
    }
    let (ra, rb) = (a.coords.norm(), b.coords.norm());
    let gap = (b - a).norm();
    let beams = a.coords.cross(&b.coords).norm() / (ra * rb).max(f32::MIN_POSITIVE);
    0.5 * (ra + rb) * beams < gap * sin_min
}

/// Keeps the first feature of each voxel: an even spread at a fraction of the cost (F-LOAM
/// downsamples its features to the map resolution).
struct Thinning {
    inv_edge: f32,
    inv_plane: f32,
    edges: FxHashSet<VoxelKey>,
    planes: FxHashSet<VoxelKey>,
}

impl Thinning {
    fn new(config: &FeatureConfig) -> Self {
        Thinning {
            inv_edge: 1.0 / config.edge_voxel,
            inv_plane: 1.0 / config.plane_voxel,
            edges: FxHashSet::default(),
            planes: FxHashSet::default(),
        }
    }
}

/// Per sector: the sharpest unblocked points above the edge threshold become edges (at most
/// `max_edges_per_sector`, suppressing their neighbours); points below the plane threshold become
/// planes. Both are thinned to one per voxel as they are found.
fn select(ring: &mut Ring, k: usize, config: &FeatureConfig, thinning: &mut Thinning, out: &mut Features) {
    let n = ring.points.len();
    if n < 2 * k + 1 {
        return;
    }
    let (start, end) = (k, n - k);
    let sectors = config.sectors.max(1);
    for s in 0..sectors {
        let lo = start + (end - start) * s / sectors;
        let hi = start + (end - start) * (s + 1) / sectors;
        // Edges: the sharpest first; only candidates above the threshold need sorting.
        let mut candidates: Vec<usize> = (lo..hi).filter(|&i| ring.smoothness[i] > config.edge_threshold).collect();
        candidates.sort_unstable_by(|&a, &b| ring.smoothness[b].total_cmp(&ring.smoothness[a]));
        let mut edges = 0;
        for &i in &candidates {
            if edges >= config.max_edges_per_sector {
                break;
            }
            if ring.blocked[i] || ring.loose[i] {
                continue;
            }
            if thinning.edges.insert(VoxelKey::of(&ring.points[i], thinning.inv_edge)) {
                out.edges.push(feature(ring, i));
            }
            edges += 1;
            suppress_neighbours(ring, i, k, config.suppression_gap);
        }
        // Planes: every reliable point flatter than the threshold, the first of its voxel.
        for i in lo..hi {
            if ring.smoothness[i] < config.plane_threshold
                && !ring.blocked[i]
                && thinning.planes.insert(VoxelKey::of(&ring.points[i], thinning.inv_plane))
            {
                out.planes.push(feature(ring, i));
            }
        }
    }
}

fn feature(ring: &Ring, i: usize) -> Feature {
    Feature { point: ring.points[i], phase: ring.phases[i], smoothness: ring.smoothness[i], ring: ring.id }
}

/// Blocks the `k` neighbours on each side of a chosen edge while the ring stays continuous, so one
/// corner does not yield a cluster of edge features.
fn suppress_neighbours(ring: &mut Ring, i: usize, k: usize, gap: f32) {
    ring.blocked[i] = true;
    let n = ring.points.len();
    for j in i + 1..=(i + k).min(n - 1) {
        if (ring.points[j] - ring.points[j - 1]).norm_squared() > gap * gap {
            break;
        }
        ring.blocked[j] = true;
    }
    for j in (i.saturating_sub(k)..i).rev() {
        if (ring.points[j + 1] - ring.points[j]).norm_squared() > gap * gap {
            break;
        }
        ring.blocked[j] = true;
    }
}

/// Missing per-point channels that feature extraction needs.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum FeatureError {
    /// The scan has no ring channel (sources derive one when the recording lacks it).
    #[error("scan has no ring channel")]
    NoRing,
    /// The scan has no per-point time channel (sources derive it from azimuth when missing).
    #[error("scan has no per-point time channel")]
    NoTime,
}

/// Which extractor made a scan's features.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FeatureKind {
    /// Ring smoothness (eq. 1): the scan has a ring channel.
    #[default]
    Rings,
    /// Voxel shape ([`super::voxel_features`]): no ring channel (solid-state, unordered points).
    VoxelShape,
}

/// The features of a scan, from its rings when it has a ring channel ([`extract`]) and from the
/// shape of its voxels when it has none ([`super::voxel_features::extract`]).
pub fn extract_any(
    scan: &PointCloud,
    period: f32,
    config: &FeatureConfig,
) -> Result<(Features, FeatureKind), FeatureError> {
    if scan.ring.is_none() {
        return Ok((super::voxel_features::extract(scan, period, config), FeatureKind::VoxelShape));
    }
    Ok((extract(scan, period, config)?, FeatureKind::Rings))
}

/// Extracts edge and plane features from a scan with ring and time channels, thinned to one per
/// voxel of `edge_voxel` / `plane_voxel`; `period` is the sweep duration in seconds, which turns
/// point times into sweep phases for distortion compensation.
pub fn extract(scan: &PointCloud, period: f32, config: &FeatureConfig) -> Result<Features, FeatureError> {
    let ring_ids = scan.ring.as_deref().ok_or(FeatureError::NoRing)?;
    let times = scan.time.as_deref().ok_or(FeatureError::NoTime)?;
    let k = config.neighbours;
    let mut out = Features::default();
    let mut thinning = Thinning::new(config);
    for mut ring in rings(scan, ring_ids, times, period, config) {
        compute_smoothness(&mut ring, k);
        block_unreliable(&mut ring, k, config);
        select(&mut ring, k, config, &mut thinning, &mut out);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::odometry::FeatureConfig;

    /// One ring sweeping a square room: walls are flat, the four corners are edges.
    fn square_room_ring(n: usize, half: f32) -> PointCloud {
        let mut c = PointCloud::with_capacity(n, cloud::Channels { intensity: false, ring: true, time: true });
        for i in 0..n {
            let a = i as f32 / n as f32 * std::f32::consts::TAU;
            let (dx, dy) = (a.cos(), a.sin());
            let t = half / dx.abs().max(dy.abs());
            c.points.push(Point3::new(dx * t, dy * t, 0.0));
            c.ring.as_mut().unwrap().push(0);
            c.time.as_mut().unwrap().push(i as f32 / n as f32 * 0.1);
        }
        c
    }

    #[test]
    fn corners_are_edges_and_walls_are_planes() {
        let scan = square_room_ring(1800, 5.0);
        // Voxels far below the point spacing: selection alone, no thinning.
        let config = FeatureConfig { edge_voxel: 1e-4, plane_voxel: 1e-4, ..FeatureConfig::default() };
        let f = extract(&scan, 0.1, &config).unwrap();
        assert!(!f.edges.is_empty());
        // Every edge lies near one of the corners (±5, ±5) at 45°, 135°, ...
        for e in &f.edges {
            let corner_dist = [(5.0, 5.0), (-5.0, 5.0), (-5.0, -5.0), (5.0, -5.0)]
                .iter()
                .map(|&(x, y)| ((e.point.x - x).powi(2) + (e.point.y - y).powi(2)).sqrt())
                .fold(f32::INFINITY, f32::min);
            assert!(corner_dist < 0.3, "edge at {:?} is {corner_dist} m from a corner", e.point);
        }
        // No more than one edge per corner: neighbours are suppressed.
        assert!(f.edges.len() <= 4, "{} edges", f.edges.len());
        // Planes: many, all on a wall (|x| or |y| = 5), none at a corner.
        assert!(f.planes.len() > 1000);
        for p in &f.planes {
            assert!((p.point.x.abs() - 5.0).abs() < 1e-4 || (p.point.y.abs() - 5.0).abs() < 1e-4);
            assert!((p.point.x.abs() - p.point.y.abs()).abs() > 0.05);
        }
        // Phases follow the firing time.
        assert!(f.planes.iter().all(|p| (0.0..=1.0).contains(&p.phase)));
        // Thinned to one per 0.4 m voxel: the 40 m of wall on the ring's plane cross about 100
        // voxels (a few more where the walls straddle voxel faces), each keeping its first plane.
        let thinned = extract(&scan, 0.1, &FeatureConfig::default()).unwrap();
        let voxels: FxHashSet<VoxelKey> = f.planes.iter().map(|p| VoxelKey::of(&p.point, 1.0 / 0.4)).collect();
        assert_eq!(thinned.planes.len(), voxels.len());
        let first =
            f.planes.iter().find(|p| VoxelKey::of(&p.point, 2.5) == VoxelKey::of(&thinned.planes[0].point, 2.5));
        assert_eq!(first, Some(&thinned.planes[0]));
        assert!((90..=140).contains(&thinned.planes.len()), "{}", thinned.planes.len());
    }

    #[test]
    fn far_side_of_an_occlusion_is_not_an_edge() {
        // A ring across a wall at 10 m with a pole at 3 m in front: the wall points right behind the
        // pole's silhouette are occluded, they must not be chosen; the pole's own border may be.
        let n = 400;
        let mut c = PointCloud::with_capacity(n, cloud::Channels { intensity: false, ring: true, time: true });
        for i in 0..n {
            let a = (i as f32 - n as f32 / 2.0) * 0.003;
            let d = if a.abs() < 0.05 { 3.0 } else { 10.0 };
            c.points.push(Point3::new(d * a.cos(), d * a.sin(), 0.0));
            c.ring.as_mut().unwrap().push(0);
            c.time.as_mut().unwrap().push(i as f32 * 1e-4);
        }
        let f = extract(&c, 0.1, &FeatureConfig::default()).unwrap();
        for e in &f.edges {
            assert!(e.point.coords.norm() < 5.0, "occluded wall point {:?} became an edge", e.point);
        }
    }

    /// One ring (azimuth step `step` rad, starting at `offset`) over a background wall 20 m away
    /// with a box in front: x (ahead) from 12.8 to 14.0 m, y from -1.0 to -1.8 m. Its near face
    /// (x = 12.8) is seen head-on, its side face (y = -1.0) at 4 to 4.5 degrees from the beams.
    fn ring_past_a_box(step: f32, offset: f32) -> PointCloud {
        let n = (std::f32::consts::TAU / step) as usize;
        let mut c = PointCloud::with_capacity(n, cloud::Channels { intensity: false, ring: true, time: true });
        for i in 0..n {
            let a = offset + i as f32 * step - std::f32::consts::PI;
            let d = nalgebra::Vector3::new(a.cos(), a.sin(), 0.0);
            // The box's faces facing the sensor, then the wall.
            let near = (d.x > 1e-6).then(|| 12.8 / d.x).filter(|t| (-1.8..=-1.0).contains(&(d.y * t)));
            let side = (d.y < -1e-6).then(|| -1.0 / d.y).filter(|t| (12.8..=14.0).contains(&(d.x * t)));
            let t = near.into_iter().chain(side).fold(20.0f32, f32::min);
            c.points.push(Point3::from(d * t));
            c.ring.as_mut().unwrap().push(0);
            c.time.as_mut().unwrap().push(i as f32 / n as f32 * 0.1);
        }
        c
    }

    #[test]
    fn a_face_seen_at_a_grazing_angle_gives_no_edge_where_a_sample_fell() {
        // The side face's samples lie ~0.6 m apart at the VLP-16's 0.2 degree step: its sharpest
        // point marks where a sample fell, not a corner. Over ten phases of the azimuth grid no
        // edge may lie on that face farther from its corners than a step of the near face (4.5
        // cm at 12.8 m); without the incidence test some phases put one there.
        let step = 0.2f32.to_radians();
        let on_the_side_face = |config: &FeatureConfig| {
            let (mut on_face, mut edges) = (0, 0);
            for k in 0..10 {
                let f = extract(&ring_past_a_box(step, k as f32 * step / 10.0), 0.1, config).unwrap();
                for e in f.edges.iter().filter(|e| e.point.coords.norm() < 15.0) {
                    edges += 1;
                    let inside = (12.8 + 0.045..14.0 - 0.045).contains(&e.point.x);
                    on_face += usize::from((e.point.y + 1.0).abs() < 1e-3 && inside);
                }
            }
            (on_face, edges)
        };
        let config = FeatureConfig { edge_voxel: 1e-4, ..FeatureConfig::default() };
        let (on_face, edges) = on_the_side_face(&config);
        assert_eq!(on_face, 0, "{on_face} of {edges} edges on the grazing face");
        // The near face's outer corner, seen against the wall, stays an edge in every phase.
        assert!(edges >= 10, "{edges} edges in 10 phases");
        let (without, _) = on_the_side_face(&FeatureConfig { edge_min_incidence_deg: 0.0, ..config });
        assert!(without > 0, "the case does not exercise the test");
    }

    #[test]
    fn missing_channels_are_errors() {
        let mut scan = square_room_ring(100, 5.0);
        scan.time = None;
        assert_eq!(extract(&scan, 0.1, &FeatureConfig::default()).unwrap_err(), FeatureError::NoTime);
        scan.ring = None;
        assert_eq!(extract(&scan, 0.1, &FeatureConfig::default()).unwrap_err(), FeatureError::NoRing);
    }
}
