"""Compiled (numba) batch kernels of the front end's per-scan bookkeeping: one call over all the
beams or rows of a scan where the Python loops went segment by segment or plane by plane.

Each kernel's unit test (tests/test_batch_kernels.py) holds the numpy code it replaced.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
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
