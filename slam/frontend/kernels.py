"""Compiled (numba) kernels of the front end: tracking's window normal equations and its
Gauss-Newton loop, association gates, segment summaries and extent cells.

They use the trajectory kernels of :mod:`slam.trajectory.kernels` for the interpolation between
knots (the same formulas, compiled into these loops).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from slam.trajectory.kernels import (
    _LOG_SMALL,
    _SERIES_MAX,
    _interpolated_into,
    exp_ab,
    interval_logs,
    place_uniform,
    so3_log_into,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]




@nb.njit(cache=True)
def window_normal_equations(
    T: FloatArray, knot_index: IntArray, alphas: FloatArray, points_body: FloatArray, normals: FloatArray,
    offsets: FloatArray, sigmas: FloatArray, huber_k: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Gauss-Newton terms of tracking's point-on-plane residuals on the window ``T`` (W, 4, 4).

    Point ``m`` (body frame) lies between knots ``knot_index[m]`` and ``+ 1`` at fraction
    ``alphas[m]``, on the world plane ``normals[m] . x + offsets[m] = 0``; its residual is
    ``r = (n . (R p + t) + d) / sigma`` and its Jacobian ``g (1 - alpha, alpha)`` on the right
    perturbations of the two knots, ``g = (p x R^T n, R^T n) / sigma``. Returns
    ``A = J^T W J`` (6W, 6W), ``b = J^T W r`` (6W,) and the Huber weights ``w`` (m,) (``huber_k``
    in sigmas): the products that ``refine_window`` formed with a dense Jacobian.
    """
    W = T.shape[0]
    n = 6 * W
    m = knot_index.shape[0]
    A = np.zeros((n, n))
    b = np.zeros(n)
    w_out = np.empty(m)
    phi = interval_logs(T, 0, W - 1)
    R = np.empty((3, 3))
    t = np.empty(3)
    E = np.empty((3, 3))
    g = np.empty(6)
    for k in range(m):
        i = knot_index[k]
        a = alphas[k]
        _interpolated_into(T, i, a, phi[i], E, R, t)
        px, py, pz = points_body[k, 0], points_body[k, 1], points_body[k, 2]
        nx, ny, nz = normals[k, 0], normals[k, 1], normals[k, 2]
        s = sigmas[k]
        wx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
        wy = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
        wz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
        r = (nx * wx + ny * wy + nz * wz + offsets[k]) / s
        ux = R[0, 0] * nx + R[1, 0] * ny + R[2, 0] * nz  # R^T n
        uy = R[0, 1] * nx + R[1, 1] * ny + R[2, 1] * nz
        uz = R[0, 2] * nx + R[1, 2] * ny + R[2, 2] * nz
        g[0] = (py * uz - pz * uy) / s
        g[1] = (pz * ux - px * uz) / s
        g[2] = (px * uy - py * ux) / s
        g[3], g[4], g[5] = ux / s, uy / s, uz / s
        ar = abs(r)
        w = 1.0 if ar <= huber_k else huber_k / max(ar, 1e-12)
        w_out[k] = w
        ca, cb = 1.0 - a, a
        waa, wab, wbb = w * ca * ca, w * ca * cb, w * cb * cb
        o = 6 * i
        for p in range(6):
            gp = g[p]
            b[o + p] += w * ca * gp * r
            b[o + 6 + p] += w * cb * gp * r
            for q in range(6):
                gg = gp * g[q]
                A[o + p, o + q] += waa * gg
                A[o + p, o + 6 + q] += wab * gg
                A[o + 6 + p, o + q] += wab * gg
                A[o + 6 + p, o + 6 + q] += wbb * gg
    return A, b, w_out


@nb.njit(cache=True)
def exp_abc(t: float) -> tuple[float, float, float]:
    """``A = sin t / t``, ``B = (1 - cos t) / t^2`` and ``C = (t - sin t) / t^3`` at an angle
    ``t`` >= 0 (rad), as ``slam.trajectory.interpolation.exp_coefficients``."""
    a, b = exp_ab(t)
    if t >= _SERIES_MAX:
        return a, b, (t - math.sin(t)) / (t * t * t)
    x = t * t
    c = 1.0 / 6.0 + x * (-1.0 / 120.0 + x * (1.0 / 5040.0 + x * (-1.0 / 362880.0 + x * (1.0 / 39916800.0 + x * (
        -1.0 / 6227020800.0 + x * (1.0 / 1307674368000.0))))))
    return a, b, c


