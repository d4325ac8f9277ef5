//! Step 5 kept across merges — paper eq. 11, the union of the placed maps voxelised to fuse their
//! duplicates, updated by what changed instead of built again.
//!
//! Voxelising the union of every map at every merge cost a 16-robot station 0.85 s per merge once
//! the maps were large, nearly all of it for points that had not moved. Each voxel here keeps the
//! running sums of the points in it, and each map its contribution (the world points it put in and
//! their voxels), so that:
//! - a map that grew at the same placement adds only its newer points (a grown map's cloud holds
//!   the previous one's points first, see [`super::Merger::grow`]);
//! - a map that moved (new placement), changed shape or left the global map has its contribution
//!   subtracted and, if still placed, put in again.
//!
//! A placement that moves none of a map's points by more than a tenth of a voxel (2 cm outdoors,
//! 1 cm indoors) keeps the contribution where it is: a refined link or a new spanning tree moves
//! placements by millimetres at nearly every merge, and putting every moved map in again cost as
//! much as building the whole map. The published placements are the new ones; a map's points are
//! never further than that tenth from them.
//!
//! When the reference map changes (a new tree centre), every placement moves by one rigid motion:
//! the grid is kept and its output moved instead (the grid's own frame is then not the global
//! frame, and its voxels' edges are not the global axes; a voxel grid is as good in any frame).
//!
//! A growing map's earlier points stay at the positions they had when they were added: a local
//! map's voxel centroids move a little as points join them (by less than the local map's voxel);
//! the next move or change of shape of that map takes them at their new positions.

use std::collections::BTreeMap;

use cloud::memory::{HeapSize, vec_bytes};
use cloud::voxel::{CellIndex, VoxelKey};
use cloud::{Channels, PointCloud};
use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;

/// One map as the merge placed it.
pub(super) struct Placed<'a> {
    /// The map's id.
    pub id: usize,
    /// Its newest cloud, in its own frame.
    pub cloud: &'a PointCloud,
    /// Bumped whenever the map changed other than by growing.
    pub shape: u64,
    /// Its placement in the global frame.
    pub transform: Isometry3<f64>,
}

/// The fused global map, kept between merges.
pub(super) struct Assembly {
    inv_size: f32,
    /// Largest move of a map's points that keeps its contribution where it is, metres.
    tolerance: f64,
    /// The grid's frame in the global frame.
    frame: Isometry3<f64>,
    /// Each voxel's index into `voxels`.
    slot: CellIndex,
    voxels: Vec<Fused>,
    /// Voxels holding at least one point.
    live: usize,
    contributions: BTreeMap<usize, Contribution>,
    /// Whether intensity is fused (every placed map has it).
    intensity: bool,
}

/// Running sums of one voxel.
#[derive(Clone, Copy, Debug)]
struct Fused {
    /// f64: points are added and later subtracted again, and must cancel exactly.
    sum: [f64; 3],
    intensity: f64,
    count: u32,
    /// The map that put the first point here, of those still in it ([`NO_LABEL`] while unknown).
    label: usize,
}

const NO_LABEL: usize = usize::MAX;

/// What one map put into the grid.
struct Contribution {
    /// The placement its points were put in at, in the grid's frame.
    transform: Isometry3<f64>,
    /// Bounds of the points taken, in the map's own frame.
    low: Point3<f64>,
    high: Point3<f64>,
    shape: u64,
    /// Points of the map's cloud taken so far.
    taken: usize,
    /// Per point taken: its voxel, its world position and intensity (empty without intensity).
    cells: Vec<u32>,
    points: Vec<Point3<f32>>,
    intensities: Vec<f32>,
}

impl Contribution {
    /// The farthest that any point taken moves when the map is placed at `to` instead.
    fn largest_move(&self, to: &Isometry3<f64>) -> f64 {
        if self.taken == 0 {
            return 0.0;
        }
        let centre = nalgebra::center(&self.low, &self.high);
        let radius = (self.high - self.low).norm() / 2.0;
        // Every point is within `radius` of the centre, and a turn by θ moves a point at distance
        // r by 2 r sin(θ/2) relative to the centre.
        let turn = (to.rotation * self.transform.rotation.inverse()).angle();
        (to * centre - self.transform * centre).norm() + 2.0 * radius * (turn / 2.0).sin()
    }
}

