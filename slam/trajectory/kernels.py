"""Compiled (numba) kernels placing body points in the world with the knot trajectory.

Placing body points in the world (``slam.trajectory.placement``, the runner's pose mirror) is a
few dozen flops per point, for which numpy's per-call overhead (tens of small array operations
per call, thousands of calls per scan) was most of the cost. These loops compute the same
formulas as the numpy functions of :mod:`slam.trajectory.interpolation` in one pass over the
points; they agree with them to rounding (~1e-15 relative, tested in tests/test_frontend.py),
not to the last bit, since sums are taken in another order. They are deterministic: the same
input gives the same output.

Between knots ``T_i`` and ``T_i+1`` (``T_world_body``, (K, 4, 4)) the rotation follows the
geodesic and the position the straight line (``slam.trajectory.interpolation.interpolate_poses``)::

    R(alpha) = R_i Exp(alpha Log(R_i^T R_i+1)),   p(alpha) = p_i + alpha (p_i+1 - p_i).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_SERIES_MAX = 0.5  # rad, as slam.trajectory.interpolation.exp_coefficients: power series below, closed forms above
_LOG_SMALL = 1e-4  # rad, as slam.trajectory.interpolation.so3_log: Taylor series of theta / (2 sin theta) below
_NEAR_PI = math.pi - 0.1  # rad, above this so3_log takes the quaternion route


@nb.njit(cache=True)
def exp_ab(t: float) -> tuple[float, float]:
    """``A = sin t / t`` and ``B = (1 - cos t) / t^2`` at an angle ``t`` >= 0 (rad): the first two
    coefficients of ``slam.trajectory.interpolation.exp_coefficients`` (seven-term series in ``t^2`` below
    0.5 rad, closed forms above)."""
    if t >= _SERIES_MAX:
        return math.sin(t) / t, (1.0 - math.cos(t)) / (t * t)
    x = t * t
    # Horner form of sum_k (-1)^k x^k / (2k+1)!  and  sum_k (-1)^k x^k / (2k+2)!, k = 0..6
    a = 1.0 + x * (-1.0 / 6.0 + x * (1.0 / 120.0 + x * (-1.0 / 5040.0 + x * (1.0 / 362880.0 + x * (
        -1.0 / 39916800.0 + x * (1.0 / 6227020800.0))))))
    b = 0.5 + x * (-1.0 / 24.0 + x * (1.0 / 720.0 + x * (-1.0 / 40320.0 + x * (1.0 / 3628800.0 + x * (
        -1.0 / 479001600.0 + x * (1.0 / 87178291200.0))))))
    return a, b


@nb.njit(cache=True)
def _quaternion_log(R: FloatArray, out: FloatArray) -> None:
    """``Log(R)`` into ``out`` (3,) through the unit quaternion (Markley's choice of the largest
    diagonal term, then ``2 atan2(|v|, w)``): scipy's ``Rotation.from_matrix(R).as_rotvec()``,
    exact near pi where the closed form of :func:`so3_log_into` loses precision."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    q = np.empty(4)
    i = 0
    best = R[0, 0]
    for c in range(1, 3):
        if R[c, c] > best:
            best, i = R[c, c], c
    if tr > best:
        q[0] = R[2, 1] - R[1, 2]
        q[1] = R[0, 2] - R[2, 0]
        q[2] = R[1, 0] - R[0, 1]
        q[3] = 1.0 + tr
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        q[i] = 1.0 - tr + 2.0 * R[i, i]
        q[j] = R[j, i] + R[i, j]
        q[k] = R[k, i] + R[i, k]
        q[3] = R[k, j] - R[j, k]
    nq = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    s = 1.0 / nq if q[3] >= 0.0 else -1.0 / nq
    x, y, z, w = q[0] * s, q[1] * s, q[2] * s, q[3] * s
    nv = math.sqrt(x * x + y * y + z * z)
    angle = 2.0 * math.atan2(nv, w)
    if angle <= 1e-3:
        a2 = angle * angle
        scale = 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0
    else:
        scale = angle / math.sin(angle / 2.0)
    out[0], out[1], out[2] = scale * x, scale * y, scale * z


