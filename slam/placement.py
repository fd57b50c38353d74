"""Placing body-frame points in the world with the trajectory's knots, fast.

Between knots ``T_i`` and ``T_i+1`` (``T_world_body``) the rotation follows the geodesic and the
position the straight line (``slam.interpolation.interpolate_poses``). Points come in runs that
share a few knot intervals (a scan spans one or two), so the rotation logarithm is taken once
per interval instead of once per point. The arithmetic is otherwise that of
``interpolate_poses`` / ``interpolate_trajectory`` on every point, element by element, so the
results are the same to the last bit.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from slam.interpolation import knot_fractions, so3_exp, so3_log

FloatArray = NDArray[np.float64]


def interval_poses(T: FloatArray, idx: NDArray[np.int64], alpha: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rotations (m, 3, 3) and positions (m, 3) of ``T_world_body`` at fractions ``alpha`` (m,)
    of the knot intervals ``idx`` (m,) (between ``T[idx]`` and ``T[idx + 1]``, knots (K, 4, 4))."""
    uniq, inv = np.unique(idx, return_inverse=True)
    phi = so3_log(np.swapaxes(T[uniq, :3, :3], -1, -2) @ T[uniq + 1, :3, :3])
    R = T[idx, :3, :3] @ so3_exp(alpha[:, None] * phi[inv.ravel()])
    p0 = T[idx, :3, 3]
    return R, p0 + alpha[:, None] * (T[idx + 1, :3, 3] - p0)


def place_points(knot_times: ArrayLike, knot_poses: ArrayLike, times: ArrayLike, points_body: FloatArray) -> FloatArray:
    """Points (m, 3) body frame at their ``times`` (m,) -> world frame, with the knots (K,) and
    their poses ``T_world_body`` (K, 4, 4): the same numbers as ``interpolate_trajectory``
    followed by ``R p + t``, with the same checks on the times."""
    idx, alpha = knot_fractions(knot_times, times)
    R, t = interval_poses(np.asarray(knot_poses, dtype=float), idx, alpha)
    return np.einsum("mij,mj->mi", R, points_body) + t
