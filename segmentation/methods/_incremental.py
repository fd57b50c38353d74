"""Incremental total-least-squares line from running sums (numba helpers).

State is a length-6 array ``[n, sx, sy, sxx, syy, sxy]`` of raw moments.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@nb.njit(cache=True, inline="always")
def moments_add(m: FloatArray, x: float, y: float, w: float) -> None:
    """Add (w = 1) or remove (w = -1) a point."""
    m[0] += w
    m[1] += w * x
    m[2] += w * y
    m[3] += w * x * x
    m[4] += w * y * y
    m[5] += w * x * y


@nb.njit(cache=True, inline="always")
def moments_line(m: FloatArray) -> tuple[float, float, float, float]:
    """(cx, cy, nx, ny) of the TLS line of the moments: centroid and unit normal."""
    n = m[0]
    cx = m[1] / n
    cy = m[2] / n
    sxx = m[3] - n * cx * cx
    syy = m[4] - n * cy * cy
    sxy = m[5] - n * cx * cy
    phi = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    return cx, cy, -np.sin(phi), np.cos(phi)


@nb.njit(cache=True, inline="always")
def point_line_distance(x: float, y: float, cx: float, cy: float, nx: float, ny: float) -> float:
    return abs((x - cx) * nx + (y - cy) * ny)


@nb.njit(cache=True)
def moments_of(points: FloatArray, i0: int, i1: int) -> FloatArray:
    """Moments of points i0..i1 inclusive."""
    m = np.zeros(6)
    for i in range(i0, i1 + 1):
        moments_add(m, points[i, 0], points[i, 1], 1.0)
    return m