@nb.njit(cache=True)
def se3_log_into(T: FloatArray, out: FloatArray) -> None:
    """Twist ``Log(T) = (omega, v)`` (6,) of a pose (4, 4) into ``out``: the formulas of
    ``slam.trajectory.interpolation.se3_log``, ``v = V^-1 t`` with ``V^-1 = I - K / 2 + e K^2``."""
    R = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            R[r, c] = T[r, c]
    phi = np.empty(3)
    so3_log_into(R, phi)
    fx, fy, fz = phi[0], phi[1], phi[2]
    th = math.sqrt(fx * fx + fy * fy + fz * fz)
    if th < _LOG_SMALL:
        e = 1.0 / 12.0 + th * th / 720.0
    else:
        e = (1.0 - th * math.sin(th) / (2.0 * (1.0 - math.cos(th)))) / (th * th)
    tx, ty, tz = T[0, 3], T[1, 3], T[2, 3]
    cx, cy, cz = fy * tz - fz * ty, fz * tx - fx * tz, fx * ty - fy * tx  # K t
    out[0], out[1], out[2] = fx, fy, fz
    out[3] = tx - 0.5 * cx + e * (fy * cz - fz * cy)
    out[4] = ty - 0.5 * cy + e * (fz * cx - fx * cz)
    out[5] = tz - 0.5 * cz + e * (fx * cy - fy * cx)


@nb.njit(cache=True)
def se3_exp_into(xi: FloatArray, out: FloatArray) -> None:
    """Pose ``Exp(xi)`` (4, 4) of a twist ``xi = (omega, v)`` (6,) into ``out``: the formulas of
    ``slam.trajectory.interpolation.se3_exp``, ``t = V v`` with ``V = I + B K + C K^2``."""
    fx, fy, fz = xi[0], xi[1], xi[2]
    a, b, c = exp_abc(math.sqrt(fx * fx + fy * fy + fz * fz))
    E = np.empty((3, 3))
    xx, yy, zz = fx * fx, fy * fy, fz * fz
    E[0, 0] = 1.0 - b * (yy + zz)
    E[1, 1] = 1.0 - b * (xx + zz)
    E[2, 2] = 1.0 - b * (xx + yy)
    bxy, bxz, byz = b * fx * fy, b * fx * fz, b * fy * fz
    E[0, 1], E[1, 0] = bxy - a * fz, bxy + a * fz
    E[0, 2], E[2, 0] = bxz + a * fy, bxz - a * fy
    E[1, 2], E[2, 1] = byz - a * fx, byz + a * fx
    vx, vy, vz = xi[3], xi[4], xi[5]
    cx, cy, cz = fy * vz - fz * vy, fz * vx - fx * vz, fx * vy - fy * vx  # K v
    for r in range(3):
        for q in range(3):
            out[r, q] = E[r, q]
        out[3, r] = 0.0
    out[0, 3] = vx + b * cx + c * (fy * cz - fz * cy)
    out[1, 3] = vy + b * cy + c * (fz * cx - fx * cz)
    out[2, 3] = vz + b * cz + c * (fx * cy - fy * cx)
    out[3, 3] = 1.0


@nb.njit(cache=True)
def _inverse(T: FloatArray) -> FloatArray:
    """Inverse (4, 4) of a pose (4, 4)."""
    out = np.zeros((4, 4))
    for r in range(3):
        for c in range(3):
            out[r, c] = T[c, r]
        out[r, 3] = -(T[0, r] * T[0, 3] + T[1, r] * T[1, 3] + T[2, r] * T[2, 3])
    out[3, 3] = 1.0
    return out


@nb.njit(cache=True)
def _add_prior(A: FloatArray, b: FloatArray, knots: tuple[int, ...], coefs: tuple[float, ...], wt: FloatArray,
               e: FloatArray) -> None:
    """Gauss-Newton terms of a diagonal-weight (``wt`` (6,)) prior residual ``e`` (6,) on the
    knots ``knots`` with the perturbation coefficients ``coefs``, in place in ``A``, ``b``."""
    for i in range(len(knots)):
        oi, ci = 6 * knots[i], coefs[i]
        for j in range(6):
            b[oi + j] += ci * wt[j] * e[j]
        for k in range(len(knots)):
            ok, ck = 6 * knots[k], coefs[k]
            for j in range(6):
                A[oi + j, ok + j] += ci * ck * wt[j]


