"""Exact summaries of point-on-plane observations whose poses are held: one 4x4 scatter per plane.

With the poses of an observation block held fixed, its points are fixed world points ``x_k`` and
its (IRLS-weighted) cost on the plane ``n . (x - a) + d = 0`` (anchor ``a``, see
``Backend.add_plane``) is a quadratic form in the plane's homogeneous vector ``pi = [n; d]``::

    sum_k w_k / sigma_k^2 (n . (x_k - a) + d)^2 = pi^T C pi,   C = sum_k w_k / sigma_k^2 h_k h_k^T,
    h_k = [x_k - a; 1]

so any number of such blocks add up to one symmetric positive semi-definite 4x4 matrix ``M`` per
plane, and one 4-dimensional factor ``e = S pi`` with ``S^T S = M`` carries them all exactly (with
the weights frozen where the summary was taken). This is what the back end's fixed-lag window
uses for the blocks that have left it: its cost per solve no longer grows with the walk
(the eigen-factor idea of plane-based bundle adjustment: Ferrer 2019, BALM 2021).

Frames: points and anchors in the world frame, metres; sigmas in metres.
"""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def scatter(points_world: FloatArray, anchor: FloatArray, weights: FloatArray) -> FloatArray:
    """``sum_k weights_k h_k h_k^T`` (4, 4) with ``h_k = [x_k - anchor; 1]`` for world points
    (N, 3) and weights (N,) (``w_k / sigma_k^2``, 1/m^2)."""
    h = np.empty((points_world.shape[0], 4))
    h[:, :3] = points_world - anchor
    h[:, 3] = 1.0
    return (h * weights[:, None]).T @ h


def shift_anchor(C: FloatArray, old_anchor: FloatArray, new_anchor: FloatArray) -> FloatArray:
    """The scatter ``C`` (4, 4) about ``old_anchor`` re-expressed about ``new_anchor``:
    ``h_new = A h_old`` with ``A = [[I, old - new], [0, 1]]``."""
    A = np.eye(4)
    A[:3, 3] = np.asarray(old_anchor, dtype=float) - np.asarray(new_anchor, dtype=float)
    return A @ C @ A.T


def square_root(M: FloatArray) -> FloatArray:
    """``S`` (4, 4) with ``S^T S = M`` for a symmetric positive semi-definite ``M`` (negative
    eigenvalues from round-off are clipped to zero)."""
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    return np.sqrt(np.clip(lam, 0.0, None))[:, None] * V.T


def plane_summary_factor(plane_key: int, M: FloatArray) -> gtsam.CustomFactor:
    """A factor on ``OrientedPlane3`` ``plane_key`` (anchor frame) whose error is
    ``0.5 pi^T M pi``: residual ``S [n; d]`` (4,), Jacobian ``S [[B, 0], [0, 1]]`` wrt the plane's
    retract coordinates (``B`` the normal's tangent basis, ``Unit3.basis()``)."""
    S = square_root(np.asarray(M, dtype=float))

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
        pl = v.atOrientedPlane3(plane_key)
        pi = np.empty(4)
        pi[:3] = pl.normal().point3()
        pi[3] = pl.distance()
        if H is not None:
            J = np.zeros((4, 3))
            J[:3, :2] = pl.normal().basis()
            J[3, 2] = 1.0
            H[0] = S @ J
        return S @ pi

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(4), [plane_key], error)
