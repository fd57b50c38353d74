"""The front end's copy of the trajectory: knot poses (and velocities and bias with an IMU).

Knots lie on a fixed grid, ``t0 + k dt``. The back end holds the estimates; the front end keeps
this mirror to place points in the world (deskewed: every point at its own time, interpolated
between its two knots, ``slam.trajectory.kernels``) without asking the back end, and refreshes
it after every back-end update. During tracking the predicted next knot is *held* in the
mirror (:meth:`KnotMirror.hold`) so that points after the last estimated knot can be placed.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slam.frontend import kernels as fk
from slam.frontend.observations import ScanSegments
from slam.trajectory import kernels as tk
from slam.trajectory.deskew import DeskewTable

FloatArray = NDArray[np.float64]


class KnotMirror:
    """Knot poses ``T`` (n, 4, 4) ``T_world_body``, velocities ``V`` (n, 3) world frame, the
    latest IMU ``bias`` (6,: accelerometer, gyroscope) and the distance walked (``odometer``,
    m, along the knots' positions). ``n`` counts the knots; the arrays grow by doubling."""

    def __init__(self, dt: float) -> None:
        self.dt = dt
        self.t0: float | None = None  # the first scan's stamp, set by :meth:`start`
        self.deskew: DeskewTable | None = None
        self.T = np.zeros((1024, 4, 4))
        self.V = np.zeros((1024, 3))
        self.bias = np.zeros(6)
        self.n = 0
        self.odometer = 0.0

    def start(self, t0: float, deskew: DeskewTable | None) -> None:
        """Put the grid's origin at ``t0`` (s), with the gyro's rotation between its knots
        (``slam.trajectory.deskew``, None without it)."""
        self.t0 = t0
        self.deskew = deskew

    def deskewed(self, points_body: FloatArray, times: FloatArray) -> FloatArray:
        """Body points seen at ``times`` with the gyro's rotation between knots applied
        (unchanged without it)."""
        return points_body if self.deskew is None else self.deskew.apply(points_body, times)

    def time(self, k: int) -> float:
        """The time (s) of knot ``k``."""
        assert self.t0 is not None
        return self.t0 + k * self.dt

    def _grow(self) -> None:
        if self.n == self.T.shape[0]:
            self.T = np.concatenate((self.T, np.zeros_like(self.T)))
            self.V = np.concatenate((self.V, np.zeros_like(self.V)))

    def append(self, T: FloatArray, v: FloatArray | None = None) -> int:
        """Add the next knot (pose (4, 4), velocity (3,) or zero); returns its index."""
        self._grow()
        k = self.n
        self.T[k] = T
        self.V[k] = 0.0 if v is None else v
        self.n += 1
        if k > 0:
            self.odometer += float(np.linalg.norm(T[:3, 3] - self.T[k - 1, :3, 3]))
        return k

    def hold(self, T: FloatArray) -> None:
        """Mirror a predicted next knot (pose (4, 4)) so that placing points can use it, until
        :meth:`release`."""
        self._grow()
        self.T[self.n] = T
        self.n += 1

    def release(self) -> None:
        """Drop the knot held by :meth:`hold` (its slot keeps the pose, for :meth:`append`)."""
        self.n -= 1

    def fractions(self, times: FloatArray) -> tuple[NDArray[np.int64], FloatArray]:
        """Knot interval index and fraction (m,) of each time (m,) on the current knots, clipped
        to the first and the last interval."""
        assert self.t0 is not None
        return tk.uniform_fractions(self.t0, self.dt, self.n, np.ascontiguousarray(times, dtype=np.float64))

    def pose_at(self, t: float) -> FloatArray:
        """``T_world_body`` (4, 4) at time ``t`` with the current knots (compiled, one call)."""
        assert self.t0 is not None
        return tk.pose_uniform(self.T, self.t0, self.dt, self.n, float(t))

    def place(self, points_body: FloatArray, times: FloatArray) -> FloatArray:
        """Points (m, 3) body frame at their times (m,) -> world frame with the current knots:
        one compiled pass, one rotation logarithm per run of equal knot intervals."""
        assert self.t0 is not None
        return tk.place_uniform(self.T, self.t0, self.dt, self.n,
                                np.ascontiguousarray(times, dtype=np.float64),
                                np.ascontiguousarray(points_body, dtype=np.float64))

    def place_segments(self, segs: ScanSegments, js: NDArray[np.int64],
                       per: int | NDArray[np.int64]) -> list[FloatArray]:
        """World points (world frame) of the segments ``js``: every ``max(1, n // per)``-th of a
        segment's n points (``per`` one for all or one per segment), placed with one
        :meth:`place` call for all of them (per point the same numbers as one call per segment)."""
        if js.size == 0:
            return []
        placed, bounds = self.place_segments_flat(segs, js, per)
        return np.split(placed, bounds[1:-1])

    def place_segments_flat(self, segs: ScanSegments, js: NDArray[np.int64],
                            per: int | NDArray[np.int64]) -> tuple[FloatArray, NDArray[np.int64]]:
        """:meth:`place_segments` as one array (n, 3), world frame, and each segment's start
        row (len(js) + 1,: the last is n)."""
        if js.size == 0:
            return np.empty((0, 3)), np.zeros(1, dtype=np.int64)
        assert self.t0 is not None
        # one compiled call: the rows picked, gathered and placed (``place``'s numbers)
        return fk.place_subsampled(self.T, self.t0, self.dt, self.n, np.ascontiguousarray(segs.offsets, dtype=np.int64),
                                   np.ascontiguousarray(segs.n_points, dtype=np.int64),
                                   np.ascontiguousarray(js, dtype=np.int64),
                                   np.ascontiguousarray(np.broadcast_to(per, js.shape), dtype=np.int64),
                                   np.ascontiguousarray(segs.points_body, dtype=np.float64),
                                   np.ascontiguousarray(segs.times, dtype=np.float64))
