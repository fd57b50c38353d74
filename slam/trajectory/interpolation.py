"""SE(3) tools for the continuous-time trajectory: exp/log, right Jacobians, interpolation.

The trajectory is a sequence of knots ``T_world_body(t_i)`` (20 Hz by default). Between knots
i and i+1 the rotation follows the SO(3) geodesic and the position the straight line, each at
constant rate (decoupled, "SO(3) x R^3" interpolation)::

    R(t) = R_i Exp(alpha Log(R_i^T R_{i+1})),   p(t) = p_i + alpha (p_{i+1} - p_i),
    alpha = (t - t_i) / (t_{i+1} - t_i)

which is what the factors in :mod:`slam.backend.factors` use, so deskewing with
:func:`interpolate_trajectory` places points exactly as the back end does. Chosen over the
SE(3) geodesic ``T_i Exp(alpha Log(T_i^-1 T_{i+1}))``, whose path is a screw: it bends the
position with the torso's sway and pitch, so that the point-to-plane residuals depend on the
speed along a corridor that the planes do not observe at all (on a 5 s corridor walk with an
IMU, tests/test_slam_pipeline.py: 0.74 m short of 3.60 m with SE(3), 0.37 m with this model).

Conventions follow gtsam: a twist ``xi = (omega, v)`` (rotation first, then translation),
``Exp``/``Log`` are gtsam's ``Pose3.Expmap``/``Pose3.Logmap`` and the right Jacobian ``Jr``
satisfies ``Exp(xi + d) ~= Exp(xi) Exp(Jr(xi) d)`` (gtsam's ``Pose3.ExpmapDerivative``).
All functions work on numpy arrays; poses are 4x4 homogeneous matrices.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]

_SMALL = 1e-4  # below this angle (rad) the two-term Taylor series in se3_log is exact to 1e-17


def hat3(v: FloatArray) -> FloatArray:
    """``[v]x`` (3, 3) of one 3-vector (fast path of :func:`hat`)."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def hat(v: ArrayLike) -> FloatArray:
    """Skew-symmetric matrices ``[v]x`` of vectors ``v`` with shape (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


_SERIES_MAX = 0.5  # below this angle (rad) the series below are exact to ~1e-16
_K = np.arange(7)
_FACT = np.array([float(np.prod(np.arange(1, m + 1))) for m in range(20)])
# coefficients of theta^(2k), k = 0..6, of A, B, C, D, F (see exp_coefficients)
_SERIES = np.array([
    (-1.0) ** _K / _FACT[2 * _K + 1],
    (-1.0) ** _K / _FACT[2 * _K + 2],
    (-1.0) ** _K / _FACT[2 * _K + 3],
    (-1.0) ** _K / _FACT[2 * _K + 4],
    (-1.0) ** _K * (_K + 1) / _FACT[2 * _K + 5],
])


def exp_coefficients(theta: ArrayLike) -> tuple[FloatArray, ...]:
    """Coefficients of the SO(3)/SE(3) series at rotation angles ``theta`` >= 0 (any shape).

    Returns ``(A, B, C, D, F)`` with ``A = sin t / t``, ``B = (1 - cos t) / t^2``,
    ``C = (t - sin t) / t^3``, ``D = (t^2/2 + cos t - 1) / t^4`` and
    ``F = (2 t - 3 sin t + t cos t) / (2 t^5)``: power series in ``t^2`` below 0.5 rad (exact to
    rounding, no cancellation), closed forms above.
    """
    t0 = np.asarray(theta, dtype=float)
    t = t0.reshape(-1)
    out = ((t * t)[:, None] ** _K @ _SERIES.T).T  # (5, M): series in t^2
    big = t >= _SERIES_MAX
    if np.any(big):
        tb = t[big]
        s, c = np.sin(tb), np.cos(tb)
        out[0, big] = s / tb
        out[1, big] = (1.0 - c) / tb**2
        out[2, big] = (tb - s) / tb**3
        out[3, big] = (tb**2 / 2.0 + c - 1.0) / tb**4
        out[4, big] = (2.0 * tb - 3.0 * s + tb * c) / (2.0 * tb**5)
    out = out.reshape(5, *t0.shape)
    return out[0], out[1], out[2], out[3], out[4]


def so3_exp(phi: ArrayLike) -> FloatArray:
    """Rotation matrices ``Exp(phi)`` for rotation vectors ``phi`` (..., 3) -> (..., 3, 3)."""
    phi = np.asarray(phi, dtype=float)
    a, b, *_ = exp_coefficients(np.linalg.norm(phi, axis=-1))
    K = hat(phi)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def se3_exp(xi: ArrayLike) -> FloatArray:
    """Poses ``Exp(xi)`` for twists ``xi = (omega, v)`` with shape (..., 6) -> (..., 4, 4)."""
    xi = np.asarray(xi, dtype=float)
    phi, rho = xi[..., :3], xi[..., 3:]
    a, b, c, *_ = exp_coefficients(np.linalg.norm(phi, axis=-1))
    K = hat(phi)
    K2 = K @ K
    T = np.zeros((*xi.shape[:-1], 4, 4))
    T[..., :3, :3] = np.eye(3) + a[..., None, None] * K + b[..., None, None] * K2
    V = np.eye(3) + b[..., None, None] * K + c[..., None, None] * K2
    T[..., :3, 3] = np.einsum("...ij,...j->...i", V, rho)
    T[..., 3, 3] = 1.0
    return T


def so3_log(R: ArrayLike) -> FloatArray:
    """Rotation vectors ``Log(R)`` of rotation matrices (..., 3, 3) -> (..., 3).

    Closed form ``theta / (2 sin theta) vee(R - R^T)`` (Taylor series near 0); rotations within
    0.1 rad of pi, where that form loses precision, go through scipy's quaternion route.
    """
    R = np.asarray(R, dtype=float)
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    theta = np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0))
    w = np.stack((R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]), axis=-1)
    small = theta < _SMALL
    ts = np.where(small, 1.0, theta)
    f = np.where(small, 0.5 + theta**2 / 12.0, ts / (2.0 * np.sin(ts)))
    phi = f[..., None] * w
    near_pi = theta > np.pi - 0.1
    if np.any(near_pi):
        phi[near_pi] = Rotation.from_matrix(R[near_pi].reshape(-1, 3, 3)).as_rotvec()
    return phi


def se3_log(T: ArrayLike) -> FloatArray:
    """Twists ``Log(T)`` = (omega, v) of poses (..., 4, 4) -> (..., 6)."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    phi = so3_log(R)
    theta = np.linalg.norm(phi, axis=-1)
    small = theta < _SMALL
    ts = np.where(small, 1.0, theta)
    # V^-1 = I - K/2 + e K^2 with e = (1 - A / (2 B)) / t^2
    e = np.where(
        small,
        1.0 / 12.0 + theta**2 / 720.0,
        (1.0 - ts * np.sin(ts) / (2.0 * (1.0 - np.cos(ts)))) / ts**2,
    )
    K = hat(phi)
    Vinv = np.eye(3) - 0.5 * K + e[..., None, None] * (K @ K)
    rho = np.einsum("...ij,...j->...i", Vinv, T[..., :3, 3])
    return np.concatenate([phi, rho], axis=-1)


