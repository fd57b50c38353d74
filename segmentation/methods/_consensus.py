"""Shared steps of the sequential global line extractors (ransac, hough), numba helpers.

Both find one line at a time among the points still *alive* (not yet taken),
then: refit it by total least squares on its inliers (points within their
threshold ``thr[i]``, m, of the line), twice; take every run of consecutive
inliers (consecutive valid points, no jump over ``max_gap``) with at least
``min_len`` points as a segment and remove those points. Inliers in shorter
runs stay alive: on a line through a corner or across another wall they
belong to that other wall, and removing them would punch holes in it.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from segmentation.methods._incremental import moments_add, moments_line, moments_of

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@nb.njit(cache=True)
def mark_inliers(points: FloatArray, thr: FloatArray, alive: BoolArray, cx: float, cy: float,
                 nx: float, ny: float, inl: BoolArray) -> int:
    """Set ``inl[i]`` for alive points within ``thr[i]`` of the line (centroid, unit normal); count them."""
    count = 0
    for i in range(points.shape[0]):
        ok = alive[i] and abs((points[i, 0] - cx) * nx + (points[i, 1] - cy) * ny) <= thr[i]
        inl[i] = ok
        if ok:
            count += 1
    return count


@nb.njit(cache=True)
def refine_line(points: FloatArray, thr: FloatArray, alive: BoolArray, inl: BoolArray,
                n_refits: int) -> int:
    """Refit the TLS line of the current inliers ``n_refits`` times, updating ``inl``; the final count."""
    count = 0
    for i in range(inl.shape[0]):
        if inl[i]:
            count += 1
    for _ in range(n_refits):
        if count < 2:
            break
        mom = moments_of(points, 0, -1)  # empty state (the range 0..-1 holds no point)
        for i in range(points.shape[0]):
            if inl[i]:
                moments_add(mom, points[i, 0], points[i, 1], 1.0)
        cx, cy, nx, ny = moments_line(mom)
        count = mark_inliers(points, thr, alive, cx, cy, nx, ny, inl)
    return count


@nb.njit(cache=True)
def take_runs(points: FloatArray, inl: BoolArray, alive: BoolArray, labels: IntArray, seg: int,
              min_len: int, max_gap: float) -> tuple[int, int]:
    """Label every run of >= ``min_len`` consecutive inliers with a new id from ``seg`` on and kill its points.

    Returns (next free id, number of points taken).
    """
    m = points.shape[0]
    g2 = max_gap * max_gap
    taken = 0
    i = 0
    while i < m:
        if not inl[i]:
            i += 1
            continue
        j = i
        while j + 1 < m and inl[j + 1]:
            dx = points[j + 1, 0] - points[j, 0]
            dy = points[j + 1, 1] - points[j, 1]
            if dx * dx + dy * dy > g2:
                break
            j += 1
        if j - i + 1 >= min_len:
            for q in range(i, j + 1):
                labels[q] = seg
                alive[q] = False
            seg += 1
            taken += j - i + 1
        i = j + 1
    return seg, taken


@nb.njit(cache=True)
def discard_inliers(inl: BoolArray, alive: BoolArray) -> int:
    """Kill the inliers without labelling them (a line whose inliers form no long run); how many."""
    n = 0
    for i in range(inl.shape[0]):
        if inl[i] and alive[i]:
            alive[i] = False
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
