"""Tracking: refine the newest knot's pose against the (fixed) map planes before association.

Between knots ``a`` (already estimated, fixed) and ``b`` (new), a point seen
at fraction ``alpha`` lies at ``T(alpha) p`` with ``T(alpha) = T_a Exp(alpha
Log(T_a^-1 T_b))`` (``slam.interpolation``). Gauss-Newton on the right
perturbation of ``T_b`` with Huber weights, regularised by the
constant-velocity prediction, using the first-order Jacobian ``alpha * g``
(``g`` the derivative wrt the interpolated pose): the step only has to bring
the prediction within the tight association gates; the back end then solves
the exact problem.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slam.interpolation import interpolate_poses, se3_exp, se3_inverse, se3_log

FloatArray = NDArray[np.float64]


def predict_constant_velocity(T_prev: FloatArray, T_last: FloatArray) -> FloatArray:
    """Next knot pose assuming the last knot interval's body twist repeats."""
    return T_last @ (se3_inverse(T_prev) @ T_last)


def refine_knot(
    T_a: FloatArray,
    T_b: FloatArray,
    points_body: FloatArray,
    alphas: FloatArray,
    normals: FloatArray,
    offsets: FloatArray,
    sigmas: FloatArray,
    prior_sigmas: FloatArray,
    iterations: int = 3,
    huber_k: float = 2.0,
) -> FloatArray:
    """Refined ``T_b`` (4x4): points (m, 3) body frame, their planes (m, 3)/(m,) world frame.

    ``prior_sigmas`` (6,) weight the deviation from the given ``T_b`` (rotation
    first, rad, then translation, m).
    """
    T_pred = T_b.copy()
    T = T_b.copy()
    w_prior = 1.0 / prior_sigmas**2
    for _ in range(iterations):
        Tk = interpolate_poses(T_a, T, alphas)
        R = Tk[:, :3, :3]
        t = Tk[:, :3, 3]
        pw = np.einsum("mij,mj->mi", R, points_body) + t
        r = (np.einsum("mi,mi->m", normals, pw) + offsets) / sigmas
        Rtn = np.einsum("mji,mj->mi", R, normals)
        J = np.concatenate((np.cross(points_body, Rtn), Rtn), axis=1) * (alphas / sigmas)[:, None]
        a = np.abs(r)
        w = np.where(a <= huber_k, 1.0, huber_k / np.maximum(a, 1e-12))
        e_prior = se3_log(se3_inverse(T_pred) @ T)
        A = (J * w[:, None]).T @ J + np.diag(w_prior)
        g = (J * w[:, None]).T @ r + w_prior * e_prior
        try:
            delta = -np.linalg.solve(A, g)
        except np.linalg.LinAlgError:
            break
        T = T @ se3_exp(delta)
        if np.linalg.norm(delta) < 1e-7:
            break
    return T
