//! The sparse normal equations of cost (1) (see [`super`]) and their Cholesky factorisation.
//!
//! Linearising every edge at the current poses (IRLS weight `w = ρ'(eᵀΩe)` from its kernel) gives
//! the Gauss-Newton system over the free poses' right perturbations `δ`:
//!
//! ```text
//! H δ = −b,   H = Σₑ Jₑᵀ wₑΩₑ Jₑ,   b = Σₑ Jₑᵀ wₑΩₑ eₑ,   Jₑ = [∂e/∂δᵢ  ∂e/∂δⱼ]          (2)
//! ```
//!
//! `H` has a 6x6 block on the diagonal for each free pose and one off the diagonal for each pair
//! of free poses joined by an edge. That pattern never changes, so it is laid out once
//! ([`Pattern`]): the lower triangle in compressed columns, as faer's Cholesky reads it, with each
//! edge knowing where its blocks go. Every linearisation then writes values into the same slots,
//! and the symbolic factorisation (fill-reducing ordering, elimination tree, supernodes) is
//! computed once and reused for every iteration and every λ ([`Factoriser`]).
//!
//! Sums are deterministic: edges are linearised in parallel, but their blocks are added in edge
//! order, so the result does not depend on the number of threads.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::solvers::LltError;
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::linalg::cholesky::{CholeskySymbolicParams, SymbolicCholesky, factorize_symbolic_cholesky};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use faer::{Conj, MatMut, Par, Side};
use nalgebra::{Isometry3, Matrix6, Vector6};
use rayon::prelude::*;

use super::residual::{self, Linearised};
use super::{Edge, PoseGraphConfig, PoseGraphError};

/// Unknowns per pose: `δ = [ρ; φ]`.
const DIM: usize = 6;

/// Edges per rayon task when linearising: enough work (~20 µs) to amortise the task.
const CHUNK: usize = 256;

/// Where each free pose's unknowns and each edge's blocks sit in `H` (lower triangle, compressed
/// columns) and `b`.
pub struct Pattern {
    /// Block column of each pose's unknowns; `None` for a fixed pose.
    variable: Vec<Option<usize>>,
    /// The structure of `H`'s lower triangle.
    symbolic: SymbolicSparseColMat<usize>,
    /// Per edge, the rank of its off-diagonal block among its column's (see [`Pattern::new`]).
    cross_slot: Vec<Option<usize>>,
    /// Value index of each diagonal entry `H[k, k]`.
    diagonal: Vec<usize>,
}

impl Pattern {
    /// The pattern of `edges` over the poses not `fixed`.
    ///
    /// Block column `c` holds, in each of its six scalar columns `6c + k`, the lower part of its
    /// diagonal block (rows `6c + k .. 6c + 6`), then one 6-row block for each free pose `r > c`
    /// joined to `c`, in increasing `r` (the block's slot).
    pub fn new(fixed: &[bool], edges: &[Edge]) -> Pattern {
        let mut next = 0..;
        let variable: Vec<Option<usize>> = fixed.iter().map(|&f| if f { None } else { next.next() }).collect();
        let blocks = variable.iter().flatten().count();
        let mut below: Vec<Vec<usize>> = vec![Vec::new(); blocks];
        let pairs: Vec<Option<(usize, usize)>> = edges.iter().map(|e| block_pair(&variable, e)).collect();
        for &(row, col) in pairs.iter().flatten() {
            below[col].push(row);
        }
        for rows in &mut below {
            rows.sort_unstable();
            rows.dedup();
        }
        let cross_slot =
            pairs.iter().map(|p| p.map(|(row, col)| below[col].binary_search(&row).unwrap_or(0))).collect();
        let (mut col_ptr, mut row_idx, mut diagonal) = (vec![0], Vec::new(), Vec::with_capacity(blocks * DIM));
        for (c, rows) in below.iter().enumerate() {
            for k in 0..DIM {
                diagonal.push(row_idx.len());
                row_idx.extend(DIM * c + k..DIM * (c + 1));
                row_idx.extend(rows.iter().flat_map(|&r| DIM * r..DIM * (r + 1)));
                col_ptr.push(row_idx.len());
            }
        }
        let n = blocks * DIM;
        let symbolic = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
        Pattern { variable, symbolic, cross_slot, diagonal }
    }

    /// Number of unknowns: six per free pose.
    pub fn unknowns(&self) -> usize {
        self.diagonal.len()
    }

