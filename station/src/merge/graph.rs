//! Step 4 — the match graph: maximum spanning forest, reference component, tree centre, chaining.
//!
//! Nodes are map positions `0..n`; an edge `(a, b, T_ab, w)` says `T_ab` maps `b` into `a` with
//! confidence `w`. The spanning tree keeps, among all ways to connect the maps, the one whose
//! weakest links are strongest (Kruskal on descending weight), so every global transform is a
//! chain of the most trusted estimates.

use std::collections::VecDeque;

use nalgebra::Isometry3;

/// A graph edge: `transform` maps node `b` into node `a`'s frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GraphEdge {
    /// First node.
    pub a: usize,
    /// Second node.
    pub b: usize,
    /// Maps `b` into `a`.
    pub transform: Isometry3<f64>,
    /// Confidence, higher is better.
    pub weight: f64,
}

/// Disjoint sets with path halving and union by size.
struct UnionFind {
    parent: Vec<usize>,
    size: Vec<usize>,
}

impl UnionFind {
    fn new(n: usize) -> Self {
        Self { parent: (0..n).collect(), size: vec![1; n] }
    }

    fn find(&mut self, mut x: usize) -> usize {
        while self.parent[x] != x {
            self.parent[x] = self.parent[self.parent[x]];
            x = self.parent[x];
        }
        x
    }

    /// Joins the sets of `a` and `b`; false if they were already one.
    fn union(&mut self, a: usize, b: usize) -> bool {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra == rb {
            return false;
        }
        let (big, small) = if self.size[ra] >= self.size[rb] { (ra, rb) } else { (rb, ra) };
        self.parent[small] = big;
        self.size[big] += self.size[small];
        true
    }
}

/// Kruskal on descending weight: the edges (indices into `edges`) of a maximum spanning forest.
/// Ties are broken by node pair, so the forest does not depend on the input order.
pub fn maximum_spanning_forest(n: usize, edges: &[GraphEdge]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..edges.len()).collect();
    order.sort_by(|&i, &j| {
        let (ei, ej) = (&edges[i], &edges[j]);
        ej.weight.total_cmp(&ei.weight).then((ei.a, ei.b).cmp(&(ej.a, ej.b)))
    });
    let mut sets = UnionFind::new(n);
    order.into_iter().filter(|&i| sets.union(edges[i].a, edges[i].b)).collect()
}

/// The connected components of the forest, each sorted, largest first (ties: lowest node first).
pub fn components(n: usize, edges: &[GraphEdge], forest: &[usize]) -> Vec<Vec<usize>> {
    let mut sets = UnionFind::new(n);
    for &i in forest {
        sets.union(edges[i].a, edges[i].b);
    }
    let mut groups: Vec<Vec<usize>> = Vec::new();
    let mut slot = vec![usize::MAX; n];
    for v in 0..n {
        let root = sets.find(v);
        if slot[root] == usize::MAX {
            slot[root] = groups.len();
            groups.push(Vec::new());
        }
        groups[slot[root]].push(v);
    }
    // Stable: equal sizes keep the order of their lowest node.
    groups.sort_by_key(|g| std::cmp::Reverse(g.len()));
    groups
}

/// Tree neighbours of every node: (neighbour, edge index).
fn adjacency(n: usize, edges: &[GraphEdge], tree: &[usize]) -> Vec<Vec<(usize, usize)>> {
    let mut adj = vec![Vec::new(); n];
    for &i in tree {
        adj[edges[i].a].push((edges[i].b, i));
        adj[edges[i].b].push((edges[i].a, i));
    }
    adj
}

/// Hop count from `root` to every node (`usize::MAX` if unreachable).
fn hops_from(root: usize, adj: &[Vec<(usize, usize)>]) -> Vec<usize> {
    let mut hops = vec![usize::MAX; adj.len()];
    hops[root] = 0;
    let mut queue = VecDeque::from([root]);
    while let Some(v) = queue.pop_front() {
        for &(w, _) in &adj[v] {
            if hops[w] == usize::MAX {
                hops[w] = hops[v] + 1;
                queue.push_back(w);
            }
        }
    }
    hops
}

/// The node of `component` with the least maximum hop count to the others (the lowest on ties).
pub fn tree_centre(n: usize, edges: &[GraphEdge], tree: &[usize], component: &[usize]) -> Option<usize> {
    let adj = adjacency(n, edges, tree);
    let eccentricity = |v: usize| {
        let hops = hops_from(v, &adj);
        component.iter().map(|&w| hops[w]).max().unwrap_or(0)
    };
    component.iter().copied().min_by_key(|&v| (eccentricity(v), v))
}

/// A node's place in the chained tree.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Chained {
    /// Maps the node into the root's frame.
    pub transform: Isometry3<f64>,
    /// Lowest edge weight on the path to the root (infinite for the root).
    pub weakest: f64,
    /// Edges on the path to the root.
    pub hops: usize,
}

/// Global transforms by chaining the tree edges outwards from `root`: `None` off the root's tree.
pub fn chain(n: usize, edges: &[GraphEdge], tree: &[usize], root: usize) -> Vec<Option<Chained>> {
    let adj = adjacency(n, edges, tree);
    let mut out: Vec<Option<Chained>> = vec![None; n];
    out[root] = Some(Chained { transform: Isometry3::identity(), weakest: f64::INFINITY, hops: 0 });
    let mut queue = VecDeque::from([root]);
    while let Some(v) = queue.pop_front() {
        let here = out[v].expect("queued nodes are chained");
        for &(w, i) in &adj[v] {
            if out[w].is_some() {
                continue;
            }
            let e = &edges[i];
            // T_root_w = T_root_v · T_v_w, where T_ab maps b into a.
            let step = if e.a == v { e.transform } else { e.transform.inverse() };
            out[w] = Some(Chained {
                transform: here.transform * step,
                weakest: here.weakest.min(e.weight),
                hops: here.hops + 1,
            });
            queue.push_back(w);
        }
    }
    out
}
