"""Compiled (numba) kernels of the door/board edges (``frontend.edge_finder``): one call over all
of a scan's segment pairs or break candidates where the Python loops went one by one.

The arithmetic is the per-candidate numpy code's, operation for operation: the dot products of
3-vectors as ``(a0 b0 + a1 b1) + a2 b2`` (numpy's ``a @ b`` of two 3-vectors, checked bit for bit
in tests/test_edge_kernels.py), norms as the square root of that. What numpy computes otherwise
(a matrix times a vector, ``math.hypot``, ``x ** 2``) stays with the caller.
Each kernel's unit test holds the code it replaced.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@nb.njit(cache=True)
def break_pairs(order: IntArray, n_points: IntArray, wall: BoolArray, max_skipped_points: int) -> IntArray:
    """Neighbouring segments in beam order ``order`` (the segments sorted by first beam),
    ``(j_wall, j_other)`` rows (P, 2), as ``frontend.edges.break_pairs`` with ``wall[j]``:
    segment j is a wall's."""
    n = order.shape[0]
    out = np.empty((4 * n, 2), dtype=np.int64)
    m = 0
    for i in range(n):
        a = order[i]
        for b_i in range(i + 1, min(i + 3, n)):
            b = order[b_i]
            if b_i != i + 1 and n_points[order[i + 1]] > max_skipped_points:
                break
            if wall[a]:
                out[m, 0] = a
                out[m, 1] = b
                m += 1
            if wall[b]:
                out[m, 0] = b
                out[m, 1] = a
                m += 1
    return out[:m]


@nb.njit(cache=True)
def _dot3(a: FloatArray, b: FloatArray) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@nb.njit(cache=True)
def _break_geometry(origin: FloatArray, x: FloatArray, n_wall: FloatArray, n_e: FloatArray, step_point: FloatArray,
                    step_height: float, line: FloatArray, min_sin: float,
                    flat_slope: float) -> tuple[bool, int, int, float, bool]:
    """``BreakFinder._break``'s checks and numbers: (steep enough, side, step, u, flat)."""
    r = x - origin
    s = abs(_dot3(r, n_wall)) / max(math.sqrt(_dot3(r, r)), 1e-12)
    if not s >= min_sin:
        return False, 0, 0, 0.0, False
    side = 1 if _dot3(n_e, step_point - x) > 0.0 else -1
    step = 1 if step_height > 0.0 else -1
    u = _dot3(n_e, x)
    flat = abs(line[2]) < flat_slope * abs(_dot3(line, n_e))
    return True, side, step, u, flat


@nb.njit(cache=True)
def pair_candidates(order: IntArray, n_points: IntArray, wall: BoolArray, max_skipped_points: int,
                    first_beam: IntArray, offsets: IntArray, points_body: FloatArray, times: FloatArray,
                    virtual_body: FloatArray, virtual_times: FloatArray, min_segment_points: int, max_gap: float,
                    ) -> tuple[IntArray, IntArray, IntArray, IntArray, IntArray, FloatArray, FloatArray]:
    """The segment pairs of :func:`break_pairs` whose other segment has ``min_segment_points`` and
    whose boundary points (``ia``: the end of the earlier segment in beam order ``lo``, ``ib``: the
    start of the later one) lie within ``max_gap``: (j_wall, j_other, lo, ia, ib) (N,) each, and
    per pair six body points with their times to place, (6 N, 3) and (6 N,): the two boundary
    points, the other's and the wall's two virtual points."""
    pairs = break_pairs(order, n_points, wall, max_skipped_points)
    n = pairs.shape[0]
    jw = np.empty(n, dtype=np.int64)
    jo = np.empty(n, dtype=np.int64)
    lo = np.empty(n, dtype=np.int64)
    ia = np.empty(n, dtype=np.int64)
    ib = np.empty(n, dtype=np.int64)
    m = 0
    for c in range(n):
        a, b = pairs[c, 0], pairs[c, 1]
        first, second = (a, b) if first_beam[a] < first_beam[b] else (b, a)
        i_a, i_b = offsets[first + 1] - 1, offsets[second]
        d0 = points_body[i_a, 0] - points_body[i_b, 0]
        d1 = points_body[i_a, 1] - points_body[i_b, 1]
        d2 = points_body[i_a, 2] - points_body[i_b, 2]
        if n_points[b] >= min_segment_points and not math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > max_gap:
            jw[m], jo[m], lo[m], ia[m], ib[m] = a, b, first, i_a, i_b
            m += 1
    pts = np.empty((6 * m, 3))
    t = np.empty(6 * m)
    for c in range(m):
        r = 6 * c
        pts[r] = points_body[ia[c]]
        pts[r + 1] = points_body[ib[c]]
        t[r], t[r + 1] = times[ia[c]], times[ib[c]]
        for k in range(2):
            pts[r + 2 + k] = virtual_body[jo[c], k]
            pts[r + 4 + k] = virtual_body[jw[c], k]
            t[r + 2 + k] = virtual_times[jo[c], k]
            t[r + 4 + k] = virtual_times[jw[c], k]
    return jw[:m], jo[:m], lo[:m], ia[:m], ib[:m], pts, t


