"""Position predictors of the EMR cloud codec, inverted: residual streams back to quantised points.

The arithmetic repeats proto/src/codec/predict.rs bit for bit: every operation on quantised values
wraps modulo 2^32, slopes are rounded to nearest even, and the scan predictor's ray correction is
an exact integer floor. Arrays hold the int32 values widened to int64 so that wrapping is explicit
(``wrap``) rather than left to numpy's overflow rules.

The delta predictor is a cumulative sum. The scan predictor is a nonlinear recurrence (each point's
dominant axis and ray slopes come from the exact point two back) that no cumulative sum expresses:
it runs as a tight loop on Python ints, see ``reconstruct_scan``.
"""

from __future__ import annotations

import numpy as np

MASK32 = 0xFFFFFFFF
HALF32 = 1 << 31
SLOPE_ONE = 1 << 16
DELTA = 0
SCAN = 1
PREDICTORS = {DELTA: "delta", SCAN: "scan"}
# Points the scan loops decode per batch: bounds the Python lists they build (about 100 bytes a point).
SCAN_BATCH = 1 << 16


def unzigzag(u: np.ndarray) -> np.ndarray:
    """Residuals (int64 holding int32 values) from zigzag codes (uint32): 0, 1, 2, 3 -> 0, -1, 1, -2."""
    u = u.astype(np.uint32, copy=False)
    return ((u >> np.uint32(1)) ^ (np.uint32(0) - (u & np.uint32(1)))).view(np.int32).astype(np.int64)


def wrap(v: np.ndarray) -> np.ndarray:
    """Integers reduced modulo 2^32 into the int32 range, as Rust's wrapping arithmetic leaves them."""
    return ((v + HALF32) & MASK32) - HALF32


def reconstruct(residuals: np.ndarray, predictor: int) -> np.ndarray:
    """Quantised points (n x 3, int64 holding int32) from the three residual streams (3 x n)."""
    if predictor == DELTA:
        return reconstruct_delta(residuals)
    if predictor == SCAN:
        return reconstruct_scan(residuals)
    raise ValueError(f"unknown predictor {predictor}")


def reconstruct_delta(residuals: np.ndarray) -> np.ndarray:
    """Each axis is the running sum of its residuals (the previous point plus the residual)."""
    return wrap(np.cumsum(residuals.T & MASK32, axis=0))


# --- the scan predictor, one point at a time (the reference, and the fallback) -------------------


def _wrap_int(v: int) -> int:
    return ((v + HALF32) & MASK32) - HALF32


def _dominant(b) -> int:
    """Axis of largest |b|, the lowest on ties (x before y before z)."""
    m0, m1, m2 = abs(b[0]), abs(b[1]), abs(b[2])
    if m0 >= m1 and m0 >= m2:
        return 0
    return 1 if m1 >= m2 else 2


def _slope(v: int, vd: int) -> int:
    """``v * 2^16 / vd`` rounded to nearest even, computed in f64 as the encoder does (exact)."""
    return round(float(v) * float(SLOPE_ONE) / float(vd if vd != 0 else 1))


