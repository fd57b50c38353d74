"""Compiled (numba) kernels of the association of one scan's segments with the map's planes
(``slam.frontend.association``, ``slam.frontend.parallel_choice``, which document the model):
the gates as a list of candidate pairs, the choice between parallel planes and the nearest
unambiguous candidate, each one call per scan where the Python code went segment by segment and
candidate by candidate.

The numbers are those of the Python code they replaced (tests/test_assoc_kernels.py holds it):
the same formulas in the same order. Where that code squared a numpy or Python scalar (``x ** 2``:
the C library's ``pow``, which rounds differently from ``x * x`` in about one case in a thousand)
these kernels call ``math.pow`` with the exponent ``two`` passed in at run time, so that the
compiler cannot fold it into a product.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from slam.frontend.kernels import pair_gate

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

NONE, HELD = -1, -2


@nb.njit(cache=True)
def gate_pairs(
    centroid: FloatArray, direction: FloatArray, endpoints: FloatArray, sigma_centroid: FloatArray,
    sigma_direction: FloatArray, seg_range: FloatArray, origin: FloatArray, normals: FloatArray, offsets: FloatArray,
    sigma_plane: FloatArray, sigma_drift: FloatArray, plane_u: FloatArray, plane_v: FloatArray, cell_size: float,
    sigma_pose: float, sigma_rotation: float, sigma_lever: float, max_endpoint_distance: float, chi2: float,
) -> tuple[IntArray, IntArray, IntArray, FloatArray, FloatArray]:
    """The gates of ``slam.frontend.kernels.association_gates`` (same inputs, same numbers) as a
    list of candidate pairs: segment ``k``'s candidates (planes passing the chi-square, end-point
    and facing gates) are ``cols[start[k]:start[k + 1]]`` (``start`` (k + 1,)), by increasing
    squared Mahalanobis distance (ties in plane order), with their extent cells ``cells`` (n, 3, 2)
    (the two end points' and the centroid's, in the plane's (u, v) frame). Also returns every
    pair's centroid signed distance ``dist`` (k, P) and its variance ``sig_d2`` (k, P) (m^2)."""
    k_n, p_n = centroid.shape[0], normals.shape[0]
    dist = np.empty((k_n, p_n))
    sig_d2 = np.empty((k_n, p_n))
    m2 = np.empty(p_n)
    facing = np.empty(p_n, dtype=np.bool_)
    for j in range(p_n):
        # map normals face the side they were seen from: the scanner must be on that side
        facing[j] = normals[j, 0] * origin[0] + normals[j, 1] * origin[1] + normals[j, 2] * origin[2] + offsets[j] > 0.0
    start = np.zeros(k_n + 1, dtype=np.int64)
    cols = np.empty(k_n * p_n, dtype=np.int64)
    n = 0
    for k in range(k_n):
        c = centroid[k]
        c_n = 0
        for j in range(p_n):
            nx, ny, nz, d = normals[j, 0], normals[j, 1], normals[j, 2], offsets[j]
            sd = sigma_drift[j]
            dc = nx * c[0] + ny * c[1] + nz * c[2] + d
            sa = abs(nx * direction[k, 0] + ny * direction[k, 1] + nz * direction[k, 2])
            s2, mk, e0, e1, cap = pair_gate(dc, sa, endpoints[k], nx, ny, nz, d, sigma_centroid[k], sigma_direction[k],
                                            seg_range[k], sigma_plane[j], sd, sigma_pose, sigma_rotation, sigma_lever,
                                            max_endpoint_distance)
            m2[j], dist[k, j], sig_d2[k, j] = mk, dc, s2
            if (mk < chi2) and (e0 < cap) and (e1 < cap) and facing[j]:
                # insertion by increasing m2 (few candidates), after the equal ones
                q = c_n
                while q > 0 and m2[cols[n + q - 1]] > mk:
                    cols[n + q] = cols[n + q - 1]
                    q -= 1
                cols[n + q] = j
                c_n += 1
        n += c_n
        start[k + 1] = n
    cells = np.empty((n, 3, 2), dtype=np.int64)
    for k in range(k_n):
        for i in range(start[k], start[k + 1]):
            j = cols[i]
            for q in range(3):
                if q < 2:
                    px, py, pz = endpoints[k, q, 0], endpoints[k, q, 1], endpoints[k, q, 2]
                else:
                    px, py, pz = centroid[k, 0], centroid[k, 1], centroid[k, 2]
                pu = px * plane_u[j, 0] + py * plane_u[j, 1] + pz * plane_u[j, 2]
                pv = px * plane_v[j, 0] + py * plane_v[j, 1] + pz * plane_v[j, 2]
                cells[i, q, 0] = int(np.floor(pu / cell_size))
                cells[i, q, 1] = int(np.floor(pv / cell_size))
    return start, cols[:n].copy(), cells, dist, sig_d2


@nb.njit(cache=True)
def _dot3(normals: FloatArray, a: int, b: int) -> float:
    """``normals[a] @ normals[b]`` as numpy computes it for 3-vectors (in order, no fused terms)."""
    return normals[a, 0] * normals[b, 0] + normals[a, 1] * normals[b, 1] + normals[a, 2] * normals[b, 2]


@nb.njit(cache=True)
def family_labels(normals: FloatArray, used: IntArray, cos_min: float) -> IntArray:
    """``parallel_choice.families`` as an array (P,): each column of ``used`` (sorted) labelled
    with the smallest column of its family (normals' dot above ``cos_min``), -1 elsewhere."""
    label = np.full(normals.shape[0], -1, dtype=np.int64)
    fams = np.empty(used.shape[0], dtype=np.int64)  # the family labels, increasing
    f_n = 0
    for i in range(used.shape[0]):
        j = used[i]
        label[j] = j
        for q in range(f_n):
            if _dot3(normals, j, fams[q]) > cos_min:
                label[j] = fams[q]
                break
        if label[j] == j:
            fams[f_n] = j
            f_n += 1
    return label


@nb.njit(cache=True)
def _nearest(dist: FloatArray, k: int, m_cols: IntArray, lo: int, up: int, h: float) -> tuple[int, float]:
    """Of segment ``k``'s candidates ``m_cols[lo:up]``, the one nearest to offset ``h`` (the first
    of equals) and its residual ``dist - h``."""
    best_q, r = lo, dist[k, m_cols[lo]] - h
    for q in range(lo + 1, up):
        rq = dist[k, m_cols[q]] - h
        if abs(rq) < abs(r):
            best_q, r = q, rq
    return best_q, r


@nb.njit(cache=True)
def _common_offset(m_seg: IntArray, m_start: IntArray, m_cols: IntArray, dist: FloatArray, weight: FloatArray,
                   tau: FloatArray, tau_host: FloatArray, hosts: BoolArray, has_hosts: bool, sp2: float,
                   outlier_nats: float) -> tuple[float, int, float]:
    """``parallel_choice._common_offset`` for one family: member ``i`` is segment ``m_seg[i]``
    with its candidates ``m_cols[m_start[i]:m_start[i + 1]]`` of the family."""
    m_n = m_seg.shape[0]
    n_h = m_start[m_n] + 1
    hyps = np.empty(n_h)
    hyps[0] = 0.0
    for i in range(m_n):
        for q in range(m_start[i], m_start[i + 1]):
            hyps[q + 1] = dist[m_seg[i], m_cols[q]]
    # sorted; a repeated hypothesis scores the same and is never strictly better, as the set's one
    hyps = np.sort(hyps)
    best_score, delta, support, best_h = -np.inf, 0.0, 0, 0.0
    for hi in range(n_h):
        h = hyps[hi]
        w_in, n_in, acc = 0.0, 0, 0.0
        for i in range(m_n):
            k = m_seg[i]
            best_q, r = _nearest(dist, k, m_cols, m_start[i], m_start[i + 1], h)
            if abs(r) < tau[k]:
                n_in += 1
                if not (has_hosts and hosts[m_cols[best_q]]) or abs(r) < tau_host[k]:
                    w_in += weight[k]
                    acc += weight[k] * (h + r)
        score = n_in * outlier_nats - 0.5 * h * h / sp2
        if score > best_score:
            best_score, support, best_h = score, n_in, h
            delta = acc / w_in if w_in > 0 else h
    return delta, support, best_h


@nb.njit(cache=True)
def _offsets_without_each(m_seg: IntArray, m_start: IntArray, m_cols: IntArray, dist: FloatArray, h: float,
                          s0: FloatArray, tau: FloatArray, tau_host: FloatArray, hosts: BoolArray, has_hosts: bool,
                          sp2: float, arm: FloatArray, has_arm: bool, normal: FloatArray,
                          sl2: float, gate: float) -> tuple[FloatArray, FloatArray]:
    """Per member of a family (normal ``normal``), what the *other* members' inliers of hypothesis
    ``h`` say of its distance to the planes: the mean and variance of the pose error along the
    normal at its centroid. The pose error is an offset ``delta`` (prior ``N(0, sp2)``) and, with
    ``has_arm``, a small rotation ``theta`` (prior ``N(0, sl2)`` about each axis across the normal)
    that moves a centroid at ``arm`` (centroid minus the scanner's position, world frame) by
    ``theta . (arm x normal)``: a board 2 cm proud at 5 m next to a wall segment the scan has
    placed is then 2 cm off by the wall's own evidence, not within the rotation's 5 mm lever.
    Each inlier (nearest candidate within ``tau``; a host wall's within ``tau_host``) weighs by
    its precision ``1 / s0^2``; an inlier that the others' prediction does not explain within
    ``gate`` is dropped and the prediction made again. Leaving the member out matters: a segment
    alone in its family set the offset to its own distance to the board and so looked certain to
    be the board's."""
    m_n = m_seg.shape[0]
    # axes across the normal: e1 horizontal where the normal is not vertical
    e1 = np.empty(3)
    if abs(normal[2]) < 0.9:
        e1[0], e1[1], e1[2] = -normal[1], normal[0], 0.0
    else:
        e1[0], e1[1], e1[2] = 1.0, 0.0, 0.0
    e1 -= (e1 @ normal) * normal
    e1 /= math.sqrt(e1 @ e1)
    e2 = np.cross(normal, e1)
    rows = np.zeros((m_n, 3))
    prec = np.zeros(m_n)
    val = np.zeros(m_n)
    lam = np.zeros((3, 3))
    lam[0, 0] = 1.0 / sp2
    lam[1, 1] = lam[2, 2] = 1.0 / sl2
    rhs = np.zeros(3)
    for i in range(m_n):
        k = m_seg[i]
        rows[i, 0] = 1.0
        if has_arm:
            c = np.cross(arm[k], normal)  # d(distance)/d(theta) = arm x normal
            rows[i, 1] = c @ e1
            rows[i, 2] = c @ e2
        best_q, r = _nearest(dist, k, m_cols, m_start[i], m_start[i + 1], h)
        if abs(r) < tau[k] and (not (has_hosts and hosts[m_cols[best_q]]) or abs(r) < tau_host[k]):
            prec[i] = 1.0 / (s0[k] * s0[k])
            val[i] = h + r
            lam += prec[i] * np.outer(rows[i], rows[i])
            rhs += prec[i] * val[i] * rows[i]
    mean, var = _predict_without_each(rows, prec, val, lam, rhs)
    # the hypothesis' wide gate let a board's segment beside its wall count as the wall's: keep
    # only the inliers that the others' prediction also explains, and predict again
    for i in range(m_n):
        if prec[i] > 0.0 and abs(val[i] - mean[i]) >= gate * math.sqrt(s0[m_seg[i]] ** 2 + var[i]):
            lam -= prec[i] * np.outer(rows[i], rows[i])
            rhs -= prec[i] * val[i] * rows[i]
            prec[i] = 0.0
    return _predict_without_each(rows, prec, val, lam, rhs)


@nb.njit(cache=True)
def _predict_without_each(rows: FloatArray, prec: FloatArray, val: FloatArray, lam: FloatArray,
                          rhs: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per member ``i``, the posterior mean and variance of ``rows[i] . x`` given the information
    ``lam`` and ``rhs`` of all inliers less member ``i``'s own (precision ``prec[i]``, value
    ``val[i]``; 0 for a non-inlier)."""
    m_n = rows.shape[0]
    mean = np.empty(m_n)
    var = np.empty(m_n)
    for i in range(m_n):
        a = rows[i]
        sol = np.linalg.solve(lam - prec[i] * np.outer(a, a), np.stack((rhs - prec[i] * val[i] * a, a), axis=1))
        mean[i] = a @ sol[:, 0]
        var[i] = a @ sol[:, 1]
    return mean, var


@nb.njit(cache=True)
def choose_columns(
    start: IntArray, cols: IntArray, keep: BoolArray, shadow: BoolArray, dist: FloatArray, sigma_own: FloatArray,
    weight: FloatArray, seg_range: FloatArray, has_range: bool, arm: FloatArray, has_arm: bool, normals: FloatArray,
    hosts: BoolArray, has_hosts: bool, rel2: float, host2: float, sp2: float, gate: float, sigma_lever: float,
    host_lever: float, cos_min: float, log_ratio: float, outlier_nats: float, walls_only: bool, model: bool, two: float,
) -> tuple[IntArray, BoolArray]:
    """``parallel_choice.choose`` (which documents it) on candidate lists given as pairs: segment
    ``k``'s candidates are the ``cols[i]``, ``start[k] <= i < start[k + 1]``, where ``keep[i]``;
    a candidate chosen where ``shadow[i]`` (a door or board the segment fits, past its extent)
    holds the segment back instead of giving it to a plane.
    ``rel2``, ``host2`` and ``sp2`` are the squares of ``relative_sigma``, ``host_sigma`` and the
    offset prior's sigma, ``log_ratio`` the log of ``ratio``, ``cos_min`` the cosine of
    ``PARALLEL_DEG``; ``seg_range`` is used with ``has_range``, ``hosts`` with ``has_hosts``, and
    ``arm`` (k, 3) (centroid minus scanner, world frame) with ``has_arm``. With ``model`` each
    segment is judged against what the *other* segments say of the scan's pose error
    (:func:`_offsets_without_each`; with ``has_arm`` the rotation's lever modelled there instead of
    added to each segment's sigma); without it, against the scan's common offset from all of them.
    Returns per segment its column (``NONE``, ``HELD``) and whether it may grow the extent."""
    k_n, p_n = start.shape[0] - 1, normals.shape[0]
    column = np.full(k_n, NONE, dtype=np.int64)
    grows = np.zeros(k_n, dtype=np.bool_)
    s_rel = np.empty(k_n)
    s0 = np.empty(k_n)
    tau = np.empty(k_n)
    tau_host = np.empty(k_n)
    for k in range(k_n):
        lever = (sigma_lever * seg_range[k]) ** 2 if has_range else 0.0
        hlever = (host_lever * seg_range[k]) ** 2 if has_range else 0.0
        s_rel[k] = math.sqrt(sigma_own[k] ** 2 + rel2 + lever)
        s0[k] = math.sqrt(sigma_own[k] ** 2 + rel2 + (0.0 if has_arm and model else lever))
        tau[k] = gate * s_rel[k]
        tau_host[k] = gate * math.sqrt(sigma_own[k] ** 2 + host2 + hlever)
    seen = np.zeros(p_n, dtype=np.bool_)
    for i in range(cols.shape[0]):
        if keep[i]:
            seen[cols[i]] = True
    used = np.flatnonzero(seen)
    if used.shape[0] == 0:
        return column, grows
    label = family_labels(normals, used, cos_min)
    n_pairs = cols.shape[0]
    m_seg = np.empty(k_n, dtype=np.int64)
    m_start = np.empty(k_n + 1, dtype=np.int64)
    m_cols = np.empty(n_pairs, dtype=np.int64)
    m_shadow = np.empty(n_pairs, dtype=np.bool_)
    rho = np.empty(p_n)
    ok = np.empty(p_n, dtype=np.int64)
    for f in used:
        if label[f] != f:
            continue
        # the family's members: the segments with a candidate in it, and those candidates in order
        m_n, n = 0, 0
        m_start[0] = 0
        for k in range(k_n):
            n0 = n
            for i in range(start[k], start[k + 1]):
                if keep[i] and label[cols[i]] == f:
                    m_cols[n] = cols[i]
                    m_shadow[n] = shadow[i]
                    n += 1
            if n > n0:
                m_seg[m_n] = k
                m_n += 1
                m_start[m_n] = n
        if m_n == 0:
            continue
        if walls_only and abs(normals[f, 2]) > 0.5:
            for i in range(m_n):
                k = m_seg[i]
                if column[k] == NONE:
                    column[k], grows[k] = m_cols[m_start[i]], True
            continue
        delta, support, h = _common_offset(m_seg[:m_n], m_start[: m_n + 1], m_cols, dist, weight, tau, tau_host,
                                           hosts, has_hosts, sp2, outlier_nats)
        if model:
            d_loo, v_loo = _offsets_without_each(m_seg[:m_n], m_start[: m_n + 1], m_cols, dist, h, s0, tau, tau_host,
                                                 hosts, has_hosts, sp2, arm, has_arm, normals[f],
                                                 max(sigma_lever, 1e-9) ** 2, gate)
        for i in range(m_n):
            k = m_seg[i]
            lo, c_n = m_start[i], m_start[i + 1] - m_start[i]
            if model:
                s_k = math.sqrt(s0[k] * s0[k] + v_loo[i])
                off_k = d_loo[i]
            else:
                s_k, off_k = s_rel[k], delta
            tau_k = gate * s_k
            o_n = 0
            for q in range(c_n):
                rho[q] = dist[k, m_cols[lo + q]] - off_k
                if abs(rho[q]) < tau_k:
                    # stable insertion by increasing |rho|
                    p = o_n
                    while p > 0 and abs(rho[ok[p - 1]]) > abs(rho[q]):
                        ok[p] = ok[p - 1]
                        p -= 1
                    ok[p] = q
                    o_n += 1
            if o_n == 0:
                continue  # on none of this family's planes: NONE unless another family takes it
            if column[k] >= 0 or column[k] == HELD:
                continue  # taken by a family seen earlier
            a = ok[0]
            decided = True
            for p in range(1, o_n):
                b = ok[p]
                if abs(rho[b] - rho[a]) < s_k:
                    continue  # the same surface
                llr = 0.5 * (math.pow(rho[b], two) - math.pow(rho[a], two)) / math.pow(s_k, two)
                if llr < log_ratio:
                    decided = False
                    break
            if decided and has_hosts and hosts[m_cols[lo + a]] and abs(rho[a]) >= tau_host[k]:
                decided = False
            if not decided or m_shadow[lo + a]:
                column[k] = HELD
                continue
            column[k] = m_cols[lo + a]
            grows[k] = c_n == 1 or (support >= 2 and o_n == 1)
    return column, grows


@nb.njit(cache=True)
def nearest_unambiguous(start: IntArray, cols: IntArray, keep: BoolArray, dist: FloatArray, sig_d2: FloatArray,
                        normals: FloatArray, ids: IntArray, same_normal: float) -> IntArray:
    """Per segment the plane id (``ids`` per column) of its nearest candidate (the first kept of
    ``cols[start[k]:start[k + 1]]``), or ``NONE`` when none is kept or a later kept one lies on
    another surface: normals' dot not above ``same_normal``, or centroid distances apart by 3
    sigmas (``sig_d2``) of the nearest's or more."""
    k_n = start.shape[0] - 1
    out = np.full(k_n, NONE, dtype=np.int64)
    for k in range(k_n):
        best = -1
        ambiguous = False
        for i in range(start[k], start[k + 1]):
            if not keep[i]:
                continue
            j = cols[i]
            if best < 0:
                best = j
                continue
            same = (_dot3(normals, best, j) > same_normal) and abs(dist[k, best] - dist[k, j]) < 3.0 * math.sqrt(
                sig_d2[k, best])
            if not same:
                ambiguous = True
                break
        if best >= 0 and not ambiguous:
            out[k] = ids[best]
    return out


@nb.njit(cache=True)
def scan_pairs(
    centroid: FloatArray, direction: FloatArray, endpoints: FloatArray, sigma_centroid: FloatArray,
    sigma_direction: FloatArray, seg_range: FloatArray, origin: FloatArray, rows: FloatArray,
    horizontal: BoolArray, ids: IntArray, child_rows: IntArray, odometer: float, drift_rate: float,
    drift_rate_vertical: float, max_drift_sigma: float, extent_margin_cells: int, max_extra_cells: int,
    child_margin_cells: int, cell_size: float, sigma_pose: float, sigma_rotation: float, sigma_lever: float,
    max_endpoint_distance: float, chi2: float,
) -> tuple[IntArray, IntArray, IntArray, FloatArray, FloatArray, IntArray, IntArray]:
    """:func:`gate_pairs` for the segments of one scan against the active planes' ``rows`` (P, 12)
    (``PlaneMap.active_rows``: normal, offset, offset sigma, odometer when last seen, axes u and
    v; world frame), with the drift since each plane was last seen (``odometer`` now; the vertical
    rate for the ``horizontal`` planes) in their sigmas and extent margins. Returns ``start``,
    ``cols``, ``cells``, ``dist`` and ``sig_d2`` as :func:`gate_pairs`, and per pair its plane's
    id (``ids`` per row) and extent margin (cells; ``child_margin_cells`` for the ``child_rows``
    when >= 0)."""
    p_n = rows.shape[0]
    normals = np.empty((p_n, 3))
    offsets = np.empty(p_n)
    sigma_plane = np.empty(p_n)
    sig_drift = np.empty(p_n)
    plane_u = np.empty((p_n, 3))
    plane_v = np.empty((p_n, 3))
    dilate = np.empty(p_n, dtype=np.int64)
    for j in range(p_n):
        for r in range(3):
            normals[j, r] = rows[j, r]
            plane_u[j, r] = rows[j, 6 + r]
            plane_v[j, r] = rows[j, 9 + r]
        offsets[j] = rows[j, 3]
        sigma_plane[j] = rows[j, 4]
        rate = drift_rate_vertical if horizontal[j] else drift_rate
        sig_drift[j] = min(rate * max(odometer - rows[j, 5], 0.0), max_drift_sigma)
        # the extent margin grown with the drift since the plane was seen (cells)
        dilate[j] = extent_margin_cells + min(int(3.0 * sig_drift[j] / cell_size), max_extra_cells)
    if child_margin_cells >= 0:
        for q in range(child_rows.shape[0]):
            dilate[child_rows[q]] = child_margin_cells
    start, cols, cells, dist, sig_d2 = gate_pairs(
        centroid, direction, endpoints, sigma_centroid, sigma_direction, seg_range, origin, normals, offsets,
        sigma_plane, sig_drift, plane_u, plane_v, cell_size, sigma_pose, sigma_rotation, sigma_lever,
        max_endpoint_distance, chi2)
    pair_ids = np.empty(cols.shape[0], dtype=np.int64)
    pair_dilate = np.empty(cols.shape[0], dtype=np.int64)
    for i in range(cols.shape[0]):
        pair_ids[i] = ids[cols[i]]
        pair_dilate[i] = dilate[cols[i]]
    return start, cols, cells, dist, sig_d2, pair_ids, pair_dilate


@nb.njit(cache=True)
def decide(
    start: IntArray, cols: IntArray, near: BoolArray, keep: BoolArray, shadow: BoolArray, dist: FloatArray,
    sig_d2: FloatArray, rows: FloatArray, ids: IntArray, same_normal: float, with_choice: bool, veto: bool,
    sigma_own: FloatArray, weight: FloatArray, seg_range: FloatArray, arm: FloatArray, hosts: BoolArray,
    has_hosts: bool, rel2: float, host2: float, sp2: float, gate: float, sigma_lever: float, host_lever: float,
    cos_min: float, log_ratio: float, outlier_nats: float, walls_only: bool, model: bool, two: float,
) -> tuple[IntArray, BoolArray]:
    """The association of one scan's segments from their candidate pairs (:func:`scan_pairs`):
    with the choice (``with_choice``) among the pairs over their extents as the choice takes
    them (``keep``, ``shadow``; :func:`choose_columns` with the scalars it documents), its plane ids and
    grows (``arm``, each centroid less the scanner's position, for the choice's ``model`` outside
    the veto); as a ``veto``, or without the choice, :func:`nearest_unambiguous` among the pairs over
    their extents (``near``), kept where the choice agrees. Returns per segment its plane id
    (``NONE``, ``HELD``) and whether it may grow the plane's extent."""
    k_n = start.shape[0] - 1
    normals = np.ascontiguousarray(rows[:, 0:3])
    chosen = np.full(k_n, NONE, dtype=np.int64)
    if with_choice:
        column, grows = choose_columns(start, cols, keep, shadow, dist, sigma_own, weight, seg_range, True, arm,
                                       not veto, normals, hosts, has_hosts, rel2, host2, sp2, gate, sigma_lever,
                                       host_lever, cos_min, log_ratio, outlier_nats, walls_only, model, two)
        for k in range(k_n):
            chosen[k] = ids[column[k]] if column[k] >= 0 else column[k]
            grows[k] = grows[k] and column[k] >= 0
        if not veto:
            return chosen, grows
    out = nearest_unambiguous(start, cols, near, dist, sig_d2, normals, ids, same_normal)
    grows = np.empty(k_n, dtype=np.bool_)
    for k in range(k_n):
        if with_choice and out[k] != chosen[k]:
            out[k] = NONE  # the choice as a veto: the nearest candidate where the choice agrees
        grows[k] = out[k] >= 0
    return out, grows


@nb.njit(cache=True)
def _end_gap(endpoints: FloatArray, a: int, b: int) -> float:
    """The least distance (m) between an end point of segment ``a`` and one of segment ``b``."""
    best = np.inf
    for p in range(2):
        for q in range(2):
            d2 = 0.0
            for r in range(3):
                e = endpoints[a, p, r] - endpoints[b, q, r]
                d2 += e * e
            best = min(best, d2)
    return math.sqrt(best)


@nb.njit(cache=True)
def local_steps(out: IntArray, grows: BoolArray, dist: FloatArray, ids: IntArray, walls: BoolArray,
                normals: FloatArray, same_normal: float, endpoints: FloatArray, centroid: FloatArray,
                sigma_own: FloatArray, weight: FloatArray, reach: float, gate: float, flat2: float,
                lever: float) -> int:
    """The local step test (``parallel_choice.ChoiceParams.local_reach``) on one scan's
    association ``out`` (plane ids per segment; changed in place with ``grows``): a segment ``k``
    given to a wall ``c`` (``walls`` (P,) over the columns of ``ids``, ``normals`` (P, 3) and
    ``dist`` (k, P), the signed centroid distances) is compared with each other segment ``j`` of
    the scan given to that wall or to a wall parallel to it (normals' cosine above
    ``same_normal``: a young duplicate of the wall awaiting its merge) whose end points lie within
    ``reach`` of its own (``endpoints`` (k, 2, 3), world frame), both measured from ``c``. The
    scan's pose error shifts both alike, so their difference ``dist[k] - dist[j]`` has the sigma of
    their own lines (``sigma_own``), the wall's flatness (``flat2``, squared) and the rotation's
    lever over their separation only. Where it exceeds ``gate`` sigmas and ``j`` lies nearer the
    wall both by its offset in this scan (the point-weighted median of the distances from ``c`` of
    the segments on ``c`` and its parallels within ``_LOCAL_NEAR``, ``weight``) and by its
    distance from ``c``'s plane, ``k`` is off the wall: left to the pool (``NONE``). Returns how
    many were."""
    k_n = out.shape[0]
    col = np.full(k_n, -1, dtype=np.int64)
    for k in range(k_n):
        if out[k] >= 0:
            for j in range(ids.shape[0]):
                if ids[j] == out[k]:
                    if walls[j]:
                        col[k] = j
                    break
    rho = np.zeros(k_n)
    members = np.empty(k_n, dtype=np.int64)
    med = np.zeros(ids.shape[0])
    has_med = np.zeros(ids.shape[0], dtype=np.bool_)
    for k in range(k_n):
        c = col[k]
        if c < 0:
            continue
        if not has_med[c]:
            # the wall's offset in this scan: the point-weighted median of the distances from c
            # of the segments on c and on walls parallel to it near c (k itself among them)
            m = 0
            total = 0.0
            for j in range(k_n):
                if col[j] >= 0 and abs(dist[j, c]) < _LOCAL_NEAR and _parallel(normals, col[j], c, same_normal):
                    members[m] = j
                    m += 1
                    total += weight[j]
            order = np.argsort(dist[members[:m], c], kind="mergesort")
            acc = 0.0
            med[c] = dist[k, c] if m > 0 else np.nan  # none near the wall: k is its own reference
            for q in range(m):
                j = members[order[q]]
                acc += weight[j]
                if acc >= 0.5 * total:
                    med[c] = dist[j, c]
                    break
            has_med[c] = True
        rho[k] = dist[k, c] - med[c] if np.isfinite(med[c]) else 0.0
    off = np.zeros(k_n, dtype=np.bool_)
    for k in range(k_n):
        c = col[k]
        if c < 0:
            continue
        for j in range(k_n):
            # j nearer the wall both in this scan (its offset from the scan's median) and on the map
            # (its distance from the wall's plane): a door whose segment holds most of the scan's
            # points on the wall sets the median and must not send the wall's own segment away
            if j == k or col[j] < 0 or not _parallel(normals, col[j], c, same_normal):
                continue
            rj = dist[j, c] - (dist[k, c] - rho[k])
            if abs(rj) >= abs(rho[k]) or abs(dist[j, c]) >= abs(dist[k, c]):
                continue
            if _end_gap(endpoints, k, j) > reach:
                continue
            sep2 = 0.0
            for r in range(3):
                e = centroid[k, r] - centroid[j, r]
                sep2 += e * e
            s = math.sqrt(sigma_own[k] ** 2 + sigma_own[j] ** 2 + flat2 + lever * lever * sep2)
            if abs(dist[k, c] - dist[j, c]) > gate * s:
                off[k] = True
                break
    n_off = 0
    for k in range(k_n):
        if off[k]:
            out[k] = NONE
            grows[k] = False
            n_off += 1
    return n_off


_LOCAL_NEAR = 0.05  # m: a parallel wall's segment this near a wall counts towards its offset in the scan


@nb.njit(cache=True)
def _parallel(normals: FloatArray, a: int, b: int, same_normal: float) -> bool:
    """Whether planes ``a`` and ``b`` (rows of ``normals``) are one surface's direction: the same
    plane, or normals within the cosine ``same_normal``, same facing."""
    if a == b:
        return True
    return normals[a, 0] * normals[b, 0] + normals[a, 1] * normals[b, 1] + normals[a, 2] * normals[b, 2] > same_normal
