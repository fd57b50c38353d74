"""Recursive splitting of scanline point runs into line intervals (numba helpers for iepf, split_and_merge).

Points are the valid points of one scanline in scan order, scanner frame;
``thr[i]`` is point i's distance threshold (m, already scaled by the noise
model). Distances are compared as ratios ``d_i / thr[i]``, so with constant
noise "farthest point" has its usual meaning.

Conventions shared by both methods:

* The scanline is first cut into *chunks* at depth jumps (consecutive points
  more than ``max_gap`` apart), as breakpoint detection before splitting does
  in the literature (Borges and Aldon 2004); a chord or a fit across a jump
  means nothing.
* A split at point k turns interval [a, b] into [a, k] and [k, b]: the split
  point is shared, as in Duda and Hart's IEPF. Intervals with fewer than
  ``max(3, min_len)`` points are not split further (they are too short to be
  kept).
* ``assign_labels`` gives every shared point to one neighbour: the one whose
  line (fitted to its other points) it is nearer to, or the only neighbour
  long enough to be kept. A shared point farther than its threshold from the
  chosen line (a mixed pixel at a step) is left unsegmented.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from segmentation.methods._incremental import moments_line, moments_of, point_line_distance

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@nb.njit(cache=True)
def gap_chunks(points: FloatArray, max_gap: float) -> tuple[IntArray, IntArray]:
    """(first, last) point index of every maximal run without a jump > ``max_gap``."""
    m = points.shape[0]
    first = np.empty(m, dtype=np.int64)
    last = np.empty(m, dtype=np.int64)
    g2 = max_gap * max_gap
    k = 0
    first[0] = 0
    for i in range(1, m):
        dx = points[i, 0] - points[i - 1, 0]
        dy = points[i, 1] - points[i - 1, 1]
        if dx * dx + dy * dy > g2:
            last[k] = i - 1
            k += 1
            first[k] = i
    last[k] = m - 1
    return first[: k + 1].copy(), last[: k + 1].copy()


@nb.njit(cache=True)
def chord_farthest(points: FloatArray, thr: FloatArray, a: int, b: int) -> tuple[int, float]:
    """Interior point of [a, b] farthest from the chord p_a p_b, and its distance / threshold."""
    ax = points[a, 0]
    ay = points[a, 1]
    ex = points[b, 0] - ax
    ey = points[b, 1] - ay
    ln = np.sqrt(ex * ex + ey * ey)
    k = a + 1
    best = -1.0
    for i in range(a + 1, b):
        dx = points[i, 0] - ax
        dy = points[i, 1] - ay
        if ln > 0.0:
            d = abs(dx * ey - dy * ex) / ln
        else:
            d = np.sqrt(dx * dx + dy * dy)
        ratio = d / thr[i]
        if ratio > best:
            best = ratio
            k = i
    return k, best


@nb.njit(cache=True)
def tls_farthest(points: FloatArray, thr: FloatArray, a: int, b: int) -> tuple[int, float]:
    """Point of [a, b] farthest from the interval's total-least-squares line, and its distance / threshold."""
    cx, cy, nx, ny = moments_line(moments_of(points, a, b))
    k = a
    best = -1.0
    for i in range(a, b + 1):
        ratio = point_line_distance(points[i, 0], points[i, 1], cx, cy, nx, ny) / thr[i]
        if ratio > best:
            best = ratio
            k = i
    return k, best


@nb.njit(cache=True)
def _tls_ratio(points: FloatArray, thr: FloatArray, a: int, b: int, p: int) -> float:
    """Distance / threshold of point p to the TLS line of points a..b."""
    cx, cy, nx, ny = moments_line(moments_of(points, a, b))
    return point_line_distance(points[p, 0], points[p, 1], cx, cy, nx, ny) / thr[p]


