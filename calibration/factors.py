"""A point-on-plane block factor with the scanner's extrinsic *and* time offset as variables.

Like :func:`slam.backend.factors.scanner_point_plane_factor` (points in the scanner frame, keys
``X(i), X(i+1), P(j), E(s)``) plus a scalar ``D(s)``: the scanner's clock offset delta [s], so
that a beam stamped ``t_k`` was really taken at ``t_k + delta``. The point moves along the
trajectory's geodesic of its knot interval::

    alpha_k' = alpha_k + delta / (t_{i+1} - t_i),   T_k = T_i Exp(alpha_k' xi)

(alpha' slightly outside [0, 1] extrapolates the same constant twist: offsets are a few ms
against 25 ms intervals). Since ``Exp((alpha + h) xi) = Exp(alpha xi) Exp(h xi)``, the
derivative wrt delta is exact and uses the interval's body velocity ``xi / dt``::

    d e_k / d delta = g_k . xi / dt,   g_k = [p_k x m_k, m_k]

with ``p_k`` the point and ``m_k`` the plane normal in the body frame at the beam time. Per-point
robust weights as in :mod:`slam.backend.factors` (IRLS inside the factor).
"""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from slam.backend.factors import (
    RobustKernel,
    point_plane_terms,
    robust_rows,
    robust_rows_dim,
    scaled_rows,
)

FloatArray = NDArray[np.float64]


def timed_scanner_plane_factor(
    key_a: int,
    key_b: int,
    plane_key: int,
    extrinsic_key: int,
    offset_key: int,
    points_scanner: FloatArray,
    alphas: FloatArray,
    interval: float,
    sigmas: FloatArray,
    kernel: RobustKernel,
) -> gtsam.CustomFactor:
    """Factor on ``(X(i), X(i+1), P(j), E(s), D(s))`` for N scanner-frame points (N, 3) at
    interval fractions ``alphas`` (N,) of a knot interval of ``interval`` seconds."""
    pts = np.ascontiguousarray(points_scanner, dtype=float)
    al = np.ascontiguousarray(alphas, dtype=float)
    s = np.asarray(sigmas, dtype=float)
    n = pts.shape[0]
    if pts.ndim != 2 or pts.shape[1] != 3 or n == 0 or not np.all(np.isfinite(pts)):
        raise ValueError(f"points_scanner: expected a finite non-empty (N, 3) array, got shape {pts.shape}")
    if al.shape != (n,) or s.shape != (n,) or np.any(s <= 0) or not interval > 0:
        raise ValueError("alphas, sigmas: expected (N,) arrays (sigmas > 0) and interval > 0")
    inv_s = 1.0 / s

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
        E = v.atPose3(extrinsic_key).matrix()
        R_bs = E[:3, :3]
        p_b = pts @ R_bs.T + E[:3, 3]
        delta = float(v.atVector(offset_key)[0])
        T_a, T_b = v.atPose3(key_a), v.atPose3(key_b)
        t = point_plane_terms(T_a, T_b, v.atOrientedPlane3(plane_key), p_b, al + delta / interval,
                              H is not None)
        e = t.residuals * inv_s
        out, sw = robust_rows(e, kernel, H is not None)
        if H is None:
            return out
        assert t.H_a is not None and t.H_b is not None and t.H_plane is not None
        assert t.normal_beam is not None and sw is not None
        f = (sw * inv_s)[:, None]
        H[0], H[1], H[2] = scaled_rows(t.H_a, f, rows), scaled_rows(t.H_b, f, rows), scaled_rows(t.H_plane, f, rows)
        m_k = t.normal_beam
        m_s = m_k @ R_bs
        He = np.empty((n, 6))
        He[:, :3] = np.cross(pts, m_s)
        He[:, 3:] = m_s
        H[3] = scaled_rows(He, f, rows)
        assert t.dres_dalpha is not None
        H[4] = scaled_rows((t.dres_dalpha / interval)[:, None], f, rows)
        return out

    rows = robust_rows_dim(n, kernel)
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(rows),
                              [key_a, key_b, plane_key, extrinsic_key, offset_key], error)