@nb.njit(cache=True)
def pair_breaks(h: FloatArray, w: FloatArray, jw: IntArray, jo: IntArray, lo: IntArray, ia: IntArray, ib: IntArray,
                ids: IntArray, seg_normal: FloatArray, seg_d: FloatArray, seg_along: FloatArray,
                points_body: FloatArray, times: FloatArray, origin: FloatArray, step_tolerance: float,
                min_step: float, max_step: float, min_sin: float, flat_slope: float, midpoint: bool,
                ) -> tuple[BoolArray, IntArray, IntArray, FloatArray, BoolArray, FloatArray, FloatArray, FloatArray,
                           FloatArray]:
    """The breaks of N segment pairs of :func:`pair_candidates` (``BreakFinder._pair_breaks`` with
    ``point`` "midpoint" or "higher"): per pair the six placed points ``w`` (N, 6, 3) world frame
    and their heights ``h`` (N, 6) along the wall normal; per segment its plane id ``ids``, its
    wall's normal, offset and along-wall direction (``seg_*``, world frame).

    Returns keep, side, step, u, flat, the edge points (N, 3) world and body frame, their times
    and the beam spacings there (N,)."""
    n = h.shape[0]
    n_pts = points_body.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    side = np.zeros(n, dtype=np.int64)
    step = np.zeros(n, dtype=np.int64)
    u = np.zeros(n)
    flat = np.zeros(n, dtype=np.bool_)
    x_world = np.zeros((n, 3))
    pt_body = np.zeros((n, 3))
    t = np.zeros(n)
    spacing = np.zeros(n)
    for c in range(n):
        j = jw[c]
        n_wall, d_wall = seg_normal[j], seg_d[j]
        h_wall = (h[c, 4] + h[c, 5]) / 2.0
        h_other = (h[c, 2] + h[c, 3]) / 2.0
        if ids[jo[c]] == ids[j] and abs(h_wall + d_wall) > abs(h_other + d_wall):
            continue
        s1, s2 = h[c, 2] - h_wall, h[c, 3] - h_wall
        if abs(s1 - s2) > step_tolerance or not min_step <= abs(0.5 * (s1 + s2)) <= max_step:
            continue
        h_view = _dot3(n_wall, origin)
        wall_higher = abs(h_view - h_wall) < abs(h_view - h_other)
        if wall_higher == (j == lo[c]):
            i_end, i_next, q = ia[c], ia[c] - 1, 0
        else:
            i_end, i_next, q = ib[c], ib[c] + 1, 1
        if midpoint:
            for k in range(3):
                x_world[c, k] = 0.5 * (w[c, 0, k] + w[c, 1, k])
                pt_body[c, k] = 0.5 * (points_body[ia[c], k] + points_body[ib[c], k])
            t[c] = 0.5 * (times[ia[c]] + times[ib[c]])
            dp = points_body[ia[c]] - points_body[ib[c]]
        else:
            if i_next < 0:  # numpy's index from the end
                i_next += n_pts
            if i_next >= n_pts:
                raise IndexError("pair_breaks: the boundary point is the scan's last")
            x_world[c] = w[c, q]
            pt_body[c] = points_body[i_end]
            t[c] = times[i_end]
            dp = points_body[i_end] - points_body[i_next]
        spacing[c] = math.sqrt(_dot3(dp, dp))
        step_point = (w[c, 2] + w[c, 3]) / 2.0
        keep[c], side[c], step[c], u[c], flat[c] = _break_geometry(
            origin, x_world[c], n_wall, seg_along[j], step_point, s1 + s2, w[c, 3] - w[c, 2], min_sin, flat_slope)
    return keep, side, step, u, flat, x_world, pt_body, t, spacing


