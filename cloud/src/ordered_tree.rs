//! A k-d tree that arranges its caller's points instead of copying them, in storage fixed at
//! construction.
//!
//! kiddo's trees own a copy of the points and allocate it afresh at every build, so a map rebuilt
//! every few scans grows its search structure with its size. This tree holds only its split planes
//! (allocated for a maximum number of points) and a scratch permutation; [`OrderedKdTree::build`]
//! says how to reorder the points so that every leaf is a contiguous run, and the caller moves its
//! points (and whatever it keeps per point) accordingly. Splits are at the median of the widest
//! extent, so the tree is balanced and its shape, hence its size, depends only on the point count.

use nalgebra::Point3;

use crate::kdtree::Neighbour;

/// Points per leaf: a leaf is scanned linearly, which beats descending for a handful of points.
const LEAF: usize = 16;

/// One inner node: points of its left half lie at or below `value` on `axis`, the right half at or above.
#[derive(Clone, Copy, Debug, Default)]
struct Split {
    value: f32,
    axis: u8,
}

/// A balanced k-d tree over up to `capacity` points kept in the caller's array (see the module doc).
pub struct OrderedKdTree {
    capacity: usize,
    len: usize,
    /// Inner nodes in heap order (children of `i` at `2i + 1`, `2i + 2`).
    splits: Vec<Split>,
    /// Build scratch: position `i` of the tree order holds the point at `order[i]` of the input.
    order: Vec<u32>,
}

impl OrderedKdTree {
    /// An empty tree whose storage fits `capacity` points.
    pub fn with_capacity(capacity: usize) -> Self {
        // Written with a non-zero value: a zero-filled vector comes from calloc, whose pages stay
        // unmapped until first use, and the tree's memory would then seem to grow with the map.
        let mut order = vec![u32::MAX; capacity];
        order.clear();
        OrderedKdTree { capacity, len: 0, splits: vec![Split::default(); inner_nodes(capacity)], order }
    }

    /// Most points the tree can hold.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Number of points in the tree.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when the tree holds no point.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Builds the tree over `points` (at most the capacity) and returns the order they must be put
    /// in before querying: position `i` must hold `points[order[i]]`.
    ///
    /// # Panics
    /// When `points` exceeds the capacity (the caller's budget is the tree's).
    pub fn build(&mut self, points: &[Point3<f32>]) -> &[u32] {
        assert!(points.len() <= self.capacity, "{} points exceed the tree's capacity {}", points.len(), self.capacity);
        self.len = points.len();
        self.order.clear();
        self.order.extend(0..points.len() as u32);
        self.split(points, 0, 0, points.len());
        &self.order
    }

    /// Splits `order[start..end]` at the median of its widest axis, recursively.
    fn split(&mut self, points: &[Point3<f32>], node: usize, start: usize, end: usize) {
        if end - start <= LEAF {
            return;
        }
        let range = &mut self.order[start..end];
        let axis = widest_axis(points, range);
        let mid = (end - start) / 2;
        range.select_nth_unstable_by(mid, |&a, &b| points[a as usize][axis].total_cmp(&points[b as usize][axis]));
        self.splits[node] = Split { value: points[range[mid] as usize][axis], axis: axis as u8 };
        self.split(points, 2 * node + 1, start, start + mid);
        self.split(points, 2 * node + 2, start + mid, end);
    }

    /// The `k` nearest of `points` (in tree order, as built) to `q` within `radius`, closest first;
    /// indices are positions in `points`.
    pub fn knn_within(&self, points: &[Point3<f32>], q: &Point3<f32>, k: usize, radius: f32) -> Vec<Neighbour> {
        let mut best = Best { found: Vec::with_capacity(k), k, limit: radius * radius };
        if k > 0 && self.len > 0 {
            self.search(&points[..self.len], q, 0, 0, self.len, &mut best);
        }
        best.found
    }

    fn search(&self, points: &[Point3<f32>], q: &Point3<f32>, node: usize, start: usize, end: usize, best: &mut Best) {
        if end - start <= LEAF {
            for (i, p) in points[start..end].iter().enumerate() {
                best.offer(start + i, (p - q).norm_squared());
            }
            return;
        }
        let split = self.splits[node];
        let mid = start + (end - start) / 2;
        let gap = q[split.axis as usize] - split.value;
        let (left, right) = ((2 * node + 1, start, mid), (2 * node + 2, mid, end));
        let (near, far) = if gap < 0.0 { (left, right) } else { (right, left) };
        self.search(points, q, near.0, near.1, near.2, best);
        if gap * gap <= best.worst() {
            self.search(points, q, far.0, far.1, far.2, best);
        }
    }
}

