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

from slam.frontend.batch_kernels import _fma, rows_dot
from slam.trajectory.kernels import place_uniform

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
def scan_pair_breaks(order: IntArray, n_points: IntArray, wall: BoolArray, max_skipped_points: int,
                     first_beam: IntArray, offsets: IntArray, points_body: FloatArray, times: FloatArray,
                     virtual_body: FloatArray, virtual_times: FloatArray, min_segment_points: int, max_gap: float,
                     T: FloatArray, t0: float, dt: float, n_knots: int, ids: IntArray, seg_normal: FloatArray,
                     seg_d: FloatArray, seg_along: FloatArray, origin: FloatArray, step_tolerance: float,
                     min_step: float, max_step: float, min_sin: float, flat_slope: float, midpoint: bool,
                     ) -> tuple[IntArray, BoolArray, IntArray, IntArray, FloatArray, BoolArray, FloatArray, FloatArray,
                                FloatArray, FloatArray]:
    """``BreakFinder._pair_breaks_batch``'s compiled part in one call: :func:`pair_candidates`
    (its first twelve arguments), the candidates' six points placed in the world with the uniform
    knots (``slam.trajectory.kernels.place_uniform`` of ``T`` (K, 4, 4), ``t0 + k dt``,
    ``n_knots``), their heights along the wall normal (``batch_kernels.rows_dot``: numpy's
    ``(6, 3) @ (3,)`` per pair, OpenBLAS's gemv) and :func:`pair_breaks` (the rest). Returns the
    pairs' wall segments ``j_wall`` (N,) and :func:`pair_breaks`' arrays."""
    jw, jo, lo, ia, ib, pts, t = pair_candidates(order, n_points, wall, max_skipped_points, first_beam, offsets,
                                                 points_body, times, virtual_body, virtual_times, min_segment_points,
                                                 max_gap)
    n = jw.shape[0]
    placed = place_uniform(T, t0, dt, n_knots, t, pts).reshape((n, 6, 3))
    h = np.empty((n, 6))
    for c in range(n):
        h[c] = rows_dot(placed[c], seg_normal[jw[c]])
    keep, side, step, u, flat, x_world, pt_body, t_edge, spacing = pair_breaks(
        h, placed, jw, jo, lo, ia, ib, ids, seg_normal, seg_d, seg_along, points_body, times, origin, step_tolerance,
        min_step, max_step, min_sin, flat_slope, midpoint)
    return jw, keep, side, step, u, flat, x_world, pt_body, t_edge, spacing


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


