//! Step 5 — reciprocal k-nearest matching in descriptor space (paper, Algorithm 1).
//!
//! A source keypoint `i` and a target keypoint `j` correspond when `j` is among the `k` nearest
//! target descriptors of `i` and `i` among the `k` nearest source descriptors of `j`; for each `i`
//! only the nearest such `j` is kept (as map_merge_3d's `findFeatureCorrespondences`). With `k = 1`
//! this is the classic mutual-nearest-neighbour filter, which removes most wrong matches before
//! RANSAC.
//!
//! Search is exhaustive: k-d trees lose their edge in 33 dimensions, and for a few thousand keypoints
//! one pass over the distance matrix, computed as a matrix product and split over rayon, is exact
//! and fast (both directions' top-k lists come from the same pass).

use nalgebra::DMatrix;
use rayon::prelude::*;

use super::error::FeatureError;
use super::fpfh::{FPFH_LEN, Fpfh};

/// Settings of step 5.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MatchingConfig {
    /// Mutual neighbourhood size `k` (default 1: mutual nearest neighbours).
    pub k: usize,
}

impl Default for MatchingConfig {
    fn default() -> Self {
        Self { k: 1 }
    }
}

impl MatchingConfig {
    /// Checks that `k` is at least 1.
    pub fn validate(&self) -> Result<(), FeatureError> {
        if self.k == 0 {
            return Err(FeatureError::InvalidConfig("matching.k must be at least 1"));
        }
        Ok(())
    }
}

/// A putative correspondence between a source and a target keypoint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Correspondence {
    /// Index into the source keypoints.
    pub source: usize,
    /// Index into the target keypoints.
    pub target: usize,
    /// Euclidean distance between the two descriptors.
    pub distance: f32,
}

/// One candidate in a top-k list: squared descriptor distance and index.
type Candidate = (f32, u32);

/// Step 5: reciprocal k-nearest matches, in source order.
pub fn reciprocal_matches(source: &[Fpfh], target: &[Fpfh], k: usize) -> Vec<Correspondence> {
    if source.is_empty() || target.is_empty() || k == 0 {
        return Vec::new();
    }
    let (rows, cols) = top_k_both_ways(source, target, k);
    rows.iter()
        .enumerate()
        .filter_map(|(i, row)| {
            let &(d2, j) = row.iter().find(|&&(_, j)| {
                j != u32::MAX && cols[j as usize * k..(j as usize + 1) * k].iter().any(|c| c.1 as usize == i)
            })?;
            Some(Correspondence { source: i, target: j as usize, distance: d2.sqrt() })
        })
        .collect()
}

/// The `k` nearest targets of each source and (flattened, `k` per target) the `k` nearest sources
/// of each target, from one pass over the distance matrix.
///
/// Squared distances come from `|a|² + |b|² − 2 a·b`, the dot products from a matrix product per
/// block of source rows (nalgebra's blocked, vectorised GEMM), which is several times faster than
/// pairwise loops; blocks run in parallel and keep memory at `ROWS_PER_TASK × targets` floats.
fn top_k_both_ways(source: &[Fpfh], target: &[Fpfh], k: usize) -> (Vec<Vec<Candidate>>, Vec<Candidate>) {
    const ROWS_PER_TASK: usize = 128;
    let empty: Candidate = (f32::INFINITY, u32::MAX);
    let n_t = target.len();
    let target_rows = DMatrix::<f32>::from_fn(n_t, FPFH_LEN, |j, c| target[j][c]);
    let target_norms: Vec<f32> = target.iter().map(|b| b.iter().map(|v| v * v).sum()).collect();
    source
        .par_chunks(ROWS_PER_TASK)
        .enumerate()
        .map(|(chunk, block)| {
            let block_cols = DMatrix::<f32>::from_fn(FPFH_LEN, block.len(), |c, r| block[r][c]);
            // Column r holds a_r · b_j for every target j, contiguous.
            let dots = &target_rows * &block_cols;
            let mut cols = vec![empty; n_t * k];
            let mut rows = Vec::with_capacity(block.len());
            for (r, a) in block.iter().enumerate() {
                let i = (chunk * ROWS_PER_TASK + r) as u32;
                let a_norm: f32 = a.iter().map(|v| v * v).sum();
                let mut row = vec![empty; k];
                for (j, (&dot, &b_norm)) in dots.column(r).iter().zip(&target_norms).enumerate() {
                    // Rounding can make the difference slightly negative for identical descriptors.
                    let d2 = (a_norm + b_norm - 2.0 * dot).max(0.0);
                    offer(&mut row, (d2, j as u32));
                    offer(&mut cols[j * k..(j + 1) * k], (d2, i));
                }
                rows.push(row);
            }
            (rows, cols)
        })
        .reduce(
            || (Vec::new(), vec![empty; n_t * k]),
            |(mut rows_a, mut cols_a), (rows_b, cols_b)| {
                rows_a.extend(rows_b);
                for (slots, other) in cols_a.chunks_mut(k).zip(cols_b.chunks(k)) {
                    for &c in other {
                        offer(slots, c);
                    }
                }
                (rows_a, cols_a)
            },
        )
}

/// Inserts `c` into the ascending list `slots` if it beats the last entry (ties: lower index first).
fn offer(slots: &mut [Candidate], c: Candidate) {
    let better = |a: &Candidate, b: &Candidate| a.0 < b.0 || (a.0 == b.0 && a.1 < b.1);
    let Some(last) = slots.last() else { return };
    if c.1 == u32::MAX || !better(&c, last) {
        return;
    }
    let mut pos = slots.len() - 1;
    while pos > 0 && better(&c, &slots[pos - 1]) {
        slots[pos] = slots[pos - 1];
        pos -= 1;
    }
    slots[pos] = c;
}

#[cfg(test)]
mod tests {
    use super::*;

    fn squared_distance(a: &Fpfh, b: &Fpfh) -> f32 {
        a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum()
    }

    fn descriptor(seed: u64) -> Fpfh {
        let mut rng = testkit::Rng::new(testkit::Rng::spread(seed));
        std::array::from_fn(|_| rng.f32() * 100.0)
    }

    #[test]
    fn mutual_nearest_neighbours_match_brute_force() {
        let src: Vec<Fpfh> = (0..300).map(descriptor).collect();
        // Targets: a shuffled, slightly perturbed copy of half the sources plus unrelated ones.
        let mut tgt: Vec<Fpfh> = (0..150).map(|i| src[(i * 7) % 300].map(|v| v + 0.5)).collect();
        tgt.extend((1000..1200).map(descriptor));
        let got = reciprocal_matches(&src, &tgt, 1);
        let nearest = |q: &Fpfh, set: &[Fpfh]| {
            (0..set.len()).min_by(|&a, &b| squared_distance(q, &set[a]).total_cmp(&squared_distance(q, &set[b])))
        };
        let want: Vec<(usize, usize)> = (0..src.len())
            .filter_map(|i| {
                let j = nearest(&src[i], &tgt)?;
                (nearest(&tgt[j], &src) == Some(i)).then_some((i, j))
            })
            .collect();
        let got_pairs: Vec<(usize, usize)> = got.iter().map(|c| (c.source, c.target)).collect();
        assert_eq!(got_pairs, want);
        assert!(got.len() >= 150);
        // k = 3 keeps at least the mutual nearest pairs.
        assert!(reciprocal_matches(&src, &tgt, 3).len() >= got.len());
    }

    #[test]
    fn empty_sets_give_nothing() {
        assert!(reciprocal_matches(&[], &[descriptor(1)], 1).is_empty());
    }
}