/// Inner nodes of the tree over `n` points: a complete binary tree down to leaves of at most
/// [`LEAF`] points.
fn inner_nodes(n: usize) -> usize {
    let mut size = n;
    let mut levels = 0;
    while size > LEAF {
        size = size.div_ceil(2);
        levels += 1;
    }
    (1usize << levels) - 1
}

/// The axis along which the points `order` picks spread the most.
fn widest_axis(points: &[Point3<f32>], order: &[u32]) -> usize {
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for &i in order {
        let p = points[i as usize];
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    (0..3).max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b]))).unwrap_or(0)
}

/// The `k` closest candidates so far within the squared radius `limit`, closest first.
struct Best {
    found: Vec<Neighbour>,
    k: usize,
    limit: f32,
}

impl Best {
    /// The squared distance a candidate must not exceed to enter.
    fn worst(&self) -> f32 {
        if self.found.len() < self.k { self.limit } else { self.found[self.k - 1].dist_sq }
    }

    fn offer(&mut self, index: usize, dist_sq: f32) {
        let full = self.found.len() == self.k;
        // A candidate as far as the k-th found so far does not displace it (the first found stays).
        if dist_sq > self.limit || (full && dist_sq >= self.found[self.k - 1].dist_sq) {
            return;
        }
        if full {
            self.found.pop();
        }
        let at = self.found.partition_point(|n| n.dist_sq <= dist_sq);
        self.found.insert(at, Neighbour { index, dist_sq });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(n: usize, seed: u64) -> Vec<Point3<f32>> {
        let mut rng = testkit::Rng::new(seed);
        let mut next = move || rng.uniform_f32(-10.0, 10.0);
        // A flattened cloud with duplicates: ties and a thin axis are where a tree goes wrong.
        let mut pts: Vec<Point3<f32>> = (0..n).map(|_| Point3::new(next(), next(), 0.05 * next())).collect();
        pts.extend_from_within(..n / 10);
        pts
    }

    #[test]
    fn nearest_within_the_radius_match_brute_force() {
        let mut pts = cloud(3000, 7);
        let mut tree = OrderedKdTree::with_capacity(4000);
        let order = tree.build(&pts).to_vec();
        pts = order.iter().map(|&i| pts[i as usize]).collect();
        for q in cloud(300, 11).iter().take(300) {
            for (k, radius) in [(1, 0.5), (5, 1.0), (8, 3.0), (20, 0.2)] {
                let got = tree.knn_within(&pts, q, k, radius);
                let mut all: Vec<f32> =
                    pts.iter().map(|p| (p - q).norm_squared()).filter(|&d| d <= radius * radius).collect();
                all.sort_by(f32::total_cmp);
                all.truncate(k);
                let dists: Vec<f32> = got.iter().map(|n| n.dist_sq).collect();
                assert_eq!(dists, all, "q {q} k {k} r {radius}");
                assert!(got.iter().all(|n| (pts[n.index] - q).norm_squared() == n.dist_sq));
            }
        }
    }

    #[test]
    fn storage_is_fixed_and_small_inputs_work() {
        let mut tree = OrderedKdTree::with_capacity(100);
        let splits = tree.splits.len();
        assert!(tree.knn_within(&[], &Point3::origin(), 3, 1.0).is_empty());
        for n in [0, 1, 16, 17, 100] {
            let pts: Vec<Point3<f32>> = (0..n).map(|i| Point3::new(i as f32, 0.0, 0.0)).collect();
            let order = tree.build(&pts).to_vec();
            let arranged: Vec<Point3<f32>> = order.iter().map(|&i| pts[i as usize]).collect();
            let got = tree.knn_within(&arranged, &Point3::new(3.2, 0.0, 0.0), 2, 10.0);
            // The nearest two of 0, 1, ..., n - 1 to 3.2 are 3 and 4, or what there is of 0-3.
            let mut want: Vec<f32> = (0..n).map(|i| i as f32).collect();
            want.sort_by(|a, b| (a - 3.2).abs().total_cmp(&(b - 3.2).abs()));
            want.truncate(2);
            assert_eq!(got.iter().map(|g| arranged[g.index].x).collect::<Vec<_>>(), want, "n {n}");
            assert_eq!(tree.splits.len(), splits);
        }
    }
}
