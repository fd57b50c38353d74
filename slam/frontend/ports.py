"""What the front end asks of the back end (structural types: the front end does not import it).

``MapSink`` is the part of the back end the map and edge builders write to (planes, ties,
observation blocks) and read the recent estimates back from; ``ImuSink`` what the IMU's use
adds (preintegrated intervals, zero-velocity priors) and reads back (velocities, bias).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


class MapSink(Protocol):
    """Planes, their ties and observations (world frame; blocks in the body frame)."""

    def add_plane(self, plane_id: int, normal_world: ArrayLike, offset: float, horizontal: bool = False,
                  vertical: bool = False, anchor: ArrayLike | None = None) -> None: ...

    def add_parallel(self, host_id: int, plane_id: int, sigma_angle: float) -> int: ...

    def add_perpendicular(self, host_id: int, plane_id: int, sigma_angle: float) -> int: ...

    def link_planes(self, keep_id: int, drop_id: int, sigma_angle: float, sigma_offset: float) -> int: ...

    def add_observations(self, knot: int, plane_id: int, points: ArrayLike, alphas: ArrayLike | None,
                         sigmas: ArrayLike) -> int: ...

    def plane(self, plane_id: int) -> tuple[FloatArray, float]: ...


class ImuSink(Protocol):
    """IMU factors and the IMU states' estimates."""

    def add_imu(self, knot: int, accel_imu: ArrayLike, gyro_imu: ArrayLike, dt: ArrayLike) -> None: ...

    def add_velocity_prior(self, knot: int, velocity_world: ArrayLike, sigma: float) -> None: ...

    def velocity(self, knot: int) -> FloatArray: ...

    def bias(self, knot: int) -> FloatArray: ...