@nb.njit(cache=True)
def split_intervals(points: FloatArray, thr: FloatArray, max_gap: float, min_len: int,
                    tls: bool) -> tuple[IntArray, IntArray]:
    """Leaf intervals (first, last; consecutive leaves of a chunk share their boundary point), in scan order.

    ``tls=False``: IEPF, the farthest point from the chord decides and is the
    split point. ``tls=True``: the farthest point from the TLS line decides;
    it is the split point unless it lies within two points of an end, where a
    split would only peel points off one by one. There, an end point whose
    neighbour fits the line is an outlier and is split off alone; otherwise
    (typically a short second wall at the end pulling the fit, so that its
    far end is farthest) the interval is split at the farthest point from its
    chord, the IEPF rule, which finds the corner.
    """
    m = points.shape[0]
    c_first, c_last = gap_chunks(points, max_gap)
    out_a = np.empty(2 * m + 2, dtype=np.int64)
    out_b = np.empty(2 * m + 2, dtype=np.int64)
    stack_a = np.empty(2 * m + 2, dtype=np.int64)
    stack_b = np.empty(2 * m + 2, dtype=np.int64)
    n_out = 0
    min_split = max(3, min_len)
    for c in range(c_first.shape[0]):
        if c_last[c] - c_first[c] + 1 < min_len:
            continue
        stack_a[0] = c_first[c]
        stack_b[0] = c_last[c]
        top = 1
        while top > 0:
            top -= 1
            a = stack_a[top]
            b = stack_b[top]
            split = False
            k = a
            if b - a + 1 >= min_split:
                if tls:
                    k, ratio = tls_farthest(points, thr, a, b)
                    if ratio > 1.0:
                        split = True
                        if k == b and _tls_ratio(points, thr, a, b, b - 1) <= 1.0:
                            k = b - 1
                        elif k == a and _tls_ratio(points, thr, a, b, a + 1) <= 1.0:
                            k = a + 1
                        elif k - a < 2 or b - k < 2:
                            k, _ = chord_farthest(points, thr, a, b)
                else:
                    k, ratio = chord_farthest(points, thr, a, b)
                    split = ratio > 1.0
            if split:
                # right part first on the stack so the left part is handled first: leaves come out in order
                stack_a[top] = k
                stack_b[top] = b
                stack_a[top + 1] = a
                stack_b[top + 1] = k
                top += 2
            else:
                out_a[n_out] = a
                out_b[n_out] = b
                n_out += 1
    return out_a[:n_out].copy(), out_b[:n_out].copy()


@nb.njit(cache=True)
def _distance_to_fit(points: FloatArray, a: int, b: int, p: int) -> float:
    """Distance of point p to the TLS line of points a..b (inf if fewer than two)."""
    if b - a + 1 < 2:
        return np.inf
    cx, cy, nx, ny = moments_line(moments_of(points, a, b))
    return point_line_distance(points[p, 0], points[p, 1], cx, cy, nx, ny)


@nb.njit(cache=True)
def assign_labels(points: FloatArray, thr: FloatArray, first: IntArray, last: IntArray,
                  min_len: int) -> IntArray:
    """Raw labels from leaf intervals (in scan order, neighbours possibly sharing a point).

    Leaf j gets id j; leaves shorter than ``min_len`` get no points. A point
    shared by leaves j-1 and j goes as described in the module docstring.
    """
    m = points.shape[0]
    labels = np.full(m, -1, dtype=np.int64)
    q = first.shape[0]
    for j in range(q):
        a = first[j]
        b = last[j]
        if b - a + 1 < min_len:
            continue
        for i in range(a + 1, b):
            labels[i] = j
        # ends not shared with a neighbour belong to this leaf
        if j == 0 or last[j - 1] != a:
            labels[a] = j
        if j == q - 1 or first[j + 1] != b:
            labels[b] = j
    for j in range(1, q):
        p = first[j]
        if last[j - 1] != p:
            continue
        keep_l = last[j - 1] - first[j - 1] + 1 >= min_len
        keep_r = last[j] - first[j] + 1 >= min_len
        if not keep_l and not keep_r:
            continue
        d_l = _distance_to_fit(points, first[j - 1], p - 1, p) if keep_l else np.inf
        d_r = _distance_to_fit(points, p + 1, last[j], p) if keep_r else np.inf
        if d_l <= d_r:
            if d_l <= thr[p]:
                labels[p] = j - 1
        elif d_r <= thr[p]:
            labels[p] = j
    return labels
