//! Position predictors: quantised points to residual streams and back.
//!
//! Every operation on quantised values wraps (two's complement), so any residual stream decodes to
//! some points and the encoder needs no overflow cases. See the module doc of `codec` for the
//! exact arithmetic, which a decoder in another language has to repeat bit for bit.
//!
//! The per-point functions are `#[inline(always)]`: left to itself, LLVM outlined them and
//! passed the points through memory, which made decoding 3x slower.

use std::ops::Range;

/// How xyz residuals are formed (header byte 6).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Predictor {
    /// Per-axis difference to the previous point: streams x, y, z.
    Delta = 0,
    /// Scan order seen from the origin: dominant axis from the previous point, the two others by
    /// linear extrapolation corrected along the ray.
    Scan = 1,
}

impl Predictor {
    /// The predictor stored as `byte`, if known.
    pub(crate) fn from_byte(byte: u8) -> Option<Self> {
        match byte {
            0 => Some(Self::Delta),
            1 => Some(Self::Scan),
            _ => None,
        }
    }
}

/// Fixed-point scale of the ray slopes.
const SLOPE_ONE: i64 = 1 << 16;

/// Zigzag-coded residuals of quantised points under `predictor`, one triple per point: entry
/// `k` of every triple makes stream `k`.
pub(crate) fn residuals(points: impl ExactSizeIterator<Item = [i32; 3]>, predictor: Predictor) -> Vec<[u32; 3]> {
    match predictor {
        Predictor::Delta => residuals_with(points, |p, a, _| std::array::from_fn(|k| p[k].wrapping_sub(a[k]))),
        Predictor::Scan => residuals_with(points, scan_residual),
    }
}

/// Rebuilds the points from their residuals (inverse of [`residuals`]), replacing each
/// point's residuals by `store(point)`.
pub(crate) fn reconstruct_in_place(slots: &mut [[u32; 3]], predictor: Predictor, store: impl Fn([i32; 3]) -> [u32; 3]) {
    match predictor {
        Predictor::Delta => reconstruct_with(slots, |r, a, _| std::array::from_fn(|k| a[k].wrapping_add(r[k])), store),
        Predictor::Scan => reconstruct_with(slots, scan_point, store),
    }
}

/// Residuals of each point `p` given by `residual(p, a, b)`, where `a` is the previous point
/// (zero before the first) and `b` the one before it (`b = a` for the first two points).
#[inline(always)]
fn residuals_with(
    points: impl ExactSizeIterator<Item = [i32; 3]>,
    residual: impl Fn([i32; 3], [i32; 3], [i32; 3]) -> [i32; 3],
) -> Vec<[u32; 3]> {
    // A plain loop keeps `a` and `b` in registers; captured by a closure they went through
    // memory, and loads spanning two stores stalled every point.
    let mut out = Vec::with_capacity(points.len());
    let (mut a, mut b) = ([0; 3], [0; 3]);
    for (i, p) in points.enumerate() {
        out.push(residual(p, a, b).map(zigzag));
        (a, b) = (p, if i == 0 { p } else { a });
    }
    out
}

/// Inverse of [`residuals_with`]: `point(r, a, b)` rebuilds a point from its residuals `r`.
#[inline(always)]
fn reconstruct_with(
    slots: &mut [[u32; 3]],
    point: impl Fn([i32; 3], [i32; 3], [i32; 3]) -> [i32; 3],
    store: impl Fn([i32; 3]) -> [u32; 3],
) {
    let (mut a, mut b) = ([0; 3], [0; 3]);
    for (i, slot) in slots.iter_mut().enumerate() {
        let p = point(slot.map(unzigzag), a, b);
        *slot = store(p);
        (a, b) = (p, if i == 0 { p } else { a });
    }
}

/// Axis of largest |b| (the lowest on ties): the one that carries most of a range change.
#[inline(always)]
fn dominant_axis(b: [i32; 3]) -> usize {
    let m = b.map(i32::unsigned_abs);
    if m[0] >= m[1] && m[0] >= m[2] {
        0
    } else if m[1] >= m[2] {
        1
    } else {
        2
    }
}

/// `v` with axis `d` first and the two others after it in cyclic order (the stream order).
#[inline(always)]
fn rotate(v: [i32; 3], d: usize) -> [i32; 3] {
    match d {
        0 => v,
        1 => [v[1], v[2], v[0]],
        _ => [v[2], v[0], v[1]],
    }
}

/// Inverse of [`rotate`].
#[inline(always)]
fn unrotate(v: [i32; 3], d: usize) -> [i32; 3] {
    match d {
        0 => v,
        1 => [v[2], v[0], v[1]],
        _ => [v[1], v[2], v[0]],
    }
}