@nb.njit(cache=True)
def refine_window(
    T_knots: FloatArray, knot_index: IntArray, alphas: FloatArray, points_body: FloatArray, normals: FloatArray,
    offsets: FloatArray, sigmas: FloatArray, w_first: FloatArray, w_stay: FloatArray, w_motion: FloatArray,
    increments: bool, freeze: bool, degenerate_ratio: float, freeze_sigma: float, iterations: int, huber_k: float,
) -> FloatArray:
    """Tracking's windowed Gauss-Newton (``slam.frontend.tracking.refine_window``, which documents
    the model) in one compiled call: the knots (W, 4, 4) refined against the fixed world planes.

    ``w_first``, ``w_stay`` (6,) are the information of the first knot's prior and of every later
    knot's pull to its given pose; ``w_motion`` (6,) that of the motion prior, on each interval's
    relative pose against the given one with ``increments``, else on the change of the body twist
    between consecutive intervals (constant velocity). With ``freeze`` the translation is held at
    the given poses (``freeze_sigma``, m) along the world directions whose point information is
    below ``degenerate_ratio`` of the largest. Returns the refined knots, rotations
    orthonormalised.
    """
    W = T_knots.shape[0]
    n = 6 * W
    T = T_knots.copy()
    given_inv = np.empty((W, 4, 4))
    for k in range(W):
        given_inv[k] = _inverse(T_knots[k])
    given_increment_inv = np.empty((max(W - 1, 0), 4, 4))
    for k in range(W - 1):
        given_increment_inv[k] = _inverse(given_inv[k] @ T_knots[k + 1])
    e = np.empty(6)
    twist = np.empty((max(W - 1, 0), 6))
    step = np.empty((4, 4))
    delta = np.empty(n)
    fs2 = freeze_sigma * freeze_sigma
    for _ in range(iterations):
        A, b, w = window_normal_equations(T, knot_index, alphas, points_body, normals, offsets, sigmas, huber_k)
        # every knot against its given pose: the first with its prior, the later ones weakly
        for k in range(W):
            se3_log_into(given_inv[k] @ T[k], e)
            _add_prior(A, b, (k,), (1.0,), w_first if k == 0 else w_stay, e)
        if freeze:
            M = np.zeros((3, 3))
            for q in range(normals.shape[0]):
                info = w[q] / (sigmas[q] * sigmas[q])
                for r in range(3):
                    for c in range(3):
                        M[r, c] += info * normals[q, r] * normals[q, c]
            lam, vec = np.linalg.eigh(M)
            floor = degenerate_ratio * max(lam[2], 1e-300)
            for ev in range(3):
                if not lam[ev] < floor:
                    continue
                dw = vec[:, ev]
                for k in range(W):
                    o = 6 * k + 3
                    db = np.empty(3)  # the direction in knot k's body frame
                    for r in range(3):
                        db[r] = T[k, 0, r] * dw[0] + T[k, 1, r] * dw[1] + T[k, 2, r] * dw[2]
                    shift = dw[0] * (T[k, 0, 3] - T_knots[k, 0, 3]) + dw[1] * (T[k, 1, 3] - T_knots[k, 1, 3]) + dw[2] * (
                        T[k, 2, 3] - T_knots[k, 2, 3])
                    for r in range(3):
                        b[o + r] += db[r] * shift / fs2
                        for c in range(3):
                            A[o + r, o + c] += db[r] * db[c] / fs2
        if increments:
            # each interval's relative pose held to the given one: d e / d delta_k ~ I,
            # d e / d delta_{k-1} ~ -I (intervals of a few centimetres)
            for k in range(W - 1):
                se3_log_into(given_increment_inv[k] @ (_inverse(T[k]) @ T[k + 1]), e)
                _add_prior(A, b, (k, k + 1), (-1.0, 1.0), w_motion, e)
        elif W > 2:
            # constant velocity: the change of the body twist between consecutive intervals
            for k in range(W - 1):
                se3_log_into(_inverse(T[k]) @ T[k + 1], twist[k])
            for k in range(W - 2):
                _add_prior(A, b, (k, k + 1, k + 2), (1.0, -2.0, 1.0), w_motion, twist[k + 1] - twist[k])
        for i in range(n):
            A[i, i] += 1e-9
        try:
            delta[:] = -np.linalg.solve(A, b)
        except Exception:  # a singular system (numba raises LinAlgError as a plain exception)
            break
        for k in range(W):
            se3_exp_into(delta[6 * k : 6 * k + 6], step)
            T[k] = T[k] @ step
        if np.abs(delta).max() < 1e-7:
            break
    for k in range(W):
        u, _, vt = np.linalg.svd(np.ascontiguousarray(T[k, :3, :3]))
        T[k, :3, :3] = u @ vt
        T[k, 3, :3] = 0.0
        T[k, 3, 3] = 1.0
    return T


