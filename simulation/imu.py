"""An optional IMU rigidly attached to the body frame, derived from the ground-truth trajectory.

The IMU frame is the body frame. At every trajectory sample ``t_k`` (200 Hz by default):

- gyro ``w_body(t_k) = log(R(t_{k-1})^T R(t_{k+1})) / (2 dt)``: the body-frame angular
  velocity, the central difference of the same slerped rotations that
  ``Trajectory.interpolate`` returns;
- accelerometer ``f_body(t_k) = R(t_k)^T (a_world(t_k) + g e_z)``: the specific
  force, with ``a_world`` the central second difference of the positions
  (``g`` = 9.80665 m/s^2; at rest it reads +g on z).

The trajectory itself is Gaussian-smoothed (see ``simulation.trajectory``), so these
differences are the derivatives of a smooth representation to O(dt^2). Noise: white
noise (density * sqrt(rate)) plus a bias that starts at a seeded value and does a
random walk (density * sqrt(dt) per sample), independently per axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import Field
from scipy.spatial.transform import Rotation

from common.config import StrictModel
from simulation.trajectory import Trajectory

FloatArray = NDArray[np.float64]
GRAVITY = 9.80665


class ImuConfig(StrictModel):
    """Noise of a MEMS IMU: the Analog Devices ADIS16448 as calibrated for the EuRoC MAV dataset
    (its ``imu0/sensor.yaml``), the class a mapping backpack carries (an Xsens MTi-G-700's
    datasheet is quieter still: 60 ug/sqrt(Hz), 0.01 deg/s/sqrt(Hz)). Until session 8 the
    defaults were ten to twenty times noisier (0.02 m/s^2/sqrt(Hz), 0.003 rad/s/sqrt(Hz)), worse
    than any such part: 3 s without an observation of the walking direction then cost ~60 mm."""

    gyro_noise: float = Field(default=1.6968e-4, ge=0, description="gyro white noise density (rad/s/sqrt(Hz))")
    accel_noise: float = Field(default=2.0e-3, ge=0, description="accel white noise density (m/s^2/sqrt(Hz))")
    gyro_bias_walk: float = Field(default=1.9393e-5, ge=0, description="gyro bias random walk (rad/s^2/sqrt(Hz))")
    accel_bias_walk: float = Field(default=3.0e-3, ge=0, description="accel bias random walk (m/s^3/sqrt(Hz))")
    gyro_bias_init: float = Field(default=0.002, ge=0, description="std of the initial gyro bias (rad/s)")
    accel_bias_init: float = Field(default=0.02, ge=0, description="std of the initial accel bias (m/s^2)")


@dataclass(frozen=True, eq=False)
class ImuData:
    """IMU samples in the body frame: ``times`` (N,), ``gyro`` (N,3) rad/s, ``accel`` (N,3) m/s^2,
    and the true biases ``gyro_bias``/``accel_bias`` (N,3) that were added."""

    times: FloatArray
    gyro: FloatArray
    accel: FloatArray
    gyro_bias: FloatArray
    accel_bias: FloatArray


def ideal_imu(traj: Trajectory) -> tuple[FloatArray, FloatArray]:
    """Noise-free (gyro, accel) in the body frame at the trajectory samples."""
    dt = traj.dt
    rot = Rotation.from_quat(traj.quaternions)
    n = len(traj.times)
    gyro = np.empty((n, 3))
    gyro[1:-1] = (rot[:-2].inv() * rot[2:]).as_rotvec() / (2 * dt)
    gyro[0], gyro[-1] = gyro[1], gyro[-2]
    p = traj.positions
    acc = np.empty((n, 3))
    acc[1:-1] = (p[2:] - 2 * p[1:-1] + p[:-2]) / dt**2
    acc[0], acc[-1] = acc[1], acc[-2]
    acc[:, 2] += GRAVITY
    accel = rot.apply(acc, inverse=True)
    return gyro, accel


def simulate_imu(traj: Trajectory, seed: int, cfg: ImuConfig | None = None, noise: bool = True) -> ImuData:
    """IMU readings at the trajectory's samples; ``noise=False`` gives the ideal readings (zero bias)."""
    c = cfg or ImuConfig()
    gyro, accel = ideal_imu(traj)
    n = len(traj.times)
    zeros = np.zeros((n, 3))
    if not noise:
        return ImuData(traj.times.copy(), gyro, accel, zeros, zeros.copy())
    rng = np.random.default_rng(seed)
    dt = traj.dt

    def bias(init: float, walk: float) -> FloatArray:
        steps = rng.standard_normal((n, 3)) * (walk * np.sqrt(dt))
        steps[0] = rng.standard_normal(3) * init
        return np.cumsum(steps, axis=0)

    bg = bias(c.gyro_bias_init, c.gyro_bias_walk)
    ba = bias(c.accel_bias_init, c.accel_bias_walk)
    gyro = gyro + bg + rng.standard_normal((n, 3)) * (c.gyro_noise / np.sqrt(dt))
    accel = accel + ba + rng.standard_normal((n, 3)) * (c.accel_noise / np.sqrt(dt))
    return ImuData(traj.times.copy(), gyro, accel, bg, ba)