    /// Number of stored entries of `H`'s lower triangle.
    pub fn entries(&self) -> usize {
        self.symbolic.row_idx().len()
    }

    /// Value indices of the diagonal of `H` (for damping).
    pub fn diagonal(&self) -> &[usize] {
        &self.diagonal
    }

    /// Block column of pose `pose`, `None` when it is fixed.
    pub fn variable(&self, pose: usize) -> Option<usize> {
        self.variable[pose]
    }

    /// `H` with `values` on this pattern.
    pub fn matrix<'a>(&'a self, values: &'a [f64]) -> SparseColMatRef<'a, usize, f64> {
        SparseColMatRef::new(self.symbolic.as_ref(), values)
    }

    /// Adds `block` to block column `col`: its diagonal block when `slot` is `None`, lower part
    /// only; else its off-diagonal block number `slot`.
    fn add_block(&self, values: &mut [f64], col: usize, slot: Option<usize>, block: &Matrix6<f64>) {
        let col_ptr = self.symbolic.col_ptr();
        for k in 0..DIM {
            let start = col_ptr[DIM * col + k];
            match slot {
                // Diagonal block: rows k..6 of column k.
                None => (k..DIM).for_each(|a| values[start + a - k] += block[(a, k)]),
                // Off-diagonal block: after the 6 − k diagonal rows, `slot` blocks of 6 rows.
                Some(s) => {
                    let first = start + (DIM - k) + DIM * s;
                    (0..DIM).for_each(|a| values[first + a] += block[(a, k)]);
                }
            }
        }
    }
}

/// The (row, column) block of an edge between two free poses, row > column; `None` when a side
/// is fixed.
fn block_pair(variable: &[Option<usize>], edge: &Edge) -> Option<(usize, usize)> {
    let (a, b) = (variable[edge.from]?, variable[edge.to]?);
    Some((a.max(b), a.min(b)))
}

/// One edge's weighted contribution to (2).
#[derive(Clone, Copy)]
struct Contribution {
    /// `Jᵢᵀ A Jᵢ`, `Jⱼᵀ A Jⱼ`, `Jⱼᵀ A Jᵢ` with `A = wΩ`.
    from_from: Matrix6<f64>,
    to_to: Matrix6<f64>,
    to_from: Matrix6<f64>,
    /// `Jᵢᵀ A e`, `Jⱼᵀ A e`.
    b_from: Vector6<f64>,
    b_to: Vector6<f64>,
}

impl Contribution {
    /// One edge linearised at `poses` and weighted by its kernel, eq. (2).
    fn of(poses: &[Isometry3<f64>], edge: &Edge, config: &PoseGraphConfig) -> Contribution {
        let Linearised { error, d_from, d_to } =
            residual::linearise(&edge.measurement, &poses[edge.from], &poses[edge.to]);
        let s = error.dot(&(edge.information * error));
        let kernel = config.kernel(edge.kind);
        let a = kernel.weight(s) * edge.information;
        let (at_from, at_to) = (d_from.transpose() * a, d_to.transpose() * a);
        Contribution {
            from_from: at_from * d_from,
            to_to: at_to * d_to,
            to_from: at_to * d_from,
            b_from: at_from * error,
            b_to: at_to * error,
        }
    }

    fn zero() -> Contribution {
        let z = Matrix6::zeros();
        Contribution { from_from: z, to_to: z, to_from: z, b_from: Vector6::zeros(), b_to: Vector6::zeros() }
    }
}

/// `H` (values on a [`Pattern`]) and `b` at one linearisation point, with the per-edge buffer they
/// are summed from (allocated once).
pub struct NormalEquations {
    /// `H`'s lower triangle, in the pattern's order.
    pub h: Vec<f64>,
    /// `b`, six entries per free pose.
    pub b: Vec<f64>,
    parts: Vec<Contribution>,
}

impl NormalEquations {
    /// Zeroed equations for `edges` on `pattern`.
    pub fn new(pattern: &Pattern, edges: usize) -> NormalEquations {
        NormalEquations {
            h: vec![0.0; pattern.entries()],
            b: vec![0.0; pattern.unknowns()],
            parts: vec![Contribution::zero(); edges],
        }
    }

