"""Total-least-squares line fits of scanline segments, in the scanner frame.

A line is ``{p : normal . p = offset}`` with ``offset >= 0``: the unit normal
points from the scanner origin towards the line. ``angle`` is the normal's
direction ``atan2(n_y, n_x)``. The 2x2 covariance of (angle, offset) is
propagated from isotropic point noise: with ``s_i`` the points' coordinates
along the line about the centroid and ``sigma^2`` their mean noise variance,
``var(angle) = sigma^2 / sum s_i^2``, the offset at the centroid has variance
``sigma^2 / n`` independent of the angle, and ``offset = normal(angle) .
centroid`` carries the angle's error through ``d offset / d angle =
dn/dangle . centroid``.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@nb.njit(cache=True, inline="always")
def scatter_normal(a: float, c: float, b: float) -> tuple[float, float]:
    """Unit eigenvector of the smallest eigenvalue of the scatter matrix [[a, b], [b, c]].

    Closed form, no trigonometry; a degenerate (isotropic or empty) scatter gives (0, 1).
    """
    h = 0.5 * (a - c)
    d = np.sqrt(h * h + b * b)
    # two algebraically equivalent eigenvectors; take the better-conditioned one
    if h >= 0.0:
        vx = -b
        vy = h + d
    else:
        vx = d - h
        vy = -b
    q = vx * vx + vy * vy
    if q == 0.0:
        return 0.0, 1.0
    inv = 1.0 / np.sqrt(q)
    return vx * inv, vy * inv


@nb.njit(cache=True)
def _fit_one(x: FloatArray, y: FloatArray, i0: int, i1: int) -> tuple[float, float, float, float, float, float, float]:
    """TLS fit of points i0..i1 (inclusive).

    Returns (cx, cy, nx, ny, offset, sum of squared residuals, sum of squared
    along-line coordinates about the centroid). One pass over the points, with
    sums about the first point so that no precision is lost far from the scanner.
    """
    n = i1 - i0 + 1
    ox = x[i0]
    oy = y[i0]
    su = 0.0
    sv = 0.0
    suu = 0.0
    svv = 0.0
    suv = 0.0
    for i in range(i0, i1 + 1):
        u = x[i] - ox
        v = y[i] - oy
        su += u
        sv += v
        suu += u * u
        svv += v * v
        suv += u * v
    mu = su / n
    mv = sv / n
    sxx = max(suu - mu * su, 0.0)
    syy = max(svv - mv * sv, 0.0)
    sxy = suv - mu * sv
    nx, ny = scatter_normal(sxx, syy, sxy)
    cx = mu + ox
    cy = mv + oy
    off = nx * cx + ny * cy
    if off < 0.0:
        nx = -nx
        ny = -ny
        off = -off
    # eigenvalues of the scatter: the smallest = sum of squared orthogonal residuals
    tr = sxx + syy
    det = sxx * syy - sxy * sxy
    disc = np.sqrt(max(0.25 * tr * tr - det, 0.0))
    ssr = max(0.5 * tr - disc, 0.0)
    ss_along = 0.5 * tr + disc
    return cx, cy, nx, ny, off, ssr, ss_along


@nb.njit(cache=True)
def fit_segments(
    points: FloatArray,
    first: IntArray,
    last: IntArray,
    sigma_pts: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Fit every segment ``points[first[k]..last[k]]`` (inclusive, point indices).

    ``sigma_pts`` is each point's range-noise standard deviation (m).
    Returns normal (k, 2), offset (k,), centroid (k, 2), direction (k, 2) in
    scan order, endpoints (k, 2, 2) projected onto the line, rms residual (k,),
    and the (angle, offset) covariance (k, 2, 2).
    """
    k = first.shape[0]
    x = np.ascontiguousarray(points[:, 0])
    y = np.ascontiguousarray(points[:, 1])
    normal = np.empty((k, 2))
    offset = np.empty(k)
    centroid = np.empty((k, 2))
    direction = np.empty((k, 2))
    endpoints = np.empty((k, 2, 2))
    rms = np.empty(k)
    cov = np.zeros((k, 2, 2))
    for s in range(k):
        i0 = first[s]
        i1 = last[s]
        n = i1 - i0 + 1
        cx, cy, nx, ny, off, ssr, ss = _fit_one(x, y, i0, i1)
        normal[s, 0] = nx
        normal[s, 1] = ny
        offset[s] = off
        centroid[s, 0] = cx
        centroid[s, 1] = cy
        dx = -ny
        dy = nx
        if (x[i1] - x[i0]) * dx + (y[i1] - y[i0]) * dy < 0.0:
            dx = -dx
            dy = -dy
        direction[s, 0] = dx
        direction[s, 1] = dy
        for e in range(2):
            j = i0 if e == 0 else i1
            t = (x[j] - cx) * dx + (y[j] - cy) * dy
            endpoints[s, e, 0] = cx + t * dx
            endpoints[s, e, 1] = cy + t * dy
        rms[s] = np.sqrt(ssr / n)
        s2 = 0.0
        for i in range(i0, i1 + 1):
            s2 += sigma_pts[i] * sigma_pts[i]
        s2 /= n
        var_a = s2 / ss if ss > 0.0 else np.inf
        var_c = s2 / n
        # d offset / d angle = (dn/dangle) . centroid, dn/dangle = (-ny, nx)
        g = -ny * cx + nx * cy
        cov[s, 0, 0] = var_a
        cov[s, 0, 1] = g * var_a
        cov[s, 1, 0] = g * var_a
        cov[s, 1, 1] = var_c + g * g * var_a
    return normal, offset, centroid, direction, endpoints, rms, cov


def fit_line(points: FloatArray, sigma: float = 0.003) -> tuple[FloatArray, float, float]:
    """TLS line through (n, 2) points: (unit normal, offset >= 0, rms residual)."""
    p = np.ascontiguousarray(points, dtype=np.float64)
    first = np.zeros(1, dtype=np.int64)
    last = np.full(1, p.shape[0] - 1, dtype=np.int64)
    nrm, off, _, _, _, rms, _ = fit_segments(p, first, last, np.full(p.shape[0], sigma))
    return nrm[0], float(off[0]), float(rms[0])