@nb.njit(inline="always")
def pair_gate(
    dc: float, sa: float, ends: FloatArray, nx: float, ny: float, nz: float, d: float, sigma_centroid: float,
    sigma_direction: float, seg_range: float, sigma_plane: float, sigma_drift: float, sigma_pose: float,
    sigma_rotation: float, sigma_lever: float, max_endpoint_distance: float,
) -> tuple[float, float, float, float, float]:
    """One (segment, plane) pair's gate terms (world frame): from the centroid's signed distance
    ``dc`` and the direction's sine ``sa`` against the plane (normal ``nx, ny, nz``, offset ``d``),
    the centroid's variance ``s2`` (m^2), the squared Mahalanobis distance ``m2``, the end points'
    (``ends`` (2, 3)) distances ``e0``, ``e1`` and their cap (m)."""
    lever = (sigma_lever * seg_range) ** 2
    s2 = sigma_centroid**2 + sigma_plane**2 + sigma_pose**2 + lever + sigma_drift**2
    a2 = sigma_direction**2 + sigma_rotation**2 + (sigma_drift / 5.0) ** 2
    m2 = dc**2 / s2 + sa**2 / a2
    e0 = abs(nx * ends[0, 0] + ny * ends[0, 1] + nz * ends[0, 2] + d)
    e1 = abs(nx * ends[1, 0] + ny * ends[1, 1] + nz * ends[1, 2] + d)
    cap = max_endpoint_distance + 3.0 * sigma_drift + 3.0 * sigma_lever * seg_range
    return s2, m2, e0, e1, cap


