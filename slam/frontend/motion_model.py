"""How the front end predicts the next knot, and what a motion sensor adds to the graph.

The runner holds one motion model: :class:`ConstantVelocity` without an IMU (the last knot
interval's body twist repeats; nothing to add to the graph), or ``slam.imu_feed.ImuMotion``
with one (IMU-predicted knots, preintegration factors, zero-velocity updates, velocities and
bias mirrored, the first knot levelled by gravity). Both have the interface of
:class:`MotionModel`.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from slam.frontend.knots import KnotMirror
from slam.frontend.tracking import orthonormalize, predict_constant_velocity

FloatArray = NDArray[np.float64]


class MotionModel(Protocol):
    """The front end's motion model (see the module doc)."""

    @property
    def increment_sigmas(self) -> FloatArray | None:
        """Tracking: sigmas (6,: rad, m) holding each knot interval to the predicted one (None:
        the constant-velocity prior on the twist's change)."""

    @property
    def degenerate_ratio(self) -> float | None:
        """Tracking: translation directions observed below this ratio are left to the prediction
        (None: all refined)."""

    def initial_pose(self, t0: float) -> FloatArray:
        """``T_world_body`` (4, 4) of the first knot at ``t0`` (s)."""

    def start_moving(self, increments: list[FloatArray], sigmas: FloatArray | None) -> None:
        """The walk starts in motion, not at rest: the first knot intervals' motions
        (``increments``, (4, 4) each, ``T(k)^-1 T(k + 1)`` body frame; ``frontend.initial_motion``)
        predict the knots they reach, and tracking holds those intervals to them with ``sigmas``
        (6,: rad, m; None: the model's own hold)."""

    def predict(self, knots: KnotMirror) -> tuple[FloatArray, FloatArray | None]:
        """The next knot's predicted pose (4, 4) and velocity (3,, world; None without one)."""

    def velocity(self, knots: KnotMirror, k: int) -> FloatArray | None:
        """Knot ``k``'s velocity (3,, world) as the back end's initial guess, None without one."""

    def add_factors(self, knots: KnotMirror, k: int) -> int:
        """Add what the sensor says about knot ``k`` (just added) to the graph; returns the
        zero-velocity updates added."""

    def refresh(self, knots: KnotMirror, k0: int) -> None:
        """After a back-end update: copy the estimates of knots ``k0`` on into the mirror (beyond
        the poses)."""


class ConstantVelocity:
    """No motion sensor: the next knot repeats the last interval's body twist; when the walk
    starts moving, the first knots follow the start's odometry (:meth:`start_moving`)."""

    degenerate_ratio: float | None = None

    def __init__(self) -> None:
        self._start: list[FloatArray] = []  # the first knot intervals' motions when the walk starts moving
        self._start_sigmas: FloatArray | None = None
        self._in_start = False  # the knot being tracked was predicted by the start's odometry

    @property
    def increment_sigmas(self) -> FloatArray | None:
        return self._start_sigmas if self._in_start else None

    def initial_pose(self, t0: float) -> FloatArray:
        """The origin."""
        return np.eye(4)

    def start_moving(self, increments: list[FloatArray], sigmas: FloatArray | None) -> None:
        self._start = [np.asarray(T, dtype=np.float64) for T in increments]
        self._start_sigmas = sigmas

    def predict(self, knots: KnotMirror) -> tuple[FloatArray, FloatArray | None]:
        k = knots.n
        self._in_start = k - 1 < len(self._start)
        if self._in_start:
            return orthonormalize(knots.T[k - 1] @ self._start[k - 1]), None
        if k >= 2:
            return predict_constant_velocity(knots.T[k - 2], knots.T[k - 1]), None
        return knots.T[k - 1].copy(), None

    def velocity(self, knots: KnotMirror, k: int) -> FloatArray | None:
        return None

    def add_factors(self, knots: KnotMirror, k: int) -> int:
        return 0

    def refresh(self, knots: KnotMirror, k0: int) -> None:
        return None