@nb.njit(cache=True)
def so3_log_into(R: FloatArray, out: FloatArray) -> None:
    """Rotation vector ``Log(R)`` (3,) of a rotation matrix (3, 3) into ``out``: the formulas of
    ``slam.trajectory.interpolation.so3_log`` (closed form, Taylor series below 1e-4 rad, quaternion route
    within 0.1 rad of pi)."""
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    theta = math.acos(min(1.0, max(-1.0, c)))
    if theta > _NEAR_PI:
        _quaternion_log(R, out)
        return
    if theta < _LOG_SMALL:
        f = 0.5 + theta * theta / 12.0
    else:
        f = theta / (2.0 * math.sin(theta))
    out[0] = f * (R[2, 1] - R[1, 2])
    out[1] = f * (R[0, 2] - R[2, 0])
    out[2] = f * (R[1, 0] - R[0, 1])


@nb.njit(cache=True)
def interval_logs(T: FloatArray, lo: int, hi: int) -> FloatArray:
    """Rotation vectors ``Log(R_i^T R_i+1)`` (hi - lo, 3) of the knot intervals ``lo <= i < hi``
    of the knots ``T`` (K, 4, 4), body frame of knot ``i``."""
    out = np.empty((max(hi - lo, 0), 3))
    D = np.empty((3, 3))
    for i in range(lo, hi):
        for r in range(3):
            for c in range(3):
                D[r, c] = T[i, 0, r] * T[i + 1, 0, c] + T[i, 1, r] * T[i + 1, 1, c] + T[i, 2, r] * T[i + 1, 2, c]
        so3_log_into(D, out[i - lo])
    return out


@nb.njit(cache=True)
def _exp_into(vx: float, vy: float, vz: float, E: FloatArray) -> None:
    """``Exp(v)`` (3, 3) of the rotation vector ``v`` into ``E``: ``I + A [v]x + B [v]x^2``."""
    a, b = exp_ab(math.sqrt(vx * vx + vy * vy + vz * vz))
    xx, yy, zz = vx * vx, vy * vy, vz * vz
    E[0, 0] = 1.0 - b * (yy + zz)
    E[1, 1] = 1.0 - b * (xx + zz)
    E[2, 2] = 1.0 - b * (xx + yy)
    bxy, bxz, byz = b * vx * vy, b * vx * vz, b * vy * vz
    E[0, 1] = bxy - a * vz
    E[1, 0] = bxy + a * vz
    E[0, 2] = bxz + a * vy
    E[2, 0] = bxz - a * vy
    E[1, 2] = byz - a * vx
    E[2, 1] = byz + a * vx


@nb.njit(cache=True)
def _interpolated_into(T: FloatArray, i: int, a: float, phi: FloatArray, E: FloatArray,
                       R: FloatArray, t: FloatArray) -> None:
    """Rotation ``R`` (3, 3) and position ``t`` (3,) of ``T_world_body`` a fraction ``a`` of the way
    from knot ``i`` to ``i + 1`` of ``T`` (K, 4, 4), with the interval's rotation vector ``phi``
    (3,); ``E`` (3, 3) is scratch."""
    _exp_into(a * phi[0], a * phi[1], a * phi[2], E)
    for r in range(3):
        r0, r1, r2 = T[i, r, 0], T[i, r, 1], T[i, r, 2]
        for c in range(3):
            R[r, c] = r0 * E[0, c] + r1 * E[1, c] + r2 * E[2, c]
        p0 = T[i, r, 3]
        t[r] = p0 + a * (T[i + 1, r, 3] - p0)


@nb.njit(cache=True)
def _interval_log_into(T: FloatArray, i: int, D: FloatArray, phi: FloatArray) -> None:
    """``phi = Log(R_i^T R_{i+1})`` of knot interval ``i`` (``D`` is scratch, 3x3)."""
    for r in range(3):
        for c in range(3):
            D[r, c] = T[i, 0, r] * T[i + 1, 0, c] + T[i, 1, r] * T[i + 1, 1, c] + T[i, 2, r] * T[i + 1, 2, c]
    so3_log_into(D, phi)