@nb.njit(cache=True)
def association_gates(
    centroid: FloatArray, direction: FloatArray, endpoints: FloatArray, sigma_centroid: FloatArray,
    sigma_direction: FloatArray, seg_range: FloatArray, origin: FloatArray, normals: FloatArray, offsets: FloatArray,
    sigma_plane: FloatArray, sigma_drift: FloatArray, plane_u: FloatArray, plane_v: FloatArray, cell_size: float,
    sigma_pose: float, sigma_rotation: float, sigma_lever: float, max_endpoint_distance: float, chi2: float,
) -> tuple[NDArray[np.bool_], FloatArray, FloatArray, FloatArray, IntArray, IntArray, IntArray]:
    """The per-pair tests of ``slam.frontend.association.associate`` for k world segments against
    P planes (world frame), which documents them.

    Segments: centroids, unit directions (k, 3), end points (k, 2, 3), the centroid's and the
    direction's sigmas (k,) (m, rad), ranges from the scanner (k,) (m) and the scanner's position
    ``origin`` (3,). Planes: ``normals`` (P, 3), ``offsets`` (P,), offset sigmas and drift sigmas
    (P,) (m), in-plane axes ``plane_u``, ``plane_v`` (P, 3) and the extent's ``cell_size`` (m).
    Returns ``ok`` (k, P), whether the pair passes the chi-square, end-point and facing gates,
    the squared Mahalanobis distance ``m2`` (k, P), the centroid's signed distance ``dist`` (k, P)
    and its variance ``sig_d2`` (k, P) (m^2), the extent cells ``cells`` (k, P, 3, 2) of the
    two end points and the centroid in each plane's (u, v) frame, and per segment its
    ``count`` (k,) passing planes, ``order[k, :count[k]]`` (k, P), by increasing ``m2``.
    """
    k_n, p_n = centroid.shape[0], normals.shape[0]
    ok = np.zeros((k_n, p_n), dtype=np.bool_)
    m2 = np.empty((k_n, p_n))
    dist = np.empty((k_n, p_n))
    sig_d2 = np.empty((k_n, p_n))
    cells = np.empty((k_n, p_n, 3, 2), dtype=np.int64)
    pts = np.empty((3, 3))
    for j in range(p_n):
        nx, ny, nz, d = normals[j, 0], normals[j, 1], normals[j, 2], offsets[j]
        # map normals face the side they were seen from: the scanner must be on that side
        facing = nx * origin[0] + ny * origin[1] + nz * origin[2] + d > 0.0
        sd = sigma_drift[j]
        for k in range(k_n):
            c = centroid[k]
            dc = nx * c[0] + ny * c[1] + nz * c[2] + d
            sa = abs(nx * direction[k, 0] + ny * direction[k, 1] + nz * direction[k, 2])
            s2, mk, e0, e1, cap = pair_gate(dc, sa, endpoints[k], nx, ny, nz, d, sigma_centroid[k], sigma_direction[k],
                                            seg_range[k], sigma_plane[j], sd, sigma_pose, sigma_rotation, sigma_lever,
                                            max_endpoint_distance)
            ok[k, j] = (mk < chi2) and (e0 < cap) and (e1 < cap) and facing
            m2[k, j], dist[k, j], sig_d2[k, j] = mk, dc, s2
            pts[0], pts[1], pts[2] = endpoints[k, 0], endpoints[k, 1], c
            for q in range(3):
                pu = pts[q, 0] * plane_u[j, 0] + pts[q, 1] * plane_u[j, 1] + pts[q, 2] * plane_u[j, 2]
                pv = pts[q, 0] * plane_v[j, 0] + pts[q, 1] * plane_v[j, 1] + pts[q, 2] * plane_v[j, 2]
                cells[k, j, q, 0] = int(np.floor(pu / cell_size))
                cells[k, j, q, 1] = int(np.floor(pv / cell_size))
    order = np.empty((k_n, p_n), dtype=np.int64)
    count = np.zeros(k_n, dtype=np.int64)
    for k in range(k_n):
        c_n = 0
        for j in range(p_n):
            if not ok[k, j]:
                continue
            # insertion by increasing m2 (few candidates), after the equal ones
            q = c_n
            while q > 0 and m2[k, order[k, q - 1]] > m2[k, j]:
                order[k, q] = order[k, q - 1]
                q -= 1
            order[k, q] = j
            c_n += 1
        count[k] = c_n
    return ok, m2, dist, sig_d2, cells, order, count


@nb.njit(cache=True)
def segment_summaries(
    virtual_world: FloatArray, endpoints_world: FloatArray, virtual_sigma: FloatArray, point_sigma: float,
    n_points: IntArray, origin: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The arrays of ``slam.frontend.association.world_segments`` for k segments placed in the
    world: centroids of the two virtual points (k, 3), unit directions of the end points (k, 3),
    the centroid's sigma (k,) (m, the virtual points' ``virtual_sigma`` over sqrt 2), the total
    least squares direction sigma ``point_sigma / (L sqrt(n / 12))`` (k,) (rad) and the range from
    the scanner at ``origin`` (3,) (k,) (m). Inputs: virtual points and end points (k, 2, 3)
    (world frame), ``virtual_sigma`` (k,) (m), the segments' point counts ``n_points`` (k,)."""
    k_n = virtual_world.shape[0]
    c = np.empty((k_n, 3))
    u = np.empty((k_n, 3))
    sig_c = np.empty(k_n)
    sig_dir = np.empty(k_n)
    rng = np.empty(k_n)
    root2 = math.sqrt(2.0)
    for k in range(k_n):
        ss = 0.0
        dd = 0.0
        for r in range(3):
            c[k, r] = (virtual_world[k, 0, r] + virtual_world[k, 1, r]) / 2.0
            u[k, r] = endpoints_world[k, 1, r] - endpoints_world[k, 0, r]
            ss += u[k, r] * u[k, r]
            dd += (c[k, r] - origin[r]) ** 2
        length = math.sqrt(ss)
        scale = max(length, 1e-9)
        for r in range(3):
            u[k, r] /= scale
        # TLS direction error: sigma / sqrt(sum s_i^2), sum s_i^2 ~ n L^2 / 12
        sig_dir[k] = point_sigma / max(length * math.sqrt(n_points[k] / 12.0), 1e-9)
        sig_c[k] = virtual_sigma[k] / root2
        rng[k] = math.sqrt(dd)
    return c, u, sig_c, sig_dir, rng


