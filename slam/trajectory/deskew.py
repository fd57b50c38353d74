"""The rotation between knots that the geodesic interpolation misses, from the gyroscope.

Between two knots ``a`` and ``b`` the trajectory model turns the body along the geodesic
``R(alpha) = R_a Exp(alpha Log(R_a^T R_b))``. A walking operator's torso does not: it pitches
at the step frequency and swings round corners, and at 20 Hz knots the geodesic is off the true
attitude by 36 mdeg RMS, 82 mdeg at worst (the office walk's ground truth), which places a point
20 m away 12-29 mm off. The gyroscope measures the curve: with ``dR(t) = Q(t_a)^T Q(t)`` the
body rotation integrated from the gyro since knot ``a``,

    R(t) = R_geo(alpha) C(t),   C(t) = Exp(-alpha Log dR(t_b)) dR(t)

holds exactly for the true rotations, and ``C`` depends on the gyro alone (its bias, a constant
rate, cancels: a rotation at a constant rate is a geodesic). ``C`` is a few milliradians, so a
body point ``p`` seen at ``t`` becomes ``p + c(t) x p`` (``c = Log C``, first order: the second
order is < 0.05 mm at 30 m) and the unchanged interpolation then places it on the curve. ``c`` is
tabulated at the IMU's sample times and the knots (where it is 0) and interpolated linearly.

All rotations are of the body frame (the IMU samples' frame); times in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class DeskewTable:
    """``c(t)`` (body frame, rad) at increasing ``times`` (s); 0 at every knot and outside."""

    times: FloatArray
    rotvec: FloatArray  # (n, 3)

    def at(self, times: FloatArray) -> FloatArray:
        """``c`` (m, 3) at ``times`` (m,), linear between the table's entries, 0 outside."""
        t = np.asarray(times, dtype=np.float64)
        return np.column_stack([np.interp(t, self.times, self.rotvec[:, j], left=0.0, right=0.0) for j in range(3)])

    def apply(self, points_body: FloatArray, times: FloatArray) -> FloatArray:
        """The points (m, 3), body frame, seen at ``times`` (m,), moved by ``c(t) x p``
        (``c`` as :meth:`at`; one compiled pass, no temporaries: the cloud has ~10^8 points)."""
        p = np.ascontiguousarray(points_body, dtype=np.float64)
        t = np.ascontiguousarray(times, dtype=np.float64)
        return _apply(p, t, self.times, self.rotvec)


@njit(cache=True)
def _apply(p: FloatArray, t: FloatArray, grid: FloatArray, c: FloatArray) -> FloatArray:  # pragma: no cover
    out = np.empty_like(p)
    n = grid.shape[0]
    for i in range(p.shape[0]):
        ti = t[i]
        cx = cy = cz = 0.0
        if grid[0] <= ti <= grid[n - 1]:
            k = min(max(np.searchsorted(grid, ti, side="right") - 1, 0), n - 2)
            w = (ti - grid[k]) / (grid[k + 1] - grid[k])
            cx = c[k, 0] + w * (c[k + 1, 0] - c[k, 0])
            cy = c[k, 1] + w * (c[k + 1, 1] - c[k, 1])
            cz = c[k, 2] + w * (c[k + 1, 2] - c[k, 2])
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        out[i, 0] = x + cy * z - cz * y
        out[i, 1] = y + cz * x - cx * z
        out[i, 2] = z + cx * y - cy * x
    return out


def gyro_attitude(times: FloatArray, gyro: FloatArray, instantaneous: bool) -> Rotation:
    """Body attitude ``Q`` (relative to the first sample) at each sample time, from the gyro:
    readings at their stamps (``instantaneous``, the midpoint rule) or held until the next."""
    steps = Rotation.from_rotvec(_interval_rates(gyro, instantaneous) * np.diff(times)[:, None]).as_quat()
    return Rotation.from_quat(_chain(np.ascontiguousarray(steps)))


def _interval_rates(gyro: FloatArray, instantaneous: bool) -> FloatArray:
    """The body rate (n - 1, 3) over each interval between consecutive samples."""
    w = np.asarray(gyro, dtype=np.float64)
    return 0.5 * (w[:-1] + w[1:]) if instantaneous else w[:-1]


@njit(cache=True)
def _chain(steps: FloatArray) -> FloatArray:  # pragma: no cover - compiled
    """Quaternions (x, y, z, w) ``q_0 = 1, q_{i+1} = q_i s_i`` (renormalised)."""
    n = steps.shape[0]
    q = np.empty((n + 1, 4))
    x, y, z, w = 0.0, 0.0, 0.0, 1.0
    q[0, 0], q[0, 1], q[0, 2], q[0, 3] = x, y, z, w
    for i in range(n):
        bx, by, bz, bw = steps[i, 0], steps[i, 1], steps[i, 2], steps[i, 3]
        nx = w * bx + x * bw + y * bz - z * by
        ny = w * by - x * bz + y * bw + z * bx
        nz = w * bz + x * by - y * bx + z * bw
        nw = w * bw - x * bx - y * by - z * bz
        r = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz + nw * nw)
        x, y, z, w = nx * r, ny * r, nz * r, nw * r
        q[i + 1, 0], q[i + 1, 1], q[i + 1, 2], q[i + 1, 3] = x, y, z, w
    return q


def deskew_table(imu_times: FloatArray, gyro: FloatArray, instantaneous: bool,
                 knot_times: FloatArray) -> DeskewTable:
    """``c(t)`` between consecutive ``knot_times`` (increasing, s) covered by the IMU samples."""
    ti = np.asarray(imu_times, dtype=np.float64)
    tk = np.asarray(knot_times, dtype=np.float64)
    tk = tk[(tk >= ti[0]) & (tk <= ti[-1])]
    if tk.shape[0] < 2:
        return DeskewTable(np.array([ti[0], ti[-1]]), np.zeros((2, 3)))
    Q = gyro_attitude(ti, gyro, instantaneous)
    inner = ti[(ti > tk[0]) & (ti < tk[-1])]
    grid = np.union1d(tk, inner)
    # attitude at the grid times: from the sample before, turning at that interval's rate
    rate = _interval_rates(gyro, instantaneous)
    i = np.clip(np.searchsorted(ti, grid, side="right") - 1, 0, ti.shape[0] - 2)
    Qg = Q[i] * Rotation.from_rotvec(rate[i] * (grid - ti[i])[:, None])
    k = np.clip(np.searchsorted(tk, grid, side="right") - 1, 0, tk.shape[0] - 2)
    ka = np.searchsorted(grid, tk)  # the knots' rows in the grid
    Qa, Qb = Qg[ka[k]], Qg[ka[k + 1]]
    alpha = (grid - tk[k]) / (tk[k + 1] - tk[k])
    d_ab = (Qa.inv() * Qb).as_rotvec()
    C = Rotation.from_rotvec(-alpha[:, None] * d_ab) * (Qa.inv() * Qg)
    c = C.as_rotvec()
    c[ka] = 0.0
    return DeskewTable(grid, c)