def scan_point(r, a, b) -> list:
    """One point from its residuals ``r`` (stream order) after points ``a`` (last) and ``b``."""
    d = _dominant(b)
    m1, m2 = (d + 1) % 3, (d + 2) % 3
    p = [0, 0, 0]
    p[d] = _wrap_int(a[d] + r[0])
    s = p[d] - _wrap_int(2 * a[d] - b[d])
    p[m1] = _wrap_int(2 * a[m1] - b[m1] + ((s * _slope(b[m1], b[d]) + SLOPE_ONE // 2) >> 16) + r[1])
    p[m2] = _wrap_int(2 * a[m2] - b[m2] + ((s * _slope(b[m2], b[d]) + SLOPE_ONE // 2) >> 16) + r[2])
    return p


def scan_sequential(residuals: np.ndarray, points: np.ndarray, start: int) -> None:
    """Fills ``points[start:]`` one point at a time with wrapping arithmetic, in batches;
    ``points[:start]`` must already be exact."""
    n = points.shape[0]
    a = points[start - 1].tolist() if start >= 1 else [0, 0, 0]
    b = points[start - 2].tolist() if start >= 2 else a
    for begin in range(start, n, SCAN_BATCH):
        out = []
        for i, r in enumerate(residuals[:, begin : begin + SCAN_BATCH].T.tolist(), begin):
            p = scan_point(r, a, b)
            out.append(p)
            a, b = p, (p if i == 0 else a)
        points[begin : begin + len(out)] = np.array(out, dtype=np.int64).reshape(-1, 3)


# --- the scan predictor, fast ----------------------------------------------------------------------


def reconstruct_scan(residuals: np.ndarray) -> np.ndarray:
    """Quantised points of a scan-predicted cloud (3 x n residuals in, n x 3 points out).

    Why a Python loop: each point's dominant axis and ray slopes come from the exact point two
    back, and a slope off by one unit flips the rounded correction within a few dozen points on
    real scans, so no cumulative-sum reformulation or fixed-point iteration converges faster than
    going point by point. The loop runs on plain ints without wrapping (a fifth of the work of
    ``scan_point``); ints that wrap in the encoder's arithmetic are detected afterwards, and only
    then is the cloud decoded again with wrapping.
    """
    n = residuals.shape[1]
    points = np.empty((n, 3), dtype=np.int64)
    state = (0, 0, 0, 0, 0, 0)
    for begin in range(0, n, SCAN_BATCH):
        end = min(n, begin + SCAN_BATCH)
        xs, ys, zs, state = _scan_unwrapped(*(r.tolist() for r in residuals[:, begin:end]), state, begin == 0)
        points[begin:end] = np.array([xs, ys, zs], dtype=np.int64).T
        if not _within_i32(points[max(0, begin - 2) : end]):
            # Everything before this batch is exact; from here on, wrap every operation.
            scan_sequential(residuals, points, begin)
            break
    return points


def _within_i32(points: np.ndarray) -> bool:
    """True when no point and no extrapolation ``2a - b`` leaves the int32 range, so that the
    unwrapped loop computed exactly what the wrapping arithmetic does."""
    if points.size == 0:
        return True
    lo, hi = -HALF32, HALF32 - 1
    lin = 2 * points[1:-1] - points[:-2]
    in_range = lambda v: v.size == 0 or (v.min() >= lo and v.max() <= hi)  # noqa: E731
    return in_range(points) and in_range(lin)


def _scan_unwrapped(r0s: list, r1s: list, r2s: list, state: tuple, first: bool):
    """The scan recurrence on Python ints, one branch per dominant axis, ``scan_point`` inlined.

    ``state`` holds the previous point ``a`` and the one before ``b`` (ax, ay, az, bx, by, bz);
    returns the three coordinate lists and the state after the last point. ``round`` of a float is
    round-half-even, and ``v * 65536.0 / div`` the same two f64 operations as the encoder's.
    """
    n = len(r0s)
    xs, ys, zs = [0] * n, [0] * n, [0] * n
    ax, ay, az, bx, by, bz = state
    for i in range(n):
        r0, r1, r2 = r0s[i], r1s[i], r2s[i]
        mx = -bx if bx < 0 else bx
        my = -by if by < 0 else by
        mz = -bz if bz < 0 else bz
        if mx >= my and mx >= mz:
            div = bx or 1
            px = ax + r0
            s = r0 - ax + bx
            py = 2 * ay - by + ((s * round(by * 65536.0 / div) + 32768) >> 16) + r1
            pz = 2 * az - bz + ((s * round(bz * 65536.0 / div) + 32768) >> 16) + r2
        elif my >= mz:
            div = by or 1
            py = ay + r0
            s = r0 - ay + by
            pz = 2 * az - bz + ((s * round(bz * 65536.0 / div) + 32768) >> 16) + r1
            px = 2 * ax - bx + ((s * round(bx * 65536.0 / div) + 32768) >> 16) + r2
        else:
            div = bz or 1
            pz = az + r0
            s = r0 - az + bz
            px = 2 * ax - bx + ((s * round(bx * 65536.0 / div) + 32768) >> 16) + r1
            py = 2 * ay - by + ((s * round(by * 65536.0 / div) + 32768) >> 16) + r2
        xs[i], ys[i], zs[i] = px, py, pz
        if first:
            # b = a for the first two points.
            ax, ay, az, first = px, py, pz, False
        bx, by, bz, ax, ay, az = ax, ay, az, px, py, pz
    return xs, ys, zs, (ax, ay, az, bx, by, bz)