@nb.njit(cache=True)
def subsample_rows(offsets: IntArray, n_points: IntArray, js: IntArray, per: IntArray) -> tuple[IntArray, IntArray]:
    """Rows of every ``max(1, n // per)``-th point of the segments ``js`` (their points are rows
    ``offsets[j]`` to ``offsets[j + 1] - 1``, ``n_points[j]`` of them; ``per`` one per segment of
    ``js``), concatenated, and the split positions (len(js) - 1,) between the segments."""
    total = 0
    for q in range(js.shape[0]):
        j = js[q]
        step = max(1, n_points[j] // per[q])
        total += (offsets[j + 1] - offsets[j] + step - 1) // step
    rows = np.empty(total, dtype=np.int64)
    splits = np.empty(max(js.shape[0] - 1, 0), dtype=np.int64)
    o = 0
    for q in range(js.shape[0]):
        j = js[q]
        step = max(1, n_points[j] // per[q])
        for i in range(offsets[j], offsets[j + 1], step):
            rows[o] = i
            o += 1
        if q < js.shape[0] - 1:
            splits[q] = o
    return rows, splits


@nb.njit(cache=True)
def place_subsampled(T: FloatArray, t0: float, dt: float, n_knots: int, offsets: IntArray, n_points: IntArray,
                     js: IntArray, per: IntArray, points_body: FloatArray,
                     times: FloatArray) -> tuple[FloatArray, IntArray]:
    """The rows :func:`subsample_rows` picks of the segments ``js`` (every ``max(1, n // per)``-th
    point; ``offsets``, ``n_points`` the scan's), placed in the world frame with the uniform knots
    (``slam.trajectory.kernels.place_uniform`` of ``T`` (K, 4, 4), ``t0 + k dt``, ``n_knots``),
    from the scan's ``points_body`` (n, 3) and ``times`` (n,): the points (m, 3) and each
    segment's start row (len(js) + 1,: the last is m). ``KnotMirror.place_segments_flat`` in one call."""
    sel, splits = subsample_rows(offsets, n_points, js, per)
    m = sel.shape[0]
    pts = np.empty((m, 3))
    t = np.empty(m)
    for k in range(m):
        i = sel[k]
        pts[k, 0], pts[k, 1], pts[k, 2] = points_body[i, 0], points_body[i, 1], points_body[i, 2]
        t[k] = times[i]
    placed = place_uniform(T, t0, dt, n_knots, t, pts)
    bounds = np.empty(js.shape[0] + 1, dtype=np.int64)
    bounds[0] = 0
    bounds[1:-1] = splits
    bounds[-1] = m
    return placed, bounds


@nb.njit(cache=True)
def plane_cells(points_world: FloatArray, u: FloatArray, v: FloatArray, cell_size: float) -> IntArray:
    """Extent cells (m, 2) of points (m, 3), world frame, in a plane's (u, v) frame (unit axes
    ``u``, ``v`` (3,), world frame): ``floor((p . u, p . v) / cell_size)``."""
    m = points_world.shape[0]
    out = np.empty((m, 2), dtype=np.int64)
    for k in range(m):
        x, y, z = points_world[k, 0], points_world[k, 1], points_world[k, 2]
        out[k, 0] = int(np.floor((x * u[0] + y * u[1] + z * u[2]) / cell_size))
        out[k, 1] = int(np.floor((x * v[0] + y * v[1] + z * v[2]) / cell_size))
    return out


@nb.njit(cache=True)
def near_cells(extent: IntArray, cells: IntArray, dilate: int) -> bool:
    """Whether any of the ``cells`` (q, 2) lies within ``dilate`` cells (Chebyshev distance, both
    axes) of any of the ``extent`` cells (n, 2): the dilated-extent test of
    ``slam.frontend.planemap.PlaneMap.overlaps`` as one pass over the extent."""
    for i in range(extent.shape[0]):
        eu, ev = extent[i, 0], extent[i, 1]
        for q in range(cells.shape[0]):
            if abs(eu - cells[q, 0]) <= dilate and abs(ev - cells[q, 1]) <= dilate:
                return True
    return False