    /// Linearises every edge at `poses` and sums (2).
    pub fn assemble(&mut self, pattern: &Pattern, poses: &[Isometry3<f64>], edges: &[Edge], config: &PoseGraphConfig) {
        // Edges are linearised in parallel and added in edge order: the sums are those of a
        // serial loop whatever the thread count.
        self.parts
            .par_iter_mut()
            .zip(edges)
            .with_min_len(CHUNK)
            .for_each(|(part, e)| *part = Contribution::of(poses, e, config));
        let NormalEquations { h, b, parts } = self;
        h.fill(0.0);
        b.fill(0.0);
        for ((edge, part), slot) in edges.iter().zip(parts.iter()).zip(&pattern.cross_slot) {
            add(pattern, edge, *slot, part, h, b);
        }
    }
}

/// Adds one edge's blocks to `h` and `b` where the pattern puts them (fixed sides are left out).
fn add(pattern: &Pattern, edge: &Edge, slot: Option<usize>, part: &Contribution, h: &mut [f64], b: &mut [f64]) {
    let (i, j) = (pattern.variable(edge.from), pattern.variable(edge.to));
    if let Some(i) = i {
        pattern.add_block(h, i, None, &part.from_from);
        add_to(&mut b[DIM * i..DIM * (i + 1)], &part.b_from);
    }
    if let Some(j) = j {
        pattern.add_block(h, j, None, &part.to_to);
        add_to(&mut b[DIM * j..DIM * (j + 1)], &part.b_to);
    }
    match (i, j) {
        // The block at (row j, column i) is Jⱼᵀ A Jᵢ; at (row i, column j) its transpose.
        (Some(i), Some(j)) if j > i => pattern.add_block(h, i, slot, &part.to_from),
        (Some(_), Some(j)) => pattern.add_block(h, j, slot, &part.to_from.transpose()),
        _ => {}
    }
}

fn add_to(target: &mut [f64], v: &Vector6<f64>) {
    target.iter_mut().zip(v.iter()).for_each(|(x, v)| *x += v);
}

/// Cost (1) at `poses` without linearising.
pub fn cost(poses: &[Isometry3<f64>], edges: &[Edge], config: &PoseGraphConfig) -> f64 {
    // Costs of fixed chunks, added in chunk order: deterministic whatever the thread count.
    let chunk_cost = |chunk: &[Edge]| -> f64 {
        chunk
            .iter()
            .map(|e| {
                let error = residual::error(&e.measurement, &poses[e.from], &poses[e.to]);
                0.5 * config.kernel(e.kind).rho(error.dot(&(e.information * error)))
            })
            .sum()
    };
    crate::gauss_newton::reduce_in_order(edges.par_chunks(CHUNK), chunk_cost, 0.0, |a, b| a + b)
}

/// The sparse Cholesky factorisation of `H` on a fixed pattern: the symbolic analysis once, then
/// one numeric factorisation per damped system, into buffers allocated once.
pub struct Factoriser {
    symbolic: SymbolicCholesky<usize>,
    factor: Vec<f64>,
    scratch: MemBuffer,
}