@nb.njit(cache=True)
def recess_breaks(w: FloatArray, n_wall: FloatArray, n_e: FloatArray, origin: FloatArray, min_sin: float,
                  flat_slope: float) -> tuple[BoolArray, IntArray, IntArray, FloatArray, BoolArray]:
    """The checks of N recess breaks (``BreakFinder._recess_breaks``): per break the placed points
    ``w`` (N, 4, 3) world frame (the edge point, the first return inside the recess, the wall's
    two virtual points), the wall's normal and along-wall direction (N, 3). Returns keep, side,
    step, u (along the wall), flat (N,)."""
    n = w.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    side = np.zeros(n, dtype=np.int64)
    step = np.zeros(n, dtype=np.int64)
    u = np.zeros(n)
    flat = np.zeros(n, dtype=np.bool_)
    for c in range(n):
        x = w[c, 0]
        keep[c], side[c], step[c], u[c], flat[c] = _break_geometry(
            origin, x, n_wall[c], n_e[c], w[c, 1], _dot3(n_wall[c], w[c, 1] - x), w[c, 3] - w[c, 2], min_sin,
            flat_slope)
    return keep, side, step, u, flat


@nb.njit(cache=True)
def _ray_on_line(angle: float, cx: float, cy: float, ux: float, uy: float) -> tuple[bool, float, float]:
    """``frontend.edges.ray_on_line``: (met, x, y)."""
    rx, ry = np.cos(angle), np.sin(angle)
    det = ux * ry - uy * rx
    if abs(det) < 1e-6:
        return False, 0.0, 0.0
    lam = (ux * cy - uy * cx) / det
    if lam <= 0.0:
        return False, 0.0, 0.0
    return True, lam * rx, lam * ry


@nb.njit(cache=True)
def bracket_on_line(angles: FloatArray, ranges: FloatArray, valid: BoolArray, centroid: FloatArray,
                    direction: FloatArray, k_end: int, step: int, tolerance: float,
                    max_beams: int = 8) -> tuple[bool, float, float, float]:
    """``frontend.edge_finder._bracket_on_line``: the end of the surface on the 2D line
    (``centroid``, ``direction``; scanner frame) walked from beam ``k_end`` in direction ``step``
    over beams still on the line within ``tolerance`` (``frontend.edges.surface_end``), bracketed
    with the next beam (``frontend.edges.bracket_point``). Returns (found, x, y, spacing)."""
    cx, cy, ux, uy = centroid[0], centroid[1], direction[0], direction[1]
    nx, ny = -uy, ux
    n = angles.shape[0]
    k = k_end
    for _ in range(max_beams):
        j = k + step
        if not 0 <= j < n or not valid[j]:
            break
        px, py = ranges[j] * np.cos(angles[j]), ranges[j] * np.sin(angles[j])
        if abs(nx * (px - cx) + ny * (py - cy)) > tolerance:
            break
        k = j
    k_next = k + step
    if not 0 <= k_next < n:
        return False, 0.0, 0.0, 0.0
    ok_a, ax, ay = _ray_on_line(angles[k], cx, cy, ux, uy)
    ok_b, bx, by = _ray_on_line(angles[k_next], cx, cy, ux, uy)
    if not (ok_a and ok_b):
        return False, 0.0, 0.0, 0.0
    dx, dy = bx - ax, by - ay
    return True, 0.5 * (ax + bx), 0.5 * (ay + by), math.sqrt(dx * dx + dy * dy)


@nb.njit(cache=True)
def along_offsets(n_e: FloatArray, x_world: FloatArray) -> FloatArray:
    """``n_e[i] . x_world[i]`` (N,): the breaks' offsets along their walls (``Break.u``)."""
    out = np.empty(x_world.shape[0])
    for i in range(x_world.shape[0]):
        out[i] = _dot3(n_e[i], x_world[i])
    return out