def se3_inverse(T: ArrayLike) -> FloatArray:
    """Inverses of poses (..., 4, 4)."""
    T = np.asarray(T, dtype=float)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def adjoint(T: ArrayLike) -> FloatArray:
    """Adjoint matrices (..., 6, 6) of poses (..., 4, 4) in gtsam's (rotation, translation) order."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    out = np.zeros((*T.shape[:-2], 6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = hat(T[..., :3, 3]) @ R
    return out


def se3_right_jacobian(xi: ArrayLike) -> FloatArray:
    """Exact right Jacobians ``Jr(xi)`` (..., 6, 6) of SE(3) for twists (..., 6).

    ``Jr = [[J, 0], [Q, J]]`` with ``J`` the SO(3) right Jacobian and ``Q`` the coupling block
    (Barfoot's ``Q(rho, phi)`` evaluated at ``(-rho, -phi)``); equal to gtsam's
    ``Pose3.ExpmapDerivative``.
    """
    xi = np.asarray(xi, dtype=float)
    phi, rho = xi[..., :3], xi[..., 3:]
    _, b, c, d, f = exp_coefficients(np.linalg.norm(phi, axis=-1))
    K, P = hat(phi), hat(rho)
    J = np.eye(3) - b[..., None, None] * K + c[..., None, None] * (K @ K)
    Q = _q_right(K, P, c, d, f)
    out = np.zeros((*xi.shape[:-1], 6, 6))
    out[..., :3, :3] = J
    out[..., 3:, 3:] = J
    out[..., 3:, :3] = Q
    return out


def _q_right(K: FloatArray, P: FloatArray, c: FloatArray, d: FloatArray, f: FloatArray) -> FloatArray:
    KP, PK = K @ P, P @ K
    KPK = KP @ K
    KK = K @ K
    return (
        -0.5 * P
        + c[..., None, None] * (KP + PK)
        + (3.0 * d - c)[..., None, None] * KPK
        - d[..., None, None] * (KK @ P + P @ KK)
        + f[..., None, None] * (KPK @ K + K @ KPK)
    )


def interpolate_poses(T_a: ArrayLike, T_b: ArrayLike, alpha: ArrayLike) -> FloatArray:
    """Poses (..., 4, 4) a fraction ``alpha`` (...) of the way from ``T_a`` to ``T_b``
    (broadcastable (..., 4, 4)): rotation ``R_a Exp(alpha Log(R_a^T R_b))``, position
    ``p_a + alpha (p_b - p_a)``."""
    T_a = np.asarray(T_a, dtype=float)
    T_b = np.asarray(T_b, dtype=float)
    alpha = np.asarray(alpha, dtype=float)
    R_a = T_a[..., :3, :3]
    phi = so3_log(np.swapaxes(R_a, -1, -2) @ T_b[..., :3, :3])
    shape = np.broadcast_shapes(T_a.shape[:-2], T_b.shape[:-2], alpha.shape)
    out = np.zeros((*shape, 4, 4))
    out[..., :3, :3] = R_a @ so3_exp(alpha[..., None] * phi)
    out[..., :3, 3] = T_a[..., :3, 3] + alpha[..., None] * (T_b[..., :3, 3] - T_a[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def knot_fractions(knot_times: ArrayLike, times: ArrayLike) -> tuple[NDArray[np.int64], FloatArray]:
    """Interval index i and fraction alpha in [0, 1] of each time: ``t = t_i + alpha (t_{i+1} - t_i)``.

    ``knot_times`` must be strictly increasing (at least two knots) and every time must lie in
    ``[knot_times[0], knot_times[-1]]``; otherwise a ValueError names the offending input.
    Times equal to the last knot map to the last interval with alpha = 1.
    """
    kt = np.asarray(knot_times, dtype=float)
    t = np.asarray(times, dtype=float)
    if kt.ndim != 1 or kt.size < 2:
        raise ValueError(f"knot_times: need a 1-D array of at least 2 knots, got shape {kt.shape}")
    if np.any(np.diff(kt) <= 0.0):
        raise ValueError("knot_times: must be strictly increasing")
    if t.size and (not np.all(np.isfinite(t)) or t.min() < kt[0] or t.max() > kt[-1]):
        raise ValueError(
            f"times: must lie within the knots [{kt[0]:.6f}, {kt[-1]:.6f}] s, "
            f"got [{np.nanmin(t):.6f}, {np.nanmax(t):.6f}] s"
        )
    idx = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, kt.size - 2)
    alpha = (t - kt[idx]) / (kt[idx + 1] - kt[idx])
    return idx.astype(np.int64), alpha


def interpolate_trajectory(
    knot_times: ArrayLike, knot_poses: ArrayLike, times: ArrayLike
) -> FloatArray:
    """Poses ``T_world_body(t)`` (M, 4, 4) at ``times`` (M,) from knots (K,) and poses (K, 4, 4)."""
    poses = np.asarray(knot_poses, dtype=float)
    kt = np.asarray(knot_times, dtype=float)
    if poses.shape != (kt.size, 4, 4):
        raise ValueError(f"knot_poses: expected shape ({kt.size}, 4, 4), got {poses.shape}")
    idx, alpha = knot_fractions(kt, times)
    return interpolate_poses(poses[idx], poses[idx + 1], alpha)