impl HeapSize for Contribution {
    fn heap_bytes(&self) -> usize {
        vec_bytes(&self.cells) + vec_bytes(&self.points) + vec_bytes(&self.intensities)
    }
}

impl Assembly {
    /// An empty global map of voxels of edge `voxel` (validated positive by the merge config).
    pub fn new(voxel: f32) -> Self {
        Self {
            inv_size: 1.0 / voxel,
            tolerance: f64::from(voxel) / 10.0,
            frame: Isometry3::identity(),
            slot: CellIndex::default(),
            voxels: Vec::new(),
            live: 0,
            contributions: BTreeMap::new(),
            intensity: false,
        }
    }

    /// Bytes held for map `id`'s contribution (the shared grid is not split between maps).
    pub fn heap_bytes_of(&self, id: usize) -> usize {
        self.contributions.get(&id).map_or(0, HeapSize::heap_bytes)
    }

    /// The global map of `placed` (every merged map, ids ascending) with each point's map id: one
    /// point per voxel, the centroid of the points in it. Ring and time are per-sweep quantities,
    /// meaningless in a global map; intensity is kept when every placed map has it.
    pub fn update(&mut self, placed: &[Placed<'_>]) -> (PointCloud, Vec<usize>) {
        let intensity = placed.iter().all(|p| p.cloud.intensity.is_some());
        if intensity != self.intensity {
            *self = Self { intensity, ..Self::new(1.0 / self.inv_size) };
        }
        self.follow_reference(placed);
        let (tolerance, to_grid) = (self.tolerance, self.frame.inverse());
        let keep = |c: &Contribution, p: &Placed<'_>| {
            c.shape == p.shape && c.taken <= p.cloud.len() && c.largest_move(&(to_grid * p.transform)) <= tolerance
        };
        let stale: Vec<usize> = self
            .contributions
            .iter()
            .filter(|&(id, c)| !placed.iter().any(|p| p.id == *id && keep(c, p)))
            .map(|(&id, _)| id)
            .collect();
        let removed = !stale.is_empty();
        for id in stale {
            self.remove(id);
        }
        // Before anything is added again: a voxel goes to the maps that were in it before.
        if removed {
            self.relabel();
        }
        // Dead voxels cost memory and a pass over them per merge: start over once they outnumber
        // the live ones.
        if self.voxels.len() > 2 * self.live.max(1024) {
            self.compact();
        }
        for p in placed {
            self.add(p);
        }
        self.cloud()
    }