/// What the scan predictor expects from the two previous points `a` (last) and `b`, both
/// rotated so that the dominant axis comes first.
struct ScanGuess {
    /// Linear extrapolation `2a - b`.
    lin: [i32; 3],
    /// Slopes of the ray through `b` on the minor axes, `b[k] / b[0]` in units of 1/`SLOPE_ONE`.
    /// The ray is taken through `b` rather than `a` so that the divisions do not wait for the
    /// previous point: decoding is a dependency chain, and this keeps them off it.
    slopes: [i32; 2],
}

impl ScanGuess {
    #[inline(always)]
    fn new(a: [i32; 3], b: [i32; 3]) -> Self {
        let lin = std::array::from_fn(|k| a[k].wrapping_mul(2).wrapping_sub(b[k]));
        Self { lin, slopes: [slope(b[1], b[0]), slope(b[2], b[0])] }
    }

    /// Guess for minor axis `k` (1 or 2) once the dominant coordinate `q0` is known: a LiDAR's
    /// noise and surface changes move a point along its ray, so the dominant axis' surprise is
    /// carried onto the minor axis with the ray's slope.
    #[inline(always)]
    fn minor(&self, q0: i32, k: usize) -> i32 {
        // |shift| <= 2^32 and |slope| <= 2^16: the product cannot overflow.
        let shift = i64::from(q0) - i64::from(self.lin[0]);
        let offset = (shift * i64::from(self.slopes[k - 1]) + SLOPE_ONE / 2) >> 16;
        self.lin[k].wrapping_add(offset as i32)
    }
}

/// Scan residuals of point `p` after `a` and `b`: the dominant axis first, then the minors.
#[inline(always)]
fn scan_residual(p: [i32; 3], a: [i32; 3], b: [i32; 3]) -> [i32; 3] {
    let d = dominant_axis(b);
    let (p, a, b) = (rotate(p, d), rotate(a, d), rotate(b, d));
    let g = ScanGuess::new(a, b);
    // Range noise makes the previous point a better guess than the extrapolation on this axis.
    [p[0].wrapping_sub(a[0]), p[1].wrapping_sub(g.minor(p[0], 1)), p[2].wrapping_sub(g.minor(p[0], 2))]
}

/// Inverse of [`scan_residual`].
#[inline(always)]
fn scan_point(r: [i32; 3], a: [i32; 3], b: [i32; 3]) -> [i32; 3] {
    let d = dominant_axis(b);
    let (a, b) = (rotate(a, d), rotate(b, d));
    let g = ScanGuess::new(a, b);
    let p0 = a[0].wrapping_add(r[0]);
    unrotate([p0, g.minor(p0, 1).wrapping_add(r[1]), g.minor(p0, 2).wrapping_add(r[2])], d)
}

/// `v * SLOPE_ONE / vd` rounded to the nearest integer, ties to even; 0 when `vd` is 0. Needs
/// |v| <= |vd|.
///
/// f64 gives the exactly rounded result the format demands, much faster than an i64 division:
/// the numerator is exact (< 2^48) and the quotient (|q| <= 2^16) off by at most 2^-37, while a
/// quotient that is not exactly a half-integer lies at least 1 / (2|vd|) >= 2^-32 from one, so
/// rounding never goes the other way.
#[inline(always)]
fn slope(v: i32, vd: i32) -> i32 {
    let divisor = if vd == 0 { 1 } else { vd };
    round_to_i32(f64::from(v) * SLOPE_ONE as f64 / f64::from(divisor))
}

/// `x` rounded to the nearest integer, ties to even; needs |x| < 2^31.
///
/// Adding 1.5 * 2^52 leaves no fraction bits, so the FPU rounds (to nearest even) and the
/// integer sits in the low bits: no libm call (`f64::round` is one on baseline x86-64) and no
/// saturating conversion.
#[inline(always)]
pub(crate) fn round_to_i32(x: f64) -> i32 {
    const ROUNDER: f64 = 6_755_399_441_055_744.0;
    (x + ROUNDER).to_bits() as i32
}

/// Maps small magnitudes of either sign to small codes: 0, -1, 1, -2 -> 0, 1, 2, 3.
pub(crate) fn zigzag(v: i32) -> u32 {
    ((v << 1) ^ (v >> 31)) as u32
}

/// Inverse of [`zigzag`].
pub(crate) fn unzigzag(u: u32) -> i32 {
    ((u >> 1) as i32) ^ -((u & 1) as i32)
}

/// The predictor that codes a cloud of `n` points smaller, judged by residual bit lengths on a
/// sample of windows; `window(range)` yields the quantised points in `range`.
pub(crate) fn choose<I: ExactSizeIterator<Item = [i32; 3]>>(n: usize, window: impl Fn(Range<usize>) -> I) -> Predictor {
    let cost = |predictor| -> u64 {
        sample_windows(n)
            .flat_map(|w| residuals(window(w), predictor))
            .flatten()
            .map(|r| u64::from(32 - r.leading_zeros()))
            .sum()
    };
    if cost(Predictor::Scan) < cost(Predictor::Delta) { Predictor::Scan } else { Predictor::Delta }
}

