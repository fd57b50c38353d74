"""Compiled (numba) kernel of the two-pose point-on-plane terms of :mod:`slam.backend.factors`.

The same formulas as ``point_plane_terms`` (see the module docstring of :mod:`slam.backend.factors`),
one loop over the points: a block holds few points (two virtual points per segment), for which
numpy's per-call overhead is most of the cost; the back end evaluates blocks tens of thousands
of times per run.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@nb.njit(cache=True)
def _coefficients(t: float) -> tuple[float, float, float]:
    """``sin t / t``, ``(1 - cos t) / t^2``, ``(t - sin t) / t^3`` without cancellation."""
    if t < 1e-3:
        t2 = t * t
        return 1.0 - t2 / 6.0 + t2 * t2 / 120.0, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, 1.0 / 6.0 - t2 / 120.0
    s, c = math.sin(t), math.cos(t)
    return s / t, (1.0 - c) / (t * t), (t - s) / (t * t * t)


@nb.njit(cache=True)
def _hat(v: FloatArray) -> FloatArray:
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2] = -v[2], v[1]
    K[1, 0], K[1, 2] = v[2], -v[0]
    K[2, 0], K[2, 1] = -v[1], v[0]
    return K


@nb.njit(cache=True)
def _log_so3(R: FloatArray) -> FloatArray:
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    c = min(1.0, max(-1.0, 0.5 * (tr - 1.0)))
    theta = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-4:
        return (0.5 + theta * theta / 12.0) * w
    return (theta / (2.0 * math.sin(theta))) * w


@nb.njit(cache=True)
def _relative_rotation(RaT: FloatArray, Rb: FloatArray) -> tuple[FloatArray, FloatArray, float, FloatArray,
                                                                  FloatArray, FloatArray]:
    """``D = Ra^T Rb``, ``phi = Log(D)``, ``|phi|``, ``hat(phi)``, its square and ``Jr(phi)^-1``."""
    D = RaT @ Rb
    phi = _log_so3(D)
    th = math.sqrt(phi[0] ** 2 + phi[1] ** 2 + phi[2] ** 2)
    K = _hat(phi)
    KK = K @ K
    if th < 1e-4:
        ci = 1.0 / 12.0 + th * th / 720.0
    else:
        ci = 1.0 / (th * th) - (1.0 + math.cos(th)) / (2.0 * th * math.sin(th))
    return D, phi, th, K, KK, np.eye(3) + 0.5 * K + ci * KK


@nb.njit(cache=True)
def two_pose_terms(
    Ra: FloatArray, ta: FloatArray, Rb: FloatArray, tb: FloatArray, n: FloatArray, dist: float,
    Bn: FloatArray, P: FloatArray, al: FloatArray, jacobians: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """(residuals (N,), H_a (N, 6), H_b (N, 6), H_plane (N, 3), m_k (N, 3), d res/d alpha (N,)) of
    body points ``P`` at fractions ``al`` between poses (Ra, ta), (Rb, tb) against the plane
    ``n . x + dist = 0`` (``Bn`` its normal's tangent basis, 3 x 2). Without ``jacobians`` only
    the residuals are filled."""
    N = P.shape[0]
    RaT = np.ascontiguousarray(Ra.T)  # contiguous operands for numba's matmul
    Rb = np.ascontiguousarray(Rb)
    Bn = np.ascontiguousarray(Bn)
    m_a = RaT @ n
    d0 = n[0] * ta[0] + n[1] * ta[1] + n[2] * ta[2] + dist
    D, phi, th, K, KK, Jinv = _relative_rotation(RaT, Rb)
    dtw = tb - ta
    dn = n[0] * dtw[0] + n[1] * dtw[1] + n[2] * dtw[2]
    RaTB = RaT @ Bn
    taB = ta @ Bn
    dtB = dtw @ Bn
    res = np.empty(N)
    Ha = np.zeros((N, 6))
    Hb = np.zeros((N, 6))
    Hp = np.ones((N, 3))
    mk = np.zeros((N, 3))
    dra = np.zeros(N)
    mD = m_a @ D
    for k in range(N):
        a = al[k]
        A, B, C = _coefficients(a * th)
        Aa, Ba2 = A * a, B * a * a
        E = np.eye(3) + Aa * K + Ba2 * KK  # Exp(a phi)
        p = P[k]
        q = E @ p
        res[k] = q[0] * m_a[0] + q[1] * m_a[1] + q[2] * m_a[2] + d0 + a * dn
        if not jacobians:
            continue
        m = E.T @ m_a
        mk[k] = m
        g = np.array([p[1] * m[2] - p[2] * m[1], p[2] * m[0] - p[0] * m[2], p[0] * m[1] - p[1] * m[0]])
        Jr = np.eye(3) - (B * a) * K + (C * a * a) * KK  # Jr(a phi)
        u = a * (g @ Jr) @ Jinv
        Eg = E @ g
        uDt = u @ D.T
        for j in range(3):
            Ha[k, j] = Eg[j] - uDt[j]
            Hb[k, j] = u[j]
            Ha[k, 3 + j] = (1.0 - a) * m_a[j]
            Hb[k, 3 + j] = a * mD[j]
        qB = q @ RaTB
        Hp[k, 0] = qB[0] + taB[0] + a * dtB[0]
        Hp[k, 1] = qB[1] + taB[1] + a * dtB[1]
        dra[k] = g[0] * phi[0] + g[1] * phi[1] + g[2] * phi[2] + dn
    return res, Ha, Hb, Hp, mk, dra


@nb.njit(cache=True, inline="always")
def _rho_w(e: float, kernel: int, k: float) -> tuple[float, float]:
    """Loss ``rho(e)`` and IRLS weight ``w(e)`` of a whitened residual: 0 none, 1 Huber, 2 Cauchy,
    3 Geman-McClure (``rho = k^2 e^2 / (2 (k^2 + e^2))``: a point far off weighs ~(k/e)^4, not
    Cauchy's (k/e)^2, so a wall's segments 1-2 cm off a board's plane stop tilting it)."""
    if kernel == 0:
        return 0.5 * e * e, 1.0
    x = abs(e)
    if kernel == 1:
        return (0.5 * e * e, 1.0) if x <= k else (k * x - 0.5 * k * k, k / x)
    if kernel == 2:
        u2 = (e / k) ** 2
        return 0.5 * k * k * math.log1p(u2), 1.0 / (1.0 + u2)
    q = k * k / (k * k + e * e)
    return 0.5 * e * e * q, q * q


@nb.njit(cache=True)
def robust_rows(e: FloatArray, kernel: int, k: float, linearize: bool) -> tuple[FloatArray, FloatArray]:
    """Compiled :func:`slam.backend.factors.robust_rows` for ``kernel`` (1 Huber, 2 Cauchy, 3 Geman-McClure) of
    threshold ``k``: the N + 1 rows and the IRLS scales ``sqrt(w)`` (N,) (empty unless
    ``linearize``). One pass; the numpy formulation costs ~30 us a block in ``np.where`` calls."""
    n = e.shape[0]
    out = np.empty(n + 1)
    sw = np.empty(n if linearize else 0)
    correction = 0.0
    for i in range(n):
        x = e[i]
        rho, w = _rho_w(x, kernel, k)
        if linearize:
            s = math.sqrt(w)
            sw[i] = s
            out[i] = s * x
            correction += rho - 0.5 * w * x * x
        else:
            r = math.sqrt(2.0 * rho)
            out[i] = r if x >= 0.0 else -r
    out[n] = math.sqrt(max(0.0, 2.0 * correction)) if linearize else 0.0
    return out, sw


@nb.njit(cache=True)
def group_rows(
    Ra: FloatArray, ta: FloatArray, Rb: FloatArray, tb: FloatArray, normals: FloatArray, dists: FloatArray,
    bases: FloatArray, anchors: FloatArray, plane: NDArray[np.int64], P: FloatArray, al: FloatArray,
    inv_s: FloatArray, kernel: int, k: float, linearize: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`group_rows_core` with the planes' rows ``normals`` (J, 3), ``dists`` (J,), ``bases``
    (J, 3, 2) in the factor's plane order."""
    slots = np.arange(normals.shape[0])
    return group_rows_core(Ra, ta, Rb, tb, normals, dists, bases, slots, anchors, plane, P, al, inv_s, kernel, k,
                           linearize)


@nb.njit(cache=True)
def group_rows_at(
    R: FloatArray, t: FloatArray, ia: int, ib: int, normals: FloatArray, dists: FloatArray, bases: FloatArray,
    slots: NDArray[np.int64], anchors: FloatArray, plane: NDArray[np.int64], P: FloatArray, al: FloatArray,
    inv_s: FloatArray, kernel: int, k: float, linearize: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`group_rows_core` with the poses read from tables: rotations ``R`` (K, 3, 3) and
    positions ``t`` (K, 3), knots ``ia`` and ``ib`` (:class:`slam.backend.factors.PlaneTable`)."""
    return group_rows_core(R[ia], t[ia], R[ib], t[ib], normals, dists, bases, slots, anchors, plane, P, al, inv_s,
                           kernel, k, linearize)


@nb.njit(cache=True)
def group_rows_core(
    Ra: FloatArray, ta: FloatArray, Rb: FloatArray, tb: FloatArray, normals: FloatArray, dists: FloatArray,
    bases: FloatArray, slots: NDArray[np.int64], anchors: FloatArray, plane: NDArray[np.int64], P: FloatArray,
    al: FloatArray, inv_s: FloatArray, kernel: int, k: float, linearize: bool,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The whitened rows of one knot interval's points on several planes (one factor).

    Point m (body frame ``P[m]`` at fraction ``al[m]`` between the poses (Ra, ta), (Rb, tb)) lies
    on the factor's plane ``j = plane[m]``: ``normals[i] . (x - anchors[j]) + dists[i] = 0`` with
    tangent basis ``bases[i]`` (3 x 2), ``i = slots[j]`` the plane's row in the tables. ``kernel``: 0 none, 1 Huber, 2 Cauchy of threshold ``k`` (sigmas).
    Returns (rows (N + r,), H_a (N + r, 6), H_b (N + r, 6), H_planes (J, N + r, 3)) with r = 1 for
    a robust kernel (:func:`robust_rows`'s correction row) else 0: the same rows, point for
    point, as one block per plane (:func:`two_pose_terms` and :func:`robust_rows`); a plane's
    Jacobian is zero on the other planes' rows. Without ``linearize`` only ``rows`` is filled
    (the robust residuals ``sign(e) sqrt(2 rho(e))``)."""
    N = P.shape[0]
    J = slots.shape[0]
    r = 0 if kernel == 0 else 1
    RaT = np.ascontiguousarray(Ra.T)
    Rb = np.ascontiguousarray(Rb)
    D, _phi, th, K, KK, Jinv = _relative_rotation(RaT, Rb)
    dtw = tb - ta
    # per plane: normal in knot a's body frame, offset at knot a, and the chained bases
    m_a = np.empty((J, 3))
    mD = np.empty((J, 3))
    d0 = np.empty(J)
    dn = np.empty(J)
    RaTB = np.empty((J, 3, 2))
    taB = np.empty((J, 2))
    dtB = np.empty((J, 2))
    for j in range(J):
        i = slots[j]
        n = np.ascontiguousarray(normals[i])
        Bn = np.ascontiguousarray(bases[i])
        m_a[j] = RaT @ n
        mD[j] = m_a[j] @ D
        tj = ta - anchors[j]
        d0[j] = n[0] * tj[0] + n[1] * tj[1] + n[2] * tj[2] + dists[i]
        dn[j] = n[0] * dtw[0] + n[1] * dtw[1] + n[2] * dtw[2]
        RaTB[j] = RaT @ Bn
        taB[j] = tj @ Bn
        dtB[j] = dtw @ Bn
    rows = np.empty(N + r)
    nr = N + r if linearize else 0
    Ha = np.zeros((nr, 6))
    Hb = np.zeros((nr, 6))
    Hp = np.zeros((J if linearize else 0, nr, 3))
    correction = 0.0
    E = np.empty((3, 3))
    Jr = np.empty((3, 3))
    q = np.empty(3)
    mk = np.empty(3)
    g = np.empty(3)
    gJ = np.empty(3)
    uu = np.empty(3)
    Eg = np.empty(3)
    for m in range(N):
        j = plane[m]
        a = al[m]
        A, B, C = _coefficients(a * th)
        ea, eb = A * a, B * a * a  # Exp(a phi) = I + ea K + eb K^2
        for r1 in range(3):
            for c in range(3):
                E[r1, c] = ea * K[r1, c] + eb * KK[r1, c] + (1.0 if r1 == c else 0.0)
        p0, p1, p2 = P[m, 0], P[m, 1], P[m, 2]
        for r1 in range(3):
            q[r1] = E[r1, 0] * p0 + E[r1, 1] * p1 + E[r1, 2] * p2
        e = (q[0] * m_a[j, 0] + q[1] * m_a[j, 1] + q[2] * m_a[j, 2] + d0[j] + a * dn[j]) * inv_s[m]
        rho, w = _rho_w(e, kernel, k)
        if not linearize:
            s = math.sqrt(2.0 * rho)
            rows[m] = s if e >= 0.0 else -s
            continue
        sw = math.sqrt(w)
        rows[m] = sw * e
        correction += rho - 0.5 * w * e * e
        f = sw * inv_s[m]
        for c in range(3):  # E^T m_a
            mk[c] = E[0, c] * m_a[j, 0] + E[1, c] * m_a[j, 1] + E[2, c] * m_a[j, 2]
        g[0] = p1 * mk[2] - p2 * mk[1]
        g[1] = p2 * mk[0] - p0 * mk[2]
        g[2] = p0 * mk[1] - p1 * mk[0]
        ja, jb = -B * a, C * a * a  # Jr(a phi) = I + ja K + jb K^2
        for r1 in range(3):
            for c in range(3):
                Jr[r1, c] = ja * K[r1, c] + jb * KK[r1, c] + (1.0 if r1 == c else 0.0)
        for c in range(3):
            gJ[c] = g[0] * Jr[0, c] + g[1] * Jr[1, c] + g[2] * Jr[2, c]
        for c in range(3):
            uu[c] = a * (gJ[0] * Jinv[0, c] + gJ[1] * Jinv[1, c] + gJ[2] * Jinv[2, c])
        for r1 in range(3):
            Eg[r1] = E[r1, 0] * g[0] + E[r1, 1] * g[1] + E[r1, 2] * g[2]
        for c in range(3):
            uDt = uu[0] * D[c, 0] + uu[1] * D[c, 1] + uu[2] * D[c, 2]
            Ha[m, c] = (Eg[c] - uDt) * f
            Hb[m, c] = uu[c] * f
            Ha[m, 3 + c] = (1.0 - a) * m_a[j, c] * f
            Hb[m, 3 + c] = a * mD[j, c] * f
        qB0 = q[0] * RaTB[j, 0, 0] + q[1] * RaTB[j, 1, 0] + q[2] * RaTB[j, 2, 0]
        qB1 = q[0] * RaTB[j, 0, 1] + q[1] * RaTB[j, 1, 1] + q[2] * RaTB[j, 2, 1]
        Hp[j, m, 0] = (qB0 + taB[j, 0] + a * dtB[j, 0]) * f
        Hp[j, m, 1] = (qB1 + taB[j, 1] + a * dtB[j, 1]) * f
        Hp[j, m, 2] = f
    if r:
        rows[N] = math.sqrt(max(0.0, 2.0 * correction)) if linearize else 0.0
    return rows, Ha, Hb, Hp


@nb.njit(cache=True)
def blocks_residuals(
    R: FloatArray, t: FloatArray, knot: NDArray[np.int64], normals: FloatArray, dists: FloatArray,
    bases: FloatArray, plane: NDArray[np.int64], anchors: FloatArray, P: FloatArray, al: FloatArray,
    starts: NDArray[np.int64],
) -> FloatArray:
    """Unwhitened residuals of many two-pose blocks at once, point for point those of
    :func:`two_pose_terms` (the same code): block b holds the points ``P[starts[b]:starts[b+1]]``
    (fractions ``al``) between knots ``knot[b]`` and ``knot[b] + 1`` (rotations ``R`` (K, 3, 3),
    positions ``t`` (K, 3)) on plane row ``plane[b]`` (``normals``, ``dists``, ``bases`` (3 x 2),
    ``anchors``)."""
    out = np.empty(P.shape[0])
    for b in range(starts.shape[0] - 1):
        s, e = starts[b], starts[b + 1]
        i, j = knot[b], plane[b]
        res = two_pose_terms(R[i], t[i] - anchors[j], R[i + 1], t[i + 1] - anchors[j], normals[j], dists[j], bases[j],
                             P[s:e], al[s:e], False)[0]
        out[s:e] = res
    return out


@nb.njit(cache=True)
def block_ok(points: FloatArray, sigmas: FloatArray, alphas: FloatArray) -> bool:
    """Whether a two-pose block passes :func:`slam.backend.factors.check_block`: finite points,
    finite sigmas > 0 and alphas in [0, 1] (shapes checked by the caller)."""
    for i in range(sigmas.shape[0]):
        s = sigmas[i]
        if not (math.isfinite(s) and s > 0.0):
            return False
        a = alphas[i]
        if not (a >= 0.0 and a <= 1.0):
            return False
        for c in range(3):
            if not math.isfinite(points[i, c]):
                return False
    return True
