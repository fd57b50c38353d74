"""Shared steps of the sequential global line extractors (ransac, hough), numba helpers.

Both find one line at a time among the points still *alive* (not yet taken),
then: refit it by total least squares on its inliers (points within their
threshold ``thr[i]``, m, of the line), twice; take every run of consecutive
inliers (consecutive valid points, no jump over ``max_gap``) with at least
``min_len`` points as a segment and remove those points. Inliers in shorter
runs stay alive: on a line through a corner or across another wall they
belong to that other wall, and removing them would punch holes in it.

The steps work on the alive points packed in scan order (``Alive``: their
coordinates, thresholds and original indices, first ``q`` entries valid):
dead points are never inliers, so skipping them changes no sum and no test,
and the contiguous arrays let the distance tests vectorise. ``inl`` flags are
per packed entry.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from segmentation.methods._incremental import moments_add, moments_line

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@nb.njit(cache=True)
def pack_alive(points: FloatArray, thr: FloatArray, alive: BoolArray, xs: FloatArray, ys: FloatArray,
               ts: FloatArray, idx: IntArray) -> int:
    """Pack the alive points (scan order) into xs, ys, ts (threshold) and idx (index); how many."""
    q = 0
    for i in range(points.shape[0]):
        if alive[i]:
            xs[q] = points[i, 0]
            ys[q] = points[i, 1]
            ts[q] = thr[i]
            idx[q] = i
            q += 1
    return q


@nb.njit(cache=True)
def mark_inliers(xs: FloatArray, ys: FloatArray, ts: FloatArray, q: int, cx: float, cy: float, nx: float,
                 ny: float, inl: BoolArray) -> int:
    """Set ``inl[t]`` for the packed points within ``ts[t]`` of the line (point on it, unit normal); count them."""
    count = 0
    for t in range(q):
        ok = abs((xs[t] - cx) * nx + (ys[t] - cy) * ny) <= ts[t]
        inl[t] = ok
        count += ok
    return count


@nb.njit(cache=True)
def refine_line(xs: FloatArray, ys: FloatArray, ts: FloatArray, q: int, inl: BoolArray, n_refits: int) -> int:
    """Refit the TLS line of the current inliers ``n_refits`` times, updating ``inl``; the final count."""
    count = 0
    for t in range(q):
        count += inl[t]
    mom = np.zeros(8)
    for _ in range(n_refits):
        if count < 2:
            break
        mom[0] = 0.0  # empty state: the next point added becomes the local origin
        mom[1:6] = 0.0
        for t in range(q):
            if inl[t]:
                moments_add(mom, xs[t], ys[t], 1.0)
        cx, cy, nx, ny = moments_line(mom)
        count = mark_inliers(xs, ys, ts, q, cx, cy, nx, ny, inl)
    return count


@nb.njit(cache=True)
def take_runs(xs: FloatArray, ys: FloatArray, idx: IntArray, q: int, inl: BoolArray, alive: BoolArray,
              labels: IntArray, seg: int, min_len: int, max_gap: float) -> tuple[int, int]:
    """Label every run of >= ``min_len`` consecutive inliers with a new id from ``seg`` on and kill its points.

    A run follows consecutive points of the scan (consecutive indices) with no step
    over ``max_gap``. Returns (next free id, number of points taken).
    """
    g2 = max_gap * max_gap
    taken = 0
    t = 0
    while t < q:
        if not inl[t]:
            t += 1
            continue
        u = t
        while u + 1 < q and inl[u + 1] and idx[u + 1] == idx[u] + 1:
            dx = xs[u + 1] - xs[u]
            dy = ys[u + 1] - ys[u]
            if dx * dx + dy * dy > g2:
                break
            u += 1
        if u - t + 1 >= min_len:
            for v in range(t, u + 1):
                labels[idx[v]] = seg
                alive[idx[v]] = False
            seg += 1
            taken += u - t + 1
        t = u + 1
    return seg, taken


@nb.njit(cache=True)
def discard_inliers(idx: IntArray, q: int, inl: BoolArray, alive: BoolArray) -> int:
    """Kill the inliers still alive without labelling them (a line whose inliers form no long run); how many."""
    n = 0
    for t in range(q):
        if inl[t] and alive[idx[t]]:
            alive[idx[t]] = False
            n += 1
    return n


@nb.njit(cache=True)
def can_take_more(alive: BoolArray, step_ok: BoolArray, min_len: int) -> bool:
    """Whether some ``min_len`` consecutive points are all alive with no step over ``max_gap``.

    ``step_ok[i]``: point i is within ``max_gap`` of point i - 1 (``gaps_ok``).
    Every run ``take_runs`` can take is such a stretch, so when none is left
    no further segment can be found and the extraction may stop: the labels
    are those it would end with anyway.
    """
    run = 0
    for i in range(alive.shape[0]):
        if not alive[i]:
            run = 0
            continue
        run = run + 1 if run > 0 and step_ok[i] else 1
        if run >= min_len:
            return True
    return False
