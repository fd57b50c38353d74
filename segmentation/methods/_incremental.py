"""Incremental total-least-squares line from running sums (numba helpers).

State is a length-8 array ``[n, sx, sy, sxx, syy, sxy, ox, oy]``: raw moments
of the points' coordinates relative to a local origin ``(ox, oy)`` (the first
point added), which keeps ``sxx - n cx^2`` free of cancellation for points far
from the scanner. The line is found without trigonometry (closed-form
eigenvector of the 2x2 scatter matrix), so a point can be added and the line
recomputed for a few nanoseconds.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from segmentation.lines import scatter_normal

FloatArray = NDArray[np.float64]


@nb.njit(cache=True, inline="always")
def moments_new() -> FloatArray:
    """Empty moment state."""
    return np.zeros(8)


@nb.njit(cache=True, inline="always")
def moments_add(m: FloatArray, x: float, y: float, w: float) -> None:
    """Add (w = 1) or remove (w = -1) a point (scanner-frame coordinates)."""
    if m[0] == 0.0:
        m[6] = x
        m[7] = y
    u = x - m[6]
    v = y - m[7]
    m[0] += w
    m[1] += w * u
    m[2] += w * v
    m[3] += w * u * u
    m[4] += w * v * v
    m[5] += w * u * v


@nb.njit(cache=True, inline="always")
def line_from_sums(n: float, su: float, sv: float, suu: float, svv: float, suv: float) -> tuple[float, float, float, float]:
    """TLS line of n points from their raw sums (coordinates u, v about any origin).

    Returns (mu, mv, nx, ny): the centroid about that origin and the unit normal (sign arbitrary).
    """
    inv_n = 1.0 / n
    mu = su * inv_n
    mv = sv * inv_n
    nx, ny = scatter_normal(suu - mu * su, svv - mv * sv, suv - mu * sv)
    return mu, mv, nx, ny


@nb.njit(cache=True, inline="always")
def moments_line(m: FloatArray) -> tuple[float, float, float, float]:
    """(cx, cy, nx, ny) of the TLS line of the moments: centroid and unit normal (sign arbitrary)."""
    mu, mv, nx, ny = line_from_sums(m[0], m[1], m[2], m[3], m[4], m[5])
    return mu + m[6], mv + m[7], nx, ny


@nb.njit(cache=True, inline="always")
def point_line_distance(x: float, y: float, cx: float, cy: float, nx: float, ny: float) -> float:
    return abs((x - cx) * nx + (y - cy) * ny)


@nb.njit(cache=True)
def moments_of(points: FloatArray, i0: int, i1: int) -> FloatArray:
    """Moments of points i0..i1 inclusive."""
    m = np.zeros(8)
    for i in range(i0, i1 + 1):
        moments_add(m, points[i, 0], points[i, 1], 1.0)
    return m


@nb.njit(cache=True)
def gaps_ok(points: FloatArray, max_gap: float) -> NDArray[np.bool_]:
    """``ok[i]``: point i is within ``max_gap`` of point i - 1 (``ok[0]`` is True)."""
    n = points.shape[0]
    ok = np.ones(n, dtype=np.bool_)
    g2 = max_gap * max_gap
    for i in range(1, n):
        dx = points[i, 0] - points[i - 1, 0]
        dy = points[i, 1] - points[i - 1, 1]
        ok[i] = dx * dx + dy * dy <= g2
    return ok
