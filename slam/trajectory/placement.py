"""Placing body-frame points in the world with the trajectory's knots, fast.

Between knots ``T_i`` and ``T_i+1`` (``T_world_body``) the rotation follows the geodesic and the
position the straight line (``slam.trajectory.interpolation.interpolate_poses``). Points come in runs that
share a few knot intervals (a scan spans one or two), so the rotation logarithm is taken once
per run of equal intervals instead of once per point, in the compiled loops of
:mod:`slam.trajectory.kernels`. The formulas are those of ``interpolate_poses`` /
``interpolate_trajectory``; the numbers agree with them to rounding (~1e-15 m), and are the
same for a point however the points are batched.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam.trajectory import kernels as tk
from slam.trajectory.interpolation import knot_fractions

FloatArray = NDArray[np.float64]


def interval_poses(T: FloatArray, idx: NDArray[np.int64], alpha: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotations (m, 3, 3) and positions (m, 3) of ``T_world_body`` at fractions ``alpha`` (m,)
    of the knot intervals ``idx`` (m,) (between ``T[idx]`` and ``T[idx + 1]``, knots (K, 4, 4),
    world frame)."""
    return tk.interval_poses(np.ascontiguousarray(T, dtype=np.float64), np.ascontiguousarray(idx, dtype=np.int64),
                             np.ascontiguousarray(alpha, dtype=np.float64))


def place_points(knot_times: ArrayLike, knot_poses: ArrayLike, times: ArrayLike, points_body: FloatArray) -> FloatArray:
    """Points (m, 3) body frame at their ``times`` (m,) -> world frame, with the knots (K,) and
    their poses ``T_world_body`` (K, 4, 4): ``interpolate_trajectory`` followed by ``R p + t``
    (to rounding), with the same checks on the times."""
    idx, alpha = knot_fractions(knot_times, times)
    return tk.place(np.ascontiguousarray(knot_poses, dtype=np.float64), idx, np.ascontiguousarray(alpha),
                    np.ascontiguousarray(points_body, dtype=np.float64))