    /// Moves the grid's frame when most of what it holds moved by one rigid motion (a new
    /// reference map): the motion that keeps the largest contribution where it is, taken when it
    /// keeps more points than the current frame does.
    fn follow_reference(&mut self, placed: &[Placed<'_>]) {
        let same = |c: &Contribution, p: &Placed<'_>| c.shape == p.shape && c.taken <= p.cloud.len();
        let held: Vec<(&Contribution, &Placed<'_>)> = placed
            .iter()
            .filter_map(|p| Some((self.contributions.get(&p.id)?, p)))
            .filter(|(c, p)| same(c, p))
            .collect();
        let Some(&(largest, p)) = held.iter().max_by_key(|(c, p)| (c.taken, std::cmp::Reverse(p.id))) else { return };
        let kept = |frame: &Isometry3<f64>| -> usize {
            let to_grid = frame.inverse();
            held.iter()
                .filter(|(c, p)| c.largest_move(&(to_grid * p.transform)) <= self.tolerance)
                .map(|(c, _)| c.taken)
                .sum()
        };
        let candidate = p.transform * largest.transform.inverse();
        if kept(&candidate) > kept(&self.frame) {
            self.frame = candidate;
        }
    }

    /// Subtracts map `id`'s contribution; voxels it labelled lose their label.
    fn remove(&mut self, id: usize) {
        let Some(c) = self.contributions.remove(&id) else { return };
        for (k, &cell) in c.cells.iter().enumerate() {
            let v = &mut self.voxels[cell as usize];
            let p = c.points[k];
            v.sum[0] -= f64::from(p.x);
            v.sum[1] -= f64::from(p.y);
            v.sum[2] -= f64::from(p.z);
            v.intensity -= c.intensities.get(k).copied().map_or(0.0, f64::from);
            v.count -= 1;
            if v.count == 0 {
                // Exactly empty: no rounding residue left for a later point to inherit.
                *v = Fused { sum: [0.0; 3], intensity: 0.0, count: 0, label: NO_LABEL };
                self.live -= 1;
            } else if v.label == id {
                v.label = NO_LABEL;
            }
        }
    }

    /// Adds what map `p` has not yet put in: everything when it is new here, else its newer points.
    fn add(&mut self, p: &Placed<'_>) {
        let in_grid = self.frame.inverse() * p.transform;
        let c = self.contributions.entry(p.id).or_insert_with(|| Contribution {
            transform: in_grid,
            low: Point3::origin(),
            high: Point3::origin(),
            shape: p.shape,
            taken: 0,
            cells: Vec::new(),
            points: Vec::new(),
            intensities: Vec::new(),
        });
        if c.taken == p.cloud.len() {
            return;
        }
        // At the contribution's own placement: within the tolerance of the current one.
        let moved = c.transform.cast::<f32>();
        let new = &p.cloud.points[c.taken..];
        let fresh: Vec<Point3<f32>> = new.par_iter().map(|q| moved * q).collect();
        for q in new {
            let q = q.cast::<f64>();
            if c.taken == 0 && c.cells.is_empty() {
                (c.low, c.high) = (q, q);
            }
            c.low = c.low.inf(&q);
            c.high = c.high.sup(&q);
        }
        let intensities = p.cloud.intensity.as_ref().filter(|_| self.intensity).map(|i| &i[c.taken..]);
        c.taken = p.cloud.len();
        for (k, q) in fresh.iter().enumerate() {
            let (cell, new) = self.slot.number(VoxelKey::of(q, self.inv_size));
            if new {
                self.voxels.push(Fused { sum: [0.0; 3], intensity: 0.0, count: 0, label: NO_LABEL });
            }
            let v = &mut self.voxels[cell as usize];
            if v.count == 0 {
                self.live += 1;
            }
            if v.label == NO_LABEL {
                v.label = p.id;
            }
            v.sum[0] += f64::from(q.x);
            v.sum[1] += f64::from(q.y);
            v.sum[2] += f64::from(q.z);
            if let Some(i) = intensities {
                v.intensity += f64::from(i[k]);
                c.intensities.push(i[k]);
            }
            v.count += 1;
            c.cells.push(cell);
        }
        c.points.extend(fresh);
    }

    /// Gives each voxel whose labelling map left the label of the first remaining map (by id) in it.
    fn relabel(&mut self) {
        for (&id, c) in &self.contributions {
            for &cell in &c.cells {
                let v = &mut self.voxels[cell as usize];
                if v.label == NO_LABEL {
                    v.label = id;
                }
            }
        }
    }

    /// Builds the grid again from the contributions, without its dead voxels.
    fn compact(&mut self) {
        self.slot.clear();
        self.voxels.clear();
        self.live = 0;
        let contributions = std::mem::take(&mut self.contributions);
        for (id, mut c) in contributions {
            c.cells.clear();
            for (k, q) in c.points.iter().enumerate() {
                let (cell, new) = self.slot.number(VoxelKey::of(q, self.inv_size));
                if new {
                    self.voxels.push(Fused { sum: [0.0; 3], intensity: 0.0, count: 0, label: id });
                    self.live += 1;
                }
                let v = &mut self.voxels[cell as usize];
                v.sum[0] += f64::from(q.x);
                v.sum[1] += f64::from(q.y);
                v.sum[2] += f64::from(q.z);
                v.intensity += c.intensities.get(k).copied().map_or(0.0, f64::from);
                v.count += 1;
                c.cells.push(cell);
            }
            self.contributions.insert(id, c);
        }
    }

    /// The live voxels' centroids in the global frame, in the order the voxels were made, with
    /// their labels.
    fn cloud(&self) -> (PointCloud, Vec<usize>) {
        let (mut out, labels) = self.grid_cloud();
        if self.frame != Isometry3::identity() {
            let frame = self.frame.cast::<f32>();
            out.points.par_iter_mut().for_each(|p| *p = frame * *p);
        }
        (out, labels)
    }

    /// The same in the grid's frame.
    fn grid_cloud(&self) -> (PointCloud, Vec<usize>) {
        let channels = Channels { intensity: self.intensity, ring: false, time: false };
        let mut out = PointCloud::with_capacity(self.live, channels);
        let mut labels = Vec::with_capacity(self.live);
        for v in self.voxels.iter().filter(|v| v.count > 0) {
            let n = f64::from(v.count);
            out.points.push(Point3::new((v.sum[0] / n) as f32, (v.sum[1] / n) as f32, (v.sum[2] / n) as f32));
            if let Some(i) = out.intensity.as_mut() {
                i.push((v.intensity / n) as f32);
            }
            labels.push(v.label);
        }
        (out, labels)
    }
}

impl HeapSize for Assembly {
    fn heap_bytes(&self) -> usize {
        self.slot.heap_bytes()
            + vec_bytes(&self.voxels)
            + self.contributions.values().map(HeapSize::heap_bytes).sum::<usize>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// A deterministic scatter of `n` points over a 20 m box (a seeded LCG).
    fn scatter(n: usize, seed: u64) -> PointCloud {
        let mut s = seed;
        let mut next = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 40) as f32 / (1u64 << 24) as f32 * 20.0
        };
        let mut c = PointCloud::with_capacity(n, Channels { intensity: true, ring: false, time: false });
        for _ in 0..n {
            c.points.push(Point3::new(next(), next(), next() * 0.2));
            c.intensity.as_mut().unwrap().push(next());
        }
        c
    }

    fn placement(x: f64, yaw: f64) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(x, 0.5, 0.0), UnitQuaternion::from_euler_angles(0.0, 0.0, yaw))
    }

    /// Eq. 11 from scratch: the union voxelised; a voxel's label is the map of its first point, in
    /// the order the parts are given (the order they reached the station).
    fn from_scratch(
        placed: &[(usize, &PointCloud, Isometry3<f64>)],
        voxel: f32,
    ) -> Vec<(VoxelKey, Point3<f32>, usize)> {
        let mut cells: BTreeMap<VoxelKey, ([f64; 3], u32, usize)> = BTreeMap::new();
        for &(id, c, t) in placed {
            for p in &c.points {
                let q = t.cast::<f32>() * p;
                let e = cells.entry(VoxelKey::of(&q, 1.0 / voxel)).or_insert(([0.0; 3], 0, id));
                for (s, x) in e.0.iter_mut().zip([q.x, q.y, q.z]) {
                    *s += f64::from(x);
                }
                e.1 += 1;
            }
        }
        cells
            .into_iter()
            .map(|(k, (s, n, id))| {
                let n = f64::from(n);
                (k, Point3::new((s[0] / n) as f32, (s[1] / n) as f32, (s[2] / n) as f32), id)
            })
            .collect()
    }

    fn sorted(cloud: &PointCloud, labels: &[usize], voxel: f32) -> Vec<(VoxelKey, Point3<f32>, usize)> {
        let mut v: Vec<_> =
            cloud.points.iter().zip(labels).map(|(p, &l)| (VoxelKey::of(p, 1.0 / voxel), *p, l)).collect();
        v.sort_by_key(|e| e.0);
        v
    }

    /// Same voxels, centroids within a micrometre, same labels.
    fn assert_same(got: &[(VoxelKey, Point3<f32>, usize)], want: &[(VoxelKey, Point3<f32>, usize)]) {
        assert_eq!(got.len(), want.len());
        for (g, w) in got.iter().zip(want) {
            assert_eq!(g.0, w.0);
            assert!((g.1 - w.1).norm() < 1e-5, "{:?} vs {:?}", g.1, w.1);
            assert_eq!(g.2, w.2, "label of voxel {:?}", g.0);
        }
    }

    #[test]
    fn growing_moving_and_leaving_maps_give_the_union_voxelised_from_scratch() {
        let voxel = 0.5;
        let a = scatter(4000, 1);
        let b = scatter(3000, 2);
        let mut assembly = Assembly::new(voxel);
        let (ta, tb) = (placement(0.0, 0.0), placement(3.0, 0.4));
        // Map 0 grows in two steps at the same placement (its first points come first).
        let part = |range: std::ops::Range<usize>| PointCloud {
            points: a.points[range.clone()].to_vec(),
            intensity: Some(a.intensity.as_ref().unwrap()[range].to_vec()),
            ring: None,
            time: None,
        };
        let (a_half, a_rest) = (part(0..2000), part(2000..4000));
        // The grid in its own frame, and that frame.
        let step = |asm: &mut Assembly, list: &[(usize, &PointCloud, u64, Isometry3<f64>)]| {
            let placed: Vec<Placed<'_>> =
                list.iter().map(|&(id, cloud, shape, transform)| Placed { id, cloud, shape, transform }).collect();
            let (cloud, _) = asm.update(&placed);
            assert_eq!(cloud.intensity.as_ref().map(Vec::len), Some(cloud.len()));
            let (grid, labels) = asm.grid_cloud();
            (sorted(&grid, &labels, voxel), asm.frame.inverse())
        };
        // From scratch in the grid's frame.
        let scratch = |(got, to_grid): (Vec<_>, Isometry3<f64>), parts: &[(usize, &PointCloud, Isometry3<f64>)]| {
            let parts: Vec<_> = parts.iter().map(|&(id, c, t)| (id, c, to_grid * t)).collect();
            assert_same(&got, &from_scratch(&parts, voxel));
        };
        scratch(step(&mut assembly, &[(0, &a_half, 0, ta), (1, &b, 0, tb)]), &[(0, &a_half, ta), (1, &b, tb)]);
        scratch(
            step(&mut assembly, &[(0, &a, 0, ta), (1, &b, 0, tb)]),
            &[(0, &a_half, ta), (1, &b, tb), (0, &a_rest, ta)],
        );
        // Map 1 moves (map 0, the larger, stays): its old contribution is gone, map 0 labels the
        // voxels map 1 held first.
        let tb2 = placement(3.5, 0.3);
        scratch(step(&mut assembly, &[(0, &a, 0, ta), (1, &b, 0, tb2)]), &[(0, &a, ta), (1, &b, tb2)]);
        // Map 1 leaves the global map, map 0 changes shape at the same placement.
        let a_other = scatter(1500, 3);
        scratch(step(&mut assembly, &[(0, &a_other, 1, ta)]), &[(0, &a_other, ta)]);
        // Everything leaves and comes back.
        assert!(step(&mut assembly, &[]).0.is_empty());
        let c = scatter(6000, 9);
        let tc = placement(-2.0, 1.0);
        scratch(step(&mut assembly, &[(1, &b, 0, tb), (2, &c, 0, tc)]), &[(1, &b, tb), (2, &c, tc)]);
        // A map moved again and again leaves dead voxels behind, compacted once they outnumber
        // the live ones.
        for k in 1..8 {
            let t = placement(30.0 * f64::from(k), 0.1 * f64::from(k));
            scratch(step(&mut assembly, &[(1, &b, 0, t), (2, &c, 0, tc)]), &[(2, &c, tc), (1, &b, t)]);
            assert!(
                assembly.voxels.len() <= 3 * assembly.live,
                "{} voxels, {} live",
                assembly.voxels.len(),
                assembly.live
            );
        }
        assert!(assembly.voxels.len() < 7 * b.len(), "dead voxels were compacted");
    }

    #[test]
    fn a_placement_moved_by_millimetres_keeps_the_points_where_they_are() {
        let voxel = 0.5;
        let b = scatter(3000, 6);
        // A larger map that stays: the grid keeps its frame.
        let (c, tc) = (scatter(6000, 9), placement(-2.0, 1.0));
        let mut assembly = Assembly::new(voxel);
        let t = placement(3.0, 0.4);
        let placed = |t| {
            [Placed { id: 1, cloud: &b, shape: 0, transform: t }, Placed { id: 2, cloud: &c, shape: 0, transform: tc }]
        };
        let first = assembly.update(&placed(t)).0;
        // The map spans about 28 m: 0.05 mm and 1e-4 rad move its far points by under 2 mm.
        let nudged = Isometry3::from_parts(
            Translation3::new(0.00005, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 1e-4),
        ) * t;
        assert_eq!(assembly.update(&placed(nudged)).0.points, first.points, "a 2 mm move is not a move");
        // A move beyond a tenth of a voxel (5 cm here) puts the map in again.
        let moved = Isometry3::translation(0.06, 0.0, 0.0) * t;
        let (cloud, labels) = assembly.update(&placed(moved));
        assert_eq!(assembly.frame, Isometry3::identity());
        assert_same(&sorted(&cloud, &labels, voxel), &from_scratch(&[(2, &c, tc), (1, &b, moved)], voxel));
        // The tolerance is against where the points are, not the last placement: small moves add up.
        let mut t = moved;
        for _ in 0..10 {
            t = Isometry3::translation(0.01, 0.0, 0.0) * t;
            assembly.update(&placed(t));
            let put = &assembly.contributions[&1].points;
            let worst = put.iter().zip(&b.points).map(|(q, p)| (q - t.cast::<f32>() * p).norm()).fold(0.0, f32::max);
            assert!(worst <= 0.05 + 1e-5, "a point {worst} m from where the placement puts it");
        }
    }

    #[test]
    fn a_new_reference_moves_the_whole_map_without_putting_it_in_again() {
        let (a, b) = (scatter(3000, 7), scatter(2000, 8));
        let mut assembly = Assembly::new(0.5);
        let (ta, tb) = (placement(0.0, 0.0), placement(4.0, 0.7));
        let both = |ta, tb| {
            [Placed { id: 0, cloud: &a, shape: 0, transform: ta }, Placed { id: 1, cloud: &b, shape: 0, transform: tb }]
        };
        let (before, labels) = assembly.update(&both(ta, tb));
        let voxels = assembly.voxels.len();
        // Map 1 becomes the reference: both placements move by the inverse of its old one.
        let g = tb.inverse();
        let (after, moved_labels) = assembly.update(&both(g * ta, g * tb));
        assert_eq!(assembly.voxels.len(), voxels, "nothing put in again");
        assert_eq!(moved_labels, labels);
        for (p, q) in before.points.iter().zip(&after.points) {
            assert!((g.cast::<f32>() * p - q).norm() < 1e-4);
        }
        // And a map that moved on its own besides is put in again where it now is.
        let nudged = Isometry3::translation(0.3, 0.0, 0.0) * g * ta;
        assembly.update(&both(nudged, g * tb));
        let put = &assembly.contributions[&0];
        let worst = put
            .points
            .iter()
            .zip(&a.points)
            .map(|(q, p)| (assembly.frame.cast::<f32>() * q - nudged.cast::<f32>() * p).norm())
            .fold(0.0, f32::max);
        assert!(worst < 1e-3, "{worst}");
    }

    #[test]
    fn intensity_is_fused_only_when_every_map_has_it() {
        let a = scatter(500, 4);
        let mut b = scatter(500, 5);
        b.intensity = None;
        let mut assembly = Assembly::new(0.5);
        let t = placement(0.0, 0.0);
        let (cloud, _) = assembly.update(&[Placed { id: 0, cloud: &a, shape: 0, transform: t }]);
        assert!(cloud.intensity.is_some());
        let both =
            [Placed { id: 0, cloud: &a, shape: 0, transform: t }, Placed { id: 1, cloud: &b, shape: 0, transform: t }];
        let (cloud, labels) = assembly.update(&both);
        assert!(cloud.intensity.is_none());
        assert_same(&sorted(&cloud, &labels, 0.5), &from_scratch(&[(0, &a, t), (1, &b, t)], 0.5));
    }
}