@nb.njit(cache=True)
def _pairwise_sum(a: FloatArray, lo: int, hi: int) -> float:
    """``np.sum(a[lo:hi])`` bit for bit: numpy's pairwise sum (eight partial sums, blocks of 128)."""
    n = hi - lo
    if n < 8:
        res = 0.0
        for i in range(lo, hi):
            res += a[i]
        return res
    if n <= 128:
        r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
        r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
        i = 8
        while i < n - (n % 8):
            b = lo + i
            r0 += a[b]
            r1 += a[b + 1]
            r2 += a[b + 2]
            r3 += a[b + 3]
            r4 += a[b + 4]
            r5 += a[b + 5]
            r6 += a[b + 6]
            r7 += a[b + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res += a[lo + i]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise_sum(a, lo, lo + n2) + _pairwise_sum(a, lo + n2, hi)


@nb.njit(cache=True)
def _recess_beyond(k_end: int, step: int, angles: FloatArray, ranges: FloatArray, valid: BoolArray,
                   cx: float, cy: float, ux: float, uy: float, min_step: float, max_step: float,
                   max_gap: float, n_beams: int, min_returns: int) -> tuple[int, int, int, float]:
    """``frontend.edges.recess_beyond``: (status, first, last, median); status 0: None, 1: found,
    2: the gap to the first return lies within rounding of ``max_gap`` (``math.hypot`` here is not
    Python's, so the caller decides that end with the reference code)."""
    nx, ny = -uy, ux
    away = 1.0 if nx * cx + ny * cy > 0.0 else -1.0
    r_end, a_end = ranges[k_end], angles[k_end]
    lx, ly = r_end * math.cos(a_end), r_end * math.sin(a_end)
    depths = np.empty(n_beams)
    beams = np.empty(n_beams, dtype=np.int64)
    m = 0
    first = -1
    for i in range(1, n_beams + 1):
        j = k_end + i * step
        if not 0 <= j < angles.shape[0]:
            break
        if not valid[j]:
            continue
        r_j, a_j = ranges[j], angles[j]
        qx, qy = r_j * math.cos(a_j), r_j * math.sin(a_j)
        if first < 0:
            gap = math.hypot(qx - lx, qy - ly)
            if abs(gap - max_gap) <= 1e-9 * max_gap:
                return 2, 0, 0, 0.0
            if gap > max_gap:
                return 0, 0, 0, 0.0
            first = j
        depths[m] = away * (nx * (qx - cx) + ny * (qy - cy))
        beams[m] = j
        m += 1
    if first < 0 or m < min_returns:
        return 0, 0, 0, 0.0
    n_inside = 0
    last = -1
    for i in range(m):
        if min_step <= depths[i] <= max_step:
            n_inside += 1
            last = beams[i]
    s = np.sort(depths[:m])
    median = s[m // 2] if m % 2 == 1 else (s[m // 2 - 1] + s[m // 2]) / 2
    if n_inside < min_returns or not min_step <= median <= max_step:
        return 0, 0, 0, 0.0
    return 1, first, last, median


@nb.njit(cache=True)
def _refine_split(r: FloatArray, k0: int, window: int) -> tuple[int, float]:
    """``frontend.edges._refine_split``, operation for operation."""
    n_r = r.shape[0]
    lo, hi = max(0, k0 + 1 - 2 * window), min(n_r, k0 + 1 + 2 * window)
    n = hi - lo
    c = np.empty(n)
    acc = 0.0
    for i in range(n):
        acc = r[lo + i] if i == 0 else acc + r[lo + i]
        c[i] = acc
    best, best_i = 0.0, -1
    for i in range(n - 1):
        n_left = i + 1
        mean_left = c[i] / n_left
        mean_right = (c[n - 1] - c[i]) / (n - n_left)
        d = mean_right - mean_left
        split = lo + n_left - 1
        near = abs(split - k0) <= window and split + 1 >= window // 2 and n_r - split - 1 >= window // 2
        g = (n_left * (n - n_left)) / n * (d * d) if near else -1.0
        if best_i < 0 or g > best or (np.isnan(g) and not np.isnan(best)):
            best, best_i = g, i
        if np.isnan(g):
            break
    k = lo + best_i
    w_lo, w_hi = max(0, k + 1 - window), min(n_r, k + 1 + window)
    after = _pairwise_sum(r, k + 1, w_hi) / (w_hi - k - 1)
    before = _pairwise_sum(r, w_lo, k + 1) / (k + 1 - w_lo)
    return k, after - before


@nb.njit(cache=True)
def _steps_within(x: FloatArray, y: FloatArray, cx: float, cy: float, ux: float, uy: float, sigma: float,
                  window: int, min_step: float, max_step: float, min_z: float) -> tuple[IntArray, FloatArray]:
    """``frontend.edges.steps_within`` of the returns ``x``, ``y`` (unsorted: the caller sorts)."""
    n = x.shape[0]
    nx, ny = -uy, ux
    r = np.empty(n)
    for i in range(n):
        # (points - centroid) @ normal as OpenBLAS's gemv rounds it: one fused multiply-add
        r[i] = _fma(x[i] - cx, nx, (y[i] - cy) * ny)  # type: ignore[call-arg]
    c = np.empty(n + 1)
    c[0] = 0.0
    acc = 0.0
    for i in range(n):
        acc = r[i] if i == 0 else acc + r[i]
        c[i + 1] = acc
    n_k = n - 2 * window + 1
    scale = sigma * math.sqrt(2.0 / window)
    z = np.empty(n_k)
    ok = np.empty(n_k, dtype=np.bool_)
    for i in range(n_k):
        k = window - 1 + i
        before = (c[k + 1] - c[k + 1 - window]) / window
        after = (c[k + 1 + window] - c[k + 1]) / window
        depth = after - before
        z[i] = abs(depth) / scale
        ok[i] = abs(depth) >= min_step and abs(depth) <= max_step
    order = np.argsort(-z, kind="mergesort")
    taken = np.zeros(n_k, dtype=np.bool_)
    idx = np.empty(n_k, dtype=np.int64)
    off = np.empty(n_k)
    m = 0
    for i in order:
        if z[i] < min_z:
            break
        if taken[i]:
            continue
        taken[max(0, i - window) : i + window + 1] = True
        if ok[i]:
            idx[m], off[m] = _refine_split(r, window - 1 + i, window)
            m += 1
    return idx[:m], off[:m]


@nb.njit(cache=True)
def scan_edge_tests(first_beam: IntArray, last_beam: IntArray, n_points: IntArray, angles: FloatArray,
                    ranges: FloatArray, valid: BoolArray, cos_a: FloatArray, sin_a: FloatArray,
                    centroid: FloatArray, direction: FloatArray, min_segment_points: int, inline: bool,
                    window: int, min_step: float, max_step: float, max_gap: float, sigma: float,
                    min_z: float) -> tuple[IntArray, IntArray, FloatArray, BoolArray, IntArray, IntArray, FloatArray]:
    """``frontend.scan_prep.scan_edge_tests`` of all k segments of a scan at once (``cos_a``,
    ``sin_a``: numpy's ``np.cos`` / ``np.sin`` of ``angles``).

    Returns ``status`` (k, 2) per segment and direction (column 0: +1, column 1: -1): -1 no test
    (short segment, or another segment next to that end), 0 None, 1 a recess (``ends`` (k, 2, 2):
    first and last beam, ``median`` (k, 2)), 2 decide with the reference code; ``inline`` (k,)
    whether the segment has the steps test, its steps rows ``start[j]`` to ``start[j + 1] - 1``
    of ``step_index`` and ``step_offset`` (unsorted)."""
    k = first_beam.shape[0]
    n_beams = angles.shape[0]
    owner = np.full(n_beams, -1, dtype=np.int64)
    for j in range(k):
        owner[first_beam[j] : last_beam[j] + 1] = j
    status = np.full((k, 2), -1, dtype=np.int64)
    ends = np.zeros((k, 2, 2), dtype=np.int64)
    median = np.zeros((k, 2))
    has_inline = np.zeros(k, dtype=np.bool_)
    start = np.zeros(k + 1, dtype=np.int64)
    step_index = np.empty(0, dtype=np.int64)
    step_offset = np.empty(0)
    for j in range(k):
        n = n_points[j]
        cx, cy = centroid[j, 0], centroid[j, 1]
        ux, uy = direction[j, 0], direction[j, 1]
        if n >= min_segment_points:
            for col in range(2):
                d = 1 if col == 0 else -1
                k_end = last_beam[j] if d == 1 else first_beam[j]
                a, b = k_end + d, k_end + 3 * d
                near = False
                for q in range(max(0, min(a, b)), min(max(a, b) + 1, n_beams)):
                    if owner[q] >= 0:
                        near = True
                        break
                if near:
                    continue
                st, f, la, med = _recess_beyond(k_end, d, angles, ranges, valid, cx, cy, ux, uy, min_step,
                                                max_step, max_gap, 8, 3)
                status[j, col] = st
                ends[j, col, 0] = f
                ends[j, col, 1] = la
                median[j, col] = med
        start[j + 1] = start[j]
        if inline and n >= 2 * window:
            has_inline[j] = True
            lo, hi = first_beam[j], last_beam[j] + 1
            m = 0
            for q in range(lo, hi):
                if valid[q]:
                    m += 1
            if m < 2 * window:
                continue
            x = np.empty(m)
            y = np.empty(m)
            m = 0
            for q in range(lo, hi):
                if valid[q]:
                    x[m] = ranges[q] * cos_a[q]
                    y[m] = ranges[q] * sin_a[q]
                    m += 1
            idx, off = _steps_within(x, y, cx, cy, ux, uy, sigma, window, min_step, max_step, min_z)
            if idx.shape[0]:
                step_index = np.concatenate((step_index, idx))
                step_offset = np.concatenate((step_offset, off))
                start[j + 1] = start[j] + idx.shape[0]
    return status, ends, median, has_inline, start, step_index, step_offset