@nb.njit(cache=True)
def interval_poses(T: FloatArray, idx: IntArray, alpha: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotations (m, 3, 3) and positions (m, 3) of ``T_world_body`` at the fractions ``alpha`` (m,)
    of the knot intervals ``idx`` (m,) of the knots ``T`` (K, 4, 4); one rotation logarithm per
    run of equal intervals."""
    m = idx.shape[0]
    R = np.empty((m, 3, 3))
    t = np.empty((m, 3))
    phi = np.empty(3)
    E = np.empty((3, 3))
    D = np.empty((3, 3))
    last = -1
    for k in range(m):
        i = idx[k]
        if i != last:
            _interval_log_into(T, i, D, phi)
            last = i
        _interpolated_into(T, i, alpha[k], phi, E, R[k], t[k])
    return R, t


@nb.njit(cache=True)
def place(T: FloatArray, idx: IntArray, alpha: FloatArray, points_body: FloatArray) -> FloatArray:
    """World points (m, 3) of body points (m, 3) seen at the fractions ``alpha`` (m,) of the knot
    intervals ``idx`` (m,) of the knots ``T`` (K, 4, 4): ``R(alpha) p + t(alpha)``, with one
    rotation logarithm per run of equal intervals and the exponential applied to the point
    (Rodrigues) instead of built as a matrix."""
    m = idx.shape[0]
    out = np.empty((m, 3))
    phi = np.empty(3)
    D = np.empty((3, 3))
    last = -1
    for k in range(m):
        i = idx[k]
        if i != last:
            _interval_log_into(T, i, D, phi)
            last = i
        a = alpha[k]
        vx, vy, vz = a * phi[0], a * phi[1], a * phi[2]
        A, B = exp_ab(math.sqrt(vx * vx + vy * vy + vz * vz))
        px, py, pz = points_body[k, 0], points_body[k, 1], points_body[k, 2]
        # Exp(v) p = p + A v x p + B v x (v x p)
        cx, cy, cz = vy * pz - vz * py, vz * px - vx * pz, vx * py - vy * px
        qx = px + A * cx + B * (vy * cz - vz * cy)
        qy = py + A * cy + B * (vz * cx - vx * cz)
        qz = pz + A * cz + B * (vx * cy - vy * cx)
        for r in range(3):
            p0 = T[i, r, 3]
            out[k, r] = T[i, r, 0] * qx + T[i, r, 1] * qy + T[i, r, 2] * qz + (p0 + a * (T[i + 1, r, 3] - p0))
    return out


@nb.njit(cache=True)
def uniform_fractions(t0: float, dt: float, n_knots: int, times: FloatArray) -> tuple[IntArray, FloatArray]:
    """Interval index and fraction (m,) of each time (m,) on knots ``t0 + k dt`` (``n_knots`` of
    them), clipped to the first and the last interval: the pipeline's ``_fractions``."""
    m = times.shape[0]
    idx = np.empty(m, dtype=np.int64)
    alpha = np.empty(m)
    top = max(n_knots - 2, 0)
    for k in range(m):
        x = (times[k] - t0) / dt
        i = min(max(int(np.floor(x)), 0), top)
        idx[k] = i
        alpha[k] = min(max(x - i, 0.0), 1.0)
    return idx, alpha


@nb.njit(cache=True)
def place_uniform(T: FloatArray, t0: float, dt: float, n_knots: int, times: FloatArray,
                  points_body: FloatArray) -> FloatArray:
    """World points (m, 3) of body points (m, 3) at their ``times`` (m,) on the uniform knots
    ``t0 + k dt`` (the first ``n_knots`` of ``T`` (K, 4, 4), ``T_world_body``)."""
    idx, alpha = uniform_fractions(t0, dt, n_knots, times)
    return place(T, idx, alpha, points_body)


@nb.njit(cache=True)
def pose_uniform(T: FloatArray, t0: float, dt: float, n_knots: int, time: float) -> FloatArray:
    """``T_world_body`` (4, 4) at ``time`` on the uniform knots ``t0 + k dt`` (the first
    ``n_knots`` of ``T`` (K, 4, 4))."""
    idx, alpha = uniform_fractions(t0, dt, n_knots, np.array([time]))
    R, t = interval_poses(T, idx, alpha)
    out = np.zeros((4, 4))
    out[:3, :3] = R[0]
    out[:3, 3] = t[0]
    out[3, 3] = 1.0
    return out