impl Factoriser {
    /// The symbolic factorisation of `pattern` (AMD ordering, faer's default).
    pub fn new(pattern: &Pattern) -> Result<Factoriser, PoseGraphError> {
        // Supernodal: H is made of dense 6x6 blocks, and its dense supernodes factor with blocked
        // kernels (faer's flop-count heuristic picks the scalar simplicial code here, 2x slower).
        let params = CholeskySymbolicParams {
            supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SUPERNODAL,
            ..Default::default()
        };
        let symbolic = factorize_symbolic_cholesky(pattern.symbolic.as_ref(), Side::Lower, Default::default(), params)
            .map_err(|e| PoseGraphError::Factorisation(e.to_string()))?;
        // One thread: faer's parallel factorisation would make the last bits depend on the
        // thread count, and at these sizes it gains little.
        let scratch = MemBuffer::new(
            symbolic
                .factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default())
                .or(symbolic.solve_in_place_scratch::<f64>(1, Par::Seq)),
        );
        Ok(Factoriser { factor: vec![0.0; symbolic.len_val()], symbolic, scratch })
    }

    /// Solves `H x = rhs` in place; `Ok(false)` when `H` is not numerically positive definite.
    pub fn solve(&mut self, h: SparseColMatRef<'_, usize, f64>, rhs: &mut [f64]) -> Result<bool, PoseGraphError> {
        let stack = MemStack::new(&mut self.scratch);
        let llt = match self.symbolic.factorize_numeric_llt(
            &mut self.factor,
            h,
            Side::Lower,
            Default::default(),
            Par::Seq,
            stack,
            Default::default(),
        ) {
            Ok(llt) => llt,
            Err(LltError::NonPositivePivot { .. }) => return Ok(false),
        };
        let n = rhs.len();
        let stack = MemStack::new(&mut self.scratch);
        llt.solve_in_place_with_conj(Conj::No, MatMut::from_column_major_slice_mut(rhs, n, 1), Par::Seq, stack);
        Ok(rhs.iter().all(|v| v.is_finite()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose_graph::EdgeKind;
    use nalgebra::{DMatrix, DVector};
    use testkit::Rng;

    /// Five poses, pose 0 fixed; edges in both directions, two between the same pair, one to the
    /// fixed pose; random poses, measurements and positive-definite information.
    fn small_graph(rng: &mut Rng) -> (Vec<Isometry3<f64>>, Vec<Edge>, Vec<bool>) {
        let poses: Vec<Isometry3<f64>> = (0..5).map(|_| random_pose(rng)).collect();
        let pairs = [(0, 1), (1, 2), (3, 1), (2, 4), (4, 2), (0, 4), (3, 4)];
        let edges = pairs
            .iter()
            .map(|&(from, to)| {
                let m = Matrix6::from_fn(|_, _| rng.uniform(-1.0, 1.0));
                let information = m * m.transpose() + Matrix6::identity();
                Edge { from, to, measurement: random_pose(rng), information, kind: EdgeKind::Odometry }
            })
            .collect();
        (poses, edges, vec![true, false, false, false, false])
    }

    fn random_pose(rng: &mut Rng) -> Isometry3<f64> {
        crate::se3::exp(&Vector6::from_fn(|_, _| rng.uniform(-1.0, 1.0)))
    }

    /// `H` and `b` summed densely over all poses, then the fixed pose's rows and columns dropped.
    fn brute_force(poses: &[Isometry3<f64>], edges: &[Edge]) -> (DMatrix<f64>, DVector<f64>) {
        let n = poses.len() * DIM;
        let (mut h, mut b) = (DMatrix::zeros(n, n), DVector::zeros(n));
        for e in edges {
            let lin = residual::linearise(&e.measurement, &poses[e.from], &poses[e.to]);
            let mut j = DMatrix::zeros(DIM, n);
            j.view_mut((0, DIM * e.from), (DIM, DIM)).copy_from(&lin.d_from);
            j.view_mut((0, DIM * e.to), (DIM, DIM)).copy_from(&lin.d_to);
            let omega = DMatrix::from_column_slice(DIM, DIM, e.information.as_slice());
            h += j.transpose() * &omega * &j;
            b += j.transpose() * &omega * DVector::from_column_slice(lin.error.as_slice());
        }
        (h.view((DIM, DIM), (n - DIM, n - DIM)).into_owned(), b.rows(DIM, n - DIM).into_owned())
    }

    #[test]
    fn assembled_blocks_land_where_the_dense_sum_has_them() {
        let mut rng = Rng::xorshift64_star(Rng::spread(4));
        let (poses, edges, fixed) = small_graph(&mut rng);
        let pattern = Pattern::new(&fixed, &edges);
        let mut eq = NormalEquations::new(&pattern, edges.len());
        eq.assemble(&pattern, &poses, &edges, &crate::pose_graph::PoseGraphConfig::least_squares());
        let (h, b) = brute_force(&poses, &edges);
        let n = pattern.unknowns();
        let mut lower = DMatrix::zeros(n, n);
        let (col_ptr, row_idx) = (pattern.symbolic.col_ptr(), pattern.symbolic.row_idx());
        for c in 0..n {
            for k in col_ptr[c]..col_ptr[c + 1] {
                lower[(row_idx[k], c)] = eq.h[k];
            }
        }
        let full = &lower + lower.transpose() - DMatrix::from_diagonal(&lower.diagonal());
        assert!((&full - &h).amax() < 1e-9 * h.amax(), "H\n{full}\nvs dense\n{h}");
        assert!((DVector::from_column_slice(&eq.b) - &b).amax() < 1e-9 * b.amax());
        // The sparse solve agrees with a dense one.
        let mut x: Vec<f64> = b.iter().map(|v| -v).collect();
        assert!(Factoriser::new(&pattern).unwrap().solve(pattern.matrix(&eq.h), &mut x).unwrap());
        let dense = h.cholesky().unwrap().solve(&-&b);
        assert!((DVector::from_column_slice(&x) - &dense).amax() < 1e-9 * dense.amax());
    }
}