/// Up to 32 evenly spread ranges of 256 consecutive indices in `0..n`.
fn sample_windows(n: usize) -> impl Iterator<Item = Range<usize>> {
    const WINDOW: usize = 256;
    let stride = (n / 32).max(WINDOW);
    (0..n).step_by(stride).map(move |s| s..(s + WINDOW).min(n))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(q: &[[i32; 3]], predictor: Predictor) -> Vec<[i32; 3]> {
        let mut slots = residuals(q.iter().copied(), predictor);
        reconstruct_in_place(&mut slots, predictor, |p| p.map(|v| v as u32));
        slots.into_iter().map(|p| p.map(|v| v as i32)).collect()
    }

    #[test]
    fn both_predictors_invert_on_extreme_values() {
        let edge = [i32::MIN, i32::MAX, 0, -1, 1, 1 << 20, -(1 << 30)];
        let mut q = Vec::new();
        for &x in &edge {
            for &y in &edge {
                for &z in &edge {
                    q.push([x, y, z]);
                }
            }
        }
        for predictor in [Predictor::Delta, Predictor::Scan] {
            assert_eq!(round_trip(&q, predictor), q, "{predictor:?}");
        }
    }

    #[test]
    fn scan_predictor_follows_a_ring() {
        // A ring of radius 20 m at 1 mm with 3 mm range noise: after the first points the minor
        // axes should be nearly free, the dominant axis carry the noise.
        let mut rng = testkit::Rng::new(0x2545_f491_4f6c_dd1d);
        let q: Vec<[i32; 3]> = (0..2000)
            .map(|i| {
                let r = 20_000.0 + (rng.next_u64() % 7) as f64 - 3.0;
                let a = i as f64 * 0.003;
                [(r * a.cos()).round() as i32, (r * a.sin()).round() as i32, -1700]
            })
            .collect();
        assert_eq!(round_trip(&q, Predictor::Scan), q);
        let res = residuals(q.iter().copied(), Predictor::Scan);
        let mean = |k: usize| res[2..].iter().map(|r| f64::from(unzigzag(r[k]).abs())).sum::<f64>() / res.len() as f64;
        assert!(mean(1) < 1.5 && mean(2) < 1.5, "{} {}", mean(1), mean(2));
        assert_eq!(choose(q.len(), |w| q[w].iter().copied()), Predictor::Scan);
    }

    #[test]
    fn slope_rounds_to_nearest_even() {
        assert_eq!(slope(1, 2), 1 << 15);
        assert_eq!(slope(-3, 3), -(1 << 16));
        assert_eq!(slope(1, 3), 21845); // 21845.33
        assert_eq!(slope(2, -3), -43691); // -43690.67
        assert_eq!(slope(1, 1 << 17), 0); // exactly 0.5
        assert_eq!(slope(3, 1 << 17), 2); // exactly 1.5
        assert_eq!(slope(-3, 1 << 17), -2);
        assert_eq!(slope(i32::MIN, i32::MIN), 1 << 16);
        assert_eq!(slope(0, 0), 0);
        assert_eq!(
            [2.5, -2.5, 3.5, 2.4999, -0.5, 1e9 + 0.6, -2147483647.0].map(round_to_i32),
            [2, -2, 4, 2, 0, 1_000_000_001, -2147483647]
        );
    }

    #[test]
    fn slope_matches_exact_rational_rounding() {
        // The f64 shortcut against integer arithmetic, on divisors with awkward odd factors.
        let mut rng = testkit::Rng::new(0x9e37_79b9_7f4a_7c15);
        for _ in 0..100_000 {
            let seed = rng.next_u64();
            let vd = (seed as i32) >> (seed >> 59);
            let v = ((seed >> 32) as i32 >> (seed >> 59)).clamp(-vd.saturating_abs(), vd.saturating_abs());
            if vd == 0 {
                continue;
            }
            let (n, d) = (i128::from(v) << 16, i128::from(vd));
            let (n, d) = if d < 0 { (-n, -d) } else { (n, d) };
            let floor = n.div_euclid(d);
            let twice_rest = 2 * n.rem_euclid(d);
            let exact = if twice_rest > d || (twice_rest == d && floor % 2 != 0) { floor + 1 } else { floor };
            assert_eq!(i128::from(slope(v, vd)), exact, "{v} / {vd}");
        }
    }

    #[test]
    fn zigzag_inverts() {
        for v in [0, 1, -1, 2, -2, i32::MAX, i32::MIN] {
            assert_eq!(unzigzag(zigzag(v)), v);
        }
        assert_eq!([0, -1, 1, -2].map(zigzag), [0, 1, 2, 3]);
    }
}
