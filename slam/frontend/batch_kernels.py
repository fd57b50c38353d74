"""Compiled (numba) batch kernels of the front end's per-scan bookkeeping: one call over all the
beams or rows of a scan where the Python loops went segment by segment or plane by plane.

Each kernel's unit test (tests/test_batch_kernels.py) holds the numpy code it replaced.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@nb.njit(cache=True)
def plane_crossings(
    dirs_world: FloatArray, ranges: FloatArray, origin_world: FloatArray, normals: FloatArray, offsets: FloatArray,
    us: FloatArray, vs: FloatArray, margin: float, min_range: float, min_cos: float,
) -> tuple[IntArray, FloatArray, NDArray[np.bool_]]:
    """The beams of one scan (unit directions ``dirs_world`` (m, 3) from ``origin_world`` (3,),
    returns at ``ranges`` (m,)) that cross each of P planes ``normals[p] . x + offsets[p] = 0``
    (world frame) before their return (``frontend.transients``): at least ``min_range`` from the
    scanner, steeper than ``min_cos`` (cosine of the incidence), with the return less than
    ``margin`` behind the plane (along the normal, away from the scanner).

    Returns ``start`` (P + 1,): plane p's crossings are rows ``start[p]`` to ``start[p + 1] - 1``
    (in beam order) of ``uv`` (n, 2), the crossing points in the plane's (``us[p]``, ``vs[p]``)
    frame, and of ``through`` (n,): whether the return lies more than ``margin`` behind."""
    m = dirs_world.shape[0]
    n_planes = normals.shape[0]
    start = np.zeros(n_planes + 1, dtype=np.int64)
    uv = np.empty((m * n_planes, 2))
    through = np.empty(m * n_planes, dtype=np.bool_)
    ox, oy, oz = origin_world[0], origin_world[1], origin_world[2]
    o = 0
    for p in range(n_planes):
        nx, ny, nz = normals[p, 0], normals[p, 1], normals[p, 2]
        s = nx * ox + ny * oy + nz * oz + offsets[p]  # the scanner's signed distance from the plane
        sign = 1.0 if s > 0.0 else (-1.0 if s < 0.0 else 0.0)
        for i in range(m):
            dx, dy, dz = dirs_world[i, 0], dirs_world[i, 1], dirs_world[i, 2]
            den = dx * nx + dy * ny + dz * nz
            if not abs(den) > min_cos:  # a grazing beam's crossing is ill-defined
                continue
            behind = (s + ranges[i] * den) * sign  # the return's signed distance, positive on the scanner's side
            t = -s / den
            if not (t > min_range and math.isfinite(t) and behind < margin):
                continue
            x, y, z = ox + t * dx, oy + t * dy, oz + t * dz
            uv[o, 0] = x * us[p, 0] + y * us[p, 1] + z * us[p, 2]
            uv[o, 1] = x * vs[p, 0] + y * vs[p, 1] + z * vs[p, 2]
            through[o] = behind < -margin
            o += 1
        start[p + 1] = o
    return start, uv[:o], through[:o]


@intrinsic
def _fma(typingctx, a, b, c):  # type: ignore[no-untyped-def]
    """``a * b + c`` rounded once (LLVM's fma): how OpenBLAS's gemv sums the rows of an
    (m, 3) @ (3,) product."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        d = ir.DoubleType()
        fn = builder.module.declare_intrinsic("llvm.fma", [d], ir.FunctionType(d, [d, d, d]))
        return builder.call(fn, args)

    return sig, codegen


@nb.njit(cache=True)
def rows_dot(a: FloatArray, x: FloatArray) -> FloatArray:
    """``a @ x`` of an (m, 3) array and a (3,) vector bit for bit as numpy computes it: a dot
    product for one row, OpenBLAS's gemv (two fused multiply-adds per row) for more."""
    m = a.shape[0]
    out = np.empty(m)
    if m == 1:
        out[0] = a[0, 0] * x[0] + a[0, 1] * x[1] + a[0, 2] * x[2]
        return out
    for i in range(m):
        out[i] = _fma(a[i, 2], x[2], _fma(a[i, 0], x[0], a[i, 1] * x[1]))  # type: ignore[call-arg]
    return out


@nb.njit(cache=True)
def _arg_first(x: FloatArray, most: bool) -> int:
    """``np.argmin`` (``np.argmax`` with ``most``): the first extreme, or the first NaN."""
    best = 0
    for i in range(x.shape[0]):
        if np.isnan(x[i]):
            return i
        if (x[i] > x[best]) if most else (x[i] < x[best]):
            best = i
    return best


@nb.njit(cache=True)
def grow_extremes(points_world: FloatArray, bounds: IntArray, seg_plane: IntArray, grows: NDArray[np.bool_],
                  extremes: FloatArray, has: NDArray[np.bool_], us: FloatArray, vs: FloatArray) -> None:
    """``PlaneMap._grow_extremes`` for a scan's segments in order: segment s (its points rows
    ``bounds[s]`` to ``bounds[s + 1] - 1`` of ``points_world`` (n, 3), world frame) grows, where
    ``grows[s]``, the extreme points ``extremes[q]`` (4, 3) (valid where ``has[q]``) of plane
    ``q = seg_plane[s]`` (axes ``us[q]``, ``vs[q]``); both updated in place."""
    for s in range(seg_plane.shape[0]):
        a, b = bounds[s], bounds[s + 1]
        if not grows[s] or b == a:
            continue
        q = seg_plane[s]
        k0 = 4 if has[q] else 0
        pts = np.empty((k0 + b - a, 3))
        pts[:k0] = extremes[q, :k0]
        pts[k0:] = points_world[a:b]
        pu, pv = rows_dot(pts, us[q]), rows_dot(pts, vs[q])
        i0, i1 = _arg_first(pu, False), _arg_first(pu, True)
        i2, i3 = _arg_first(pv, False), _arg_first(pv, True)
        extremes[q, 0] = pts[i0]
        extremes[q, 1] = pts[i1]
        extremes[q, 2] = pts[i2]
        extremes[q, 3] = pts[i3]
        has[q] = True


@nb.njit(cache=True)
def segment_cells(points_world: FloatArray, bounds: IntArray, seg_plane: IntArray, grows: NDArray[np.bool_],
                  us: FloatArray, vs: FloatArray, cell_size: float) -> tuple[IntArray, IntArray]:
    """The extent cells (``PlaneMap.cells_of``) of the segments that grow (see
    :func:`grow_extremes`), each segment's without the cells an earlier segment of this call
    gave its plane or it gave itself (first occurrences in order: added to a set in this order
    they leave the set as all of them would). Returns the cells (c, 2) and each segment's
    start (S + 1,) in them."""
    n_seg = seg_plane.shape[0]
    out = np.empty((points_world.shape[0], 2), dtype=np.int64)
    owner = np.empty(points_world.shape[0], dtype=np.int64)
    start = np.zeros(n_seg + 1, dtype=np.int64)
    o = 0
    for s in range(n_seg):
        q = seg_plane[s]
        if grows[s]:
            u, v = us[q], vs[q]
            for k in range(bounds[s], bounds[s + 1]):
                x, y, z = points_world[k, 0], points_world[k, 1], points_world[k, 2]
                cu = int(np.floor((x * u[0] + y * u[1] + z * u[2]) / cell_size))
                cv = int(np.floor((x * v[0] + y * v[1] + z * v[2]) / cell_size))
                new = True
                for i in range(o):
                    if owner[i] == q and out[i, 0] == cu and out[i, 1] == cv:
                        new = False
                        break
                if new:
                    out[o, 0] = cu
                    out[o, 1] = cv
                    owner[o] = q
                    o += 1
        start[s + 1] = o
    return out[:o], start


@nb.njit(cache=True)
def _near_any(su: FloatArray, sv: FloatArray, qu: float, qv: float, near: float) -> bool:
    """Whether a point ``(su, sv)`` (sorted by ``su``) lies less than ``near`` from ``(qu, qv)``:
    ``du * du + dv * dv < near * near``, as ``cKDTree.query`` with ``distance_upper_bound`` decides
    (only the points within ``2 near`` in u are looked at: any other's ``du * du`` alone is at
    least ``near * near``)."""
    near2 = near * near
    k = np.searchsorted(su, qu - 2.0 * near)
    hi = qu + 2.0 * near
    while k < su.shape[0] and su[k] <= hi:
        du = su[k] - qu
        dv = sv[k] - qv
        if du * du + dv * dv < near2:
            return True
        k += 1
    return False


@nb.njit(cache=True)
def strided_beams_world(
    cos_a: FloatArray, sin_a: FloatArray, ranges: NDArray[np.float32] | FloatArray, valid: NDArray[np.bool_],
    beam_start: IntArray, T_world_scanner: FloatArray, step: int,
) -> tuple[FloatArray, FloatArray, IntArray, FloatArray]:
    """The beams ``frontend.transients`` tests, of S scans at once: scan i's beams are entries
    ``beam_start[i]`` to ``beam_start[i + 1] - 1`` of ``cos_a``/``sin_a`` (of its beam angles,
    scanner frame), ``ranges`` and ``valid``; of its valid beams every ``step``-th from the first
    (``np.flatnonzero(valid)[::step]``). Returns their unit directions (world frame, by
    ``T_world_scanner[i]`` (4, 4)), ranges (float64), the row bounds of the scans that have any
    (k + 1,) and those scans' origins (k, 3), world frame: bit for bit numpy's
    ``np.column_stack((cos, sin)) @ T[:3, :2].T`` (a dot product for one beam, OpenBLAS's fused
    multiply-add for more)."""
    n_scans = beam_start.shape[0] - 1
    total = 0
    for i in range(n_scans):
        total += beam_start[i + 1] - beam_start[i]
    dirs = np.empty((total // step + n_scans, 3))
    out_r = np.empty(total // step + n_scans)
    bounds = np.zeros(n_scans + 1, dtype=np.int64)
    origins = np.empty((n_scans, 3))
    o = 0
    k = 0
    for i in range(n_scans):
        lo, hi = beam_start[i], beam_start[i + 1]
        rows = np.empty(hi - lo, dtype=np.int64)
        m = 0
        c = 0
        for b in range(lo, hi):
            if valid[b]:
                if c % step == 0:
                    rows[m] = b
                    m += 1
                c += 1
        if m == 0:
            continue
        T = T_world_scanner[i]
        for q in range(m):
            b = rows[q]
            for j in range(3):
                if m == 1:
                    dirs[o + q, j] = _fma(cos_a[b], T[j, 0], sin_a[b] * T[j, 1])  # type: ignore[call-arg]
                else:
                    dirs[o + q, j] = _fma(sin_a[b], T[j, 1], cos_a[b] * T[j, 0])  # type: ignore[call-arg]
            out_r[o + q] = np.float64(ranges[b])
        origins[k, 0], origins[k, 1], origins[k, 2] = T[0, 3], T[1, 3], T[2, 3]
        o += m
        k += 1
        bounds[k] = o
    return dirs[:o], out_r[:o], bounds[: k + 1], origins[:k]


@nb.njit(cache=True)
def see_through_counts(
    dirs_world: FloatArray, ranges: FloatArray, scan_start: IntArray, origins_world: FloatArray, normals: FloatArray,
    offsets: FloatArray, us: FloatArray, vs: FloatArray, sample_u: FloatArray, sample_v: FloatArray,
    sample_start: IntArray, margin: float, near: float, min_range: float, min_cos: float,
) -> tuple[IntArray, IntArray, IntArray]:
    """The see-through counts of ``frontend.transients`` for S scans and P planes at once: scan
    i's beams are rows ``scan_start[i]`` to ``scan_start[i + 1] - 1`` of ``dirs_world``/``ranges``
    from ``origins_world[i]``, crossing the planes as :func:`plane_crossings` finds; plane p's
    sample points (its (u, v) frame, sorted by u) are ``sample_u``/``sample_v`` rows
    ``sample_start[p]`` to ``sample_start[p + 1] - 1``. Returns per scan and plane (S, P) the
    crossings, those within ``near`` of a sample whose return lies beyond the margin (through)
    and those within ``near`` of one whose return does not (on)."""
    n_scans, n_planes = scan_start.shape[0] - 1, normals.shape[0]
    n_cross = np.zeros((n_scans, n_planes), dtype=np.int64)
    through = np.zeros((n_scans, n_planes), dtype=np.int64)
    on = np.zeros((n_scans, n_planes), dtype=np.int64)
    for i in range(n_scans):
        a, b = scan_start[i], scan_start[i + 1]
        start, uv, far = plane_crossings(dirs_world[a:b], ranges[a:b], origins_world[i], normals, offsets, us, vs,
                                         margin, min_range, min_cos)
        for p in range(n_planes):
            su = sample_u[sample_start[p] : sample_start[p + 1]]
            sv = sample_v[sample_start[p] : sample_start[p + 1]]
            n_cross[i, p] = start[p + 1] - start[p]
            for o in range(start[p], start[p + 1]):
                if _near_any(su, sv, uv[o, 0], uv[o, 1], near):
                    if far[o]:
                        through[i, p] += 1
                    else:
                        on[i, p] += 1
    return n_cross, through, on


@nb.njit(cache=True)
def _max_abs_offset(points: FloatArray, n: FloatArray, d: float) -> float:
    """``np.max(np.abs(points @ n + d))`` of (m, 3) points (NaN if any is NaN or there are none)."""
    if points.shape[0] == 0:
        return np.nan
    r = rows_dot(points, n)
    out = abs(r[0] + d)
    for i in range(r.shape[0]):
        x = abs(r[i] + d)
        if np.isnan(x):
            return x
        if x > out:
            out = x
    return out


@nb.njit(cache=True)
def on_plane_many(lines: FloatArray, samples: FloatArray, sample_start: IntArray, idx: IntArray, n: FloatArray,
                  d: float, coplanar_distance: float, sample_distance: float) -> NDArray[np.bool_]:
    """``plane_init.on_plane`` of the pooled segments ``idx``: segment i's fitted line
    ``lines[i]`` (2, 3) and its samples, rows ``sample_start[i]`` to ``sample_start[i + 1] - 1``
    (at least one) of ``samples``, world frame, against the plane ``n . x + d = 0``."""
    out = np.zeros(idx.shape[0], dtype=np.bool_)
    for k in range(idx.shape[0]):
        i = idx[k]
        if _max_abs_offset(lines[i], n, d) > coplanar_distance:
            continue
        out[k] = _max_abs_offset(samples[sample_start[i] : sample_start[i + 1]], n, d) <= sample_distance
    return out


@nb.njit(cache=True)
def cross_rows(a: FloatArray, b: FloatArray) -> FloatArray:
    """``np.cross(a, b)`` of a (3,) vector and (n, 3) rows, bit for bit (numpy's products and
    differences, none fused)."""
    out = np.empty((b.shape[0], 3))
    for i in range(b.shape[0]):
        out[i, 0] = a[1] * b[i, 2] - a[2] * b[i, 1]
        out[i, 1] = a[2] * b[i, 0] - a[0] * b[i, 2]
        out[i, 2] = a[0] * b[i, 1] - a[1] * b[i, 0]
    return out


@nb.njit(cache=True)
def lift_segments(
    labels: IntArray, valid_index: IntArray, points_xy: FloatArray, beam_times: FloatArray, k: int, R: FloatArray,
    t: FloatArray, centroid: FloatArray, direction: FloatArray, var_point: float, var_model: float,
) -> tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """``frontend.observations.scan_segments``'s arithmetic in one pass, bit for bit (its numpy
    code with more than one labelled return: OpenBLAS's gemm for ``@ R.T``, two fused multiply-adds
    per entry; ``np.bincount``'s sums in point order). ``labels`` per beam, ``valid_index`` and
    ``points_xy`` the valid returns (``Scanline``), ``var_point`` / ``var_model`` the squared
    sigmas. Returns (counts, offsets, points_body, times, v_scanner, v_body, v_times, v_sigma)."""
    m = valid_index.shape[0]
    n_keep = 0
    for i in range(m):
        if labels[valid_index[i]] >= 0:
            n_keep += 1
    lab = np.empty(n_keep, dtype=np.int64)
    pts2 = np.empty((n_keep, 2))
    tms = np.empty(n_keep)
    o = 0
    for i in range(m):
        b = valid_index[i]
        if labels[b] >= 0:
            lab[o] = labels[b]
            pts2[o, 0] = points_xy[i, 0]
            pts2[o, 1] = points_xy[i, 1]
            tms[o] = beam_times[b]
            o += 1
    counts = np.zeros(k, dtype=np.int64)
    for i in range(n_keep):
        counts[lab[i]] += 1
    offsets = np.zeros(k + 1, dtype=np.int64)
    for j in range(k):
        offsets[j + 1] = offsets[j] + counts[j]
    pts_body = np.empty((n_keep, 3))
    for i in range(n_keep):
        x, y = pts2[i, 0], pts2[i, 1]
        for c in range(3):
            pts_body[i, c] = _fma(0.0, R[c, 2], _fma(y, R[c, 1], x * R[c, 0])) + t[c]  # type: ignore[call-arg]
    s = np.empty(n_keep)
    ss = np.zeros(k)
    st = np.zeros(k)
    for i in range(n_keep):
        j = lab[i]
        s[i] = (pts2[i, 0] - centroid[j, 0]) * direction[j, 0] + (pts2[i, 1] - centroid[j, 1]) * direction[j, 1]
        ss[j] += s[i] * s[i]
        st[j] += tms[i]
    var_s = np.empty(k)
    t_mean = np.empty(k)
    for j in range(k):
        var_s[j] = ss[j] / max(float(counts[j]), 1.0)
        t_mean[j] = st[j] / max(float(counts[j]), 1.0)
    cts = np.zeros(k)
    for i in range(n_keep):
        j = lab[i]
        cts[j] += (tms[i] - t_mean[j]) * s[i]
    v_scanner = np.zeros((k, 2, 3))
    v_body = np.empty((k, 2, 3))
    v_times = np.empty((k, 2))
    v_sigma = np.empty(k)
    for j in range(k):
        n = float(counts[j])
        cov_ts = cts[j] / max(n, 1.0)
        beta = cov_ts / var_s[j] if var_s[j] > 0 else 0.0
        h = math.sqrt(var_s[j])
        hu0, hu1, bh = h * direction[j, 0], h * direction[j, 1], beta * h
        v_scanner[j, 0, 0], v_scanner[j, 0, 1] = centroid[j, 0] - hu0, centroid[j, 1] - hu1
        v_scanner[j, 1, 0], v_scanner[j, 1, 1] = centroid[j, 0] + hu0, centroid[j, 1] + hu1
        v_times[j, 0], v_times[j, 1] = t_mean[j] - bh, t_mean[j] + bh
        for e in range(2):
            x, y, z = v_scanner[j, e, 0], v_scanner[j, e, 1], v_scanner[j, e, 2]
            for c in range(3):
                v_body[j, e, c] = _fma(z, R[c, 2], _fma(y, R[c, 1], x * R[c, 0])) + t[c]  # type: ignore[call-arg]
        v_sigma[j] = math.sqrt(var_point / (max(n, 2.0) / 2.0) + var_model)
    return counts, offsets, pts_body, tms, v_scanner, v_body, v_times, v_sigma
