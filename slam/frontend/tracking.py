"""Tracking: refine the newest knot's pose against the (fixed) map planes before association.

Between knots ``a`` (already estimated, fixed) and ``b`` (new), a point seen
at fraction ``alpha`` lies at ``T(alpha) p`` with ``T(alpha) = T_a Exp(alpha
Log(T_a^-1 T_b))`` (``slam.trajectory.interpolation``). Gauss-Newton on the right
perturbation of ``T_b`` with Huber weights, regularised by the
constant-velocity prediction, using the first-order Jacobian ``alpha * g``
(``g`` the derivative wrt the interpolated pose): the step only has to bring
the prediction within the tight association gates; the back end then solves
the exact problem.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam.frontend import kernels as fk
from slam.trajectory.interpolation import interpolate_poses, se3_exp, se3_inverse, se3_log

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class TrackingParams:
    """Tracking of the newest knots (``slam.params.tracking_params``): ``window`` knot intervals
    refined together in ``iterations`` Gauss-Newton steps; ``first_prior_sigmas`` (6,: rad, m)
    hold the window's oldest knot, ``twist_sigmas`` (6,: rad, m) the change of the body twist
    per knot interval."""

    window: int
    iterations: int
    first_prior_sigmas: FloatArray
    twist_sigmas: FloatArray


def orthonormalize(T: FloatArray) -> FloatArray:
    """The pose with its rotation block projected back onto SO(3) (round-off of chained products)."""
    u, _, vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = u @ vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def predict_constant_velocity(T_prev: FloatArray, T_last: FloatArray) -> FloatArray:
    """Next knot pose assuming the last knot interval's body twist repeats."""
    return orthonormalize(T_last @ (se3_inverse(T_prev) @ T_last))


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
    return orthonormalize(T)


def refine_window(
    T_knots: FloatArray,
    knot_index: NDArray[np.int64],
    alphas: FloatArray,
    points_body: FloatArray,
    normals: FloatArray,
    offsets: FloatArray,
    sigmas: FloatArray,
    first_prior_sigmas: FloatArray,
    cv_sigmas: FloatArray,
    iterations: int = 3,
    huber_k: float = 2.0,
    stay_sigmas: FloatArray | None = None,
    increment_sigmas: FloatArray | None = None,
    degenerate_ratio: float | None = None,
    freeze_sigma: float = 1e-4,
) -> FloatArray:
    """Jointly refine a window of knots (W, 4, 4) against fixed planes (world frame).

    Point ``m`` (body frame at its time) lies between knots ``knot_index[m]``
    and ``knot_index[m] + 1`` of the window at fraction ``alphas[m]``, on the
    plane ``normals[m] . x + offsets[m] = 0``. The first knot is held near its
    given pose by ``first_prior_sigmas`` (6,), consecutive knot intervals by a
    constant-velocity prior with ``cv_sigmas`` (6,) on the change of the body
    twist, and every knot weakly by ``stay_sigmas`` (6,) to its given pose, so
    that directions the planes do not observe stay at the prediction instead
    of drifting with the null space. With ``increment_sigmas`` (6,) the motion prior holds each
    interval's relative pose to the given one instead (an IMU-predicted window: the IMU knows
    the motion over one interval far better than a constant-velocity model of a walking torso,
    whose bob and sway would otherwise drag the window along directions no plane observes,
    e.g. along a corridor). With ``degenerate_ratio`` the window's translation is frozen at the
    given poses along world directions the planes hardly observe: eigenvectors of the points'
    translation information ``sum n n^T / sigma^2`` whose eigenvalue is below that ratio of the
    largest (degeneracy-aware solution remapping, Zhang, Kaess & Singh 2016). Otherwise a plane
    whose heading is a fraction of a degree off, the only "observation" of the direction along a
    corridor, would slide the window along it by decimetres. Right perturbations; the Jacobians use the first-order split
    ``(1 - alpha, alpha)`` of an interpolated pose's perturbation, exact
    enough for the few-centimetre corrections tracking makes.

    The iterations run in one compiled call (``slam.kernels.refine_window``), with the
    numbers of the numpy formulation (dense Jacobian, ``slam.trajectory.interpolation``'s batched
    logarithms, :func:`freeze_unobserved`) to rounding.
    """
    stay = stay_sigmas if stay_sigmas is not None else np.array([np.radians(1.0)] * 3 + [0.03] * 3)
    motion = increment_sigmas if increment_sigmas is not None else cv_sigmas

    def f64(x: FloatArray) -> FloatArray:
        return np.ascontiguousarray(x, dtype=np.float64)

    return fk.refine_window(
        f64(T_knots), np.ascontiguousarray(knot_index, dtype=np.int64), f64(alphas), f64(points_body), f64(normals),
        f64(offsets), f64(sigmas),
        f64(1.0 / first_prior_sigmas**2), f64(1.0 / stay**2), f64(1.0 / motion**2),
        increment_sigmas is not None,
        degenerate_ratio is not None,
        -1.0 if degenerate_ratio is None else float(degenerate_ratio),
        float(freeze_sigma),
        int(iterations),
        float(huber_k),
    )


def freeze_unobserved(A: FloatArray, b: FloatArray, T: FloatArray, T_given: FloatArray, normals: FloatArray,
                      info: FloatArray, ratio: float, freeze_sigma: float) -> None:
    """Hold the window's translation at the given poses along the world directions the planes
    hardly observe, in place in the normal equations ``A`` (6W, 6W), ``b`` (6W,).

    ``T``, ``T_given`` (W, 4, 4) are the current and the given knots (world frame), ``normals``
    (m, 3) the points' plane normals (world frame) with their weights ``info`` (m,), 1/m^2. The
    directions are the eigenvectors of ``sum info n n^T`` whose eigenvalue is below ``ratio``
    of the largest; each knot gets a prior of ``freeze_sigma`` (m) along them. (The numpy
    formulation of the step that ``slam.kernels.refine_window`` takes compiled.)
    """
    M = (normals * info[:, None]).T @ normals
    lam, vec = np.linalg.eigh(M)
    for ev in np.flatnonzero(lam < ratio * max(float(lam[-1]), 1e-300)):
        dw = vec[:, ev]
        for k in range(T.shape[0]):
            db = T[k, :3, :3].T @ dw  # the direction in knot k's body frame
            sl = slice(6 * k + 3, 6 * k + 6)
            A[sl, sl] += np.outer(db, db) / freeze_sigma**2
            b[sl] += db * float(dw @ (T[k, :3, 3] - T_given[k, :3, 3])) / freeze_sigma**2
