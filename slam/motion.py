"""Motion and datum factors for the trajectory knots: constant-velocity prior, datum, horizontal
planes and (optional) IMU preintegration.

Constant-velocity prior (chosen over a smoothness prior on pose differences, which pulls a
walking operator towards standing still): three consecutive knots ``X(i-1), X(i), X(i+1)`` at
times ``t0 < t1 < t2``, residual the change of the body twist rate between the two intervals::

    r = Log(T1^-1 T2) / dt2 - Log(T0^-1 T1) / dt1          (rotation rad/s, translation m/s)

zero for any motion with a constant body twist (straight walking, steady turns, helices). Its
noise is white acceleration of power spectral density ``q`` (rotation and translation each):
``sigma = sqrt(q (dt1 + dt2) / 2)``, the standard deviation of a velocity change over the
half-intervals of the two twists. Tuned to walking: the torso's vertical bounce (+-2 m/s^2 at
the 2 Hz step rate) and sway/turns (a few rad/s^2) give velocity changes of about 0.05 m/s and
0.1 rad/s per 25 ms knot, i.e. ``q_lin ~ 0.1-0.25 m^2/s^3`` and ``q_ang ~ 0.5-1 rad^2/s^3``
(see :class:`MotionPriorConfig`; ``scripts/bench_backend.py`` prints the whitened residuals on a
walking trajectory). The Jacobians are exact (gtsam's ``LogmapDerivative`` and adjoints).

IMU: gtsam's ``PreintegratedImuMeasurements``/``ImuFactor`` between knots, with a velocity
``V(i)`` (world frame) and bias ``B(i)`` per knot and a bias random walk between knots.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class MotionPriorConfig:
    """White-acceleration power spectral densities of the constant-velocity prior.

    ``q_ang`` [rad^2/s^3] and ``q_lin`` [m^2/s^3] (the SLAM configuration's ``backend.motion_sigma_*``
    squared times the knot interval).
    """

    q_ang: float
    q_lin: float

    def __post_init__(self) -> None:
        for name in ("q_ang", "q_lin"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f"motion prior {name}: must be > 0, got {v}")

    def sigmas(self, dt1: float, dt2: float) -> FloatArray:
        """Standard deviations (6,) of the twist-rate change between intervals dt1 and dt2 [s]."""
        h = 0.5 * (dt1 + dt2)
        return np.sqrt(np.array([self.q_ang] * 3 + [self.q_lin] * 3) * h)


def constant_velocity_terms(
    T0: gtsam.Pose3, T1: gtsam.Pose3, T2: gtsam.Pose3, dt1: float, dt2: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Residual (6,) and Jacobians (6, 6) wrt right perturbations of T0, T1, T2."""
    D1, D2 = T0.between(T1), T1.between(T2)
    J1 = gtsam.Pose3.LogmapDerivative(D1) / dt1
    J2 = gtsam.Pose3.LogmapDerivative(D2) / dt2
    r = gtsam.Pose3.Logmap(D2) / dt2 - gtsam.Pose3.Logmap(D1) / dt1
    H0 = J1 @ D1.inverse().AdjointMap()
    H1 = -J2 @ D2.inverse().AdjointMap() - J1
    return r, H0, H1, J2


def constant_velocity_factor(
    key0: int, key1: int, key2: int, dt1: float, dt2: float, config: MotionPriorConfig
) -> gtsam.CustomFactor:
    """Constant-velocity prior on three consecutive knots (``dt1 = t1 - t0``, ``dt2 = t2 - t1``)."""
    if not (dt1 > 0.0 and dt2 > 0.0):
        raise ValueError(f"knot intervals: must be > 0, got dt1={dt1}, dt2={dt2}")
    noise = gtsam.noiseModel.Diagonal.Sigmas(config.sigmas(dt1, dt2))

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
        T1 = v.atPose3(key1)
        if H is None:
            return gtsam.Pose3.Logmap(T1.between(v.atPose3(key2))) / dt2 - gtsam.Pose3.Logmap(
                v.atPose3(key0).between(T1)) / dt1
        # constant_velocity_terms with the derivatives from the same gtsam calls: between's
        # Jacobian is -Ad(D^-1) and Logmap's is LogmapDerivative (equal bit for bit, tested)
        A1, A2 = np.empty((6, 6), order="F"), np.empty((6, 6), order="F")
        L1, L2 = np.empty((6, 6), order="F"), np.empty((6, 6), order="F")
        D1 = v.atPose3(key0).between(T1, A1)
        D2 = T1.between(v.atPose3(key2), A2)
        r = gtsam.Pose3.Logmap(D2, L2) / dt2 - gtsam.Pose3.Logmap(D1, L1) / dt1
        J1, J2 = L1 / dt1, L2 / dt2
        H[0] = J1 @ np.negative(A1)
        H[1] = -J2 @ np.negative(A2) - J1
        H[2] = J2
        return r

    return gtsam.CustomFactor(noise, [key0, key1, key2], error)


def initial_velocity_factor(
    key0: int, key1: int, T_delta: gtsam.Pose3, dt: float, sigma_ang_rate: float,
    sigma_lin_rate: float,
) -> gtsam.BetweenFactorPose3:
    """Weak prior on the first interval's motion (``T0^-1 T1 ~ T_delta``), so that the second knot
    is determined before the constant-velocity prior can reach it. Sigmas are rates (rad/s, m/s)."""
    sig = np.array([sigma_ang_rate] * 3 + [sigma_lin_rate] * 3) * dt
    return gtsam.BetweenFactorPose3(key0, key1, T_delta, gtsam.noiseModel.Diagonal.Sigmas(sig))


def datum_prior(key: int, T_world_body: gtsam.Pose3, sigma_rot: float = 1e-6,
                sigma_trans: float = 1e-6) -> gtsam.PriorFactorPose3:
    """Prior fixing a pose (the first knot defines the world datum)."""
    sig = np.array([sigma_rot] * 3 + [sigma_trans] * 3)
    return gtsam.PriorFactorPose3(key, T_world_body, gtsam.noiseModel.Diagonal.Sigmas(sig))


def horizontal_plane_prior(key: int, normal_world: ArrayLike, sigma_rad: float
                           ) -> gtsam.OrientedPlane3DirectionPrior:
    """Keep a floor/ceiling plane horizontal: its normal stays +z or -z (the sign of the given
    current normal's z), with a 2-dof direction noise ``sigma_rad``."""
    nz = float(np.asarray(normal_world, dtype=float)[2])
    if abs(nz) < 0.5:
        raise ValueError(f"normal_world: not near vertical (z = {nz:.3f}); not a floor or ceiling")
    z = np.array([0.0, 0.0, np.sign(nz), 0.0])
    return gtsam.OrientedPlane3DirectionPrior(key, z, gtsam.noiseModel.Isotropic.Sigma(2, sigma_rad))


@dataclass(frozen=True)
class ImuConfig:
    """IMU noise (continuous-time densities) and mounting; gravity along world -z.

    ``accel_noise_density`` [m/s^2/sqrt(Hz)], ``gyro_noise_density`` [rad/s/sqrt(Hz)],
    ``accel_bias_rw``/``gyro_bias_rw`` bias random walks [per sqrt(s)], ``bias_prior_sigmas``
    (accelerometer m/s^2, gyroscope rad/s) on the first knot's bias, ``velocity_prior_sigma``
    [m/s] on the first knot's velocity, ``T_body_imu`` (4, 4).
    """

    accel_noise_density: float
    gyro_noise_density: float
    accel_bias_rw: float
    gyro_bias_rw: float
    integration_sigma: float
    bias_prior_sigmas: tuple[float, float]
    velocity_prior_sigma: float
    gravity: float
    T_body_imu: tuple[tuple[float, ...], ...] | None

    def params(self) -> gtsam.PreintegrationParams:
        """gtsam preintegration parameters (z-up world); one shared object per configuration (an
        hour's final batch preintegrates every interval again, 16 us each to make them; callers
        must not change it)."""
        return _preintegration_params(self)


@functools.lru_cache(maxsize=8)
def _preintegration_params(config: ImuConfig) -> gtsam.PreintegrationParams:
    """:meth:`ImuConfig.params`, made once per configuration."""
    p = gtsam.PreintegrationParams.MakeSharedU(config.gravity)
    p.setAccelerometerCovariance(np.eye(3) * config.accel_noise_density**2)
    p.setGyroscopeCovariance(np.eye(3) * config.gyro_noise_density**2)
    p.setIntegrationCovariance(np.eye(3) * config.integration_sigma**2)
    if config.T_body_imu is not None:
        p.setBodyPSensor(gtsam.Pose3(np.asarray(config.T_body_imu, dtype=float)))
    return p


def preintegrate(
    params: gtsam.PreintegrationParams,
    bias: gtsam.imuBias.ConstantBias,
    accel_imu: ArrayLike,
    gyro_imu: ArrayLike,
    dt: ArrayLike,
) -> gtsam.PreintegratedImuMeasurements:
    """Preintegrate M samples: specific force (M, 3) [m/s^2] and angular rate (M, 3) [rad/s] in the
    IMU frame, each held for dt (M,) [s] (the time to the next sample)."""
    a = np.asarray(accel_imu, dtype=float)
    g = np.asarray(gyro_imu, dtype=float)
    d = np.asarray(dt, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3 or g.shape != a.shape or d.shape != (a.shape[0],):
        raise ValueError(f"imu samples: need accel (M,3), gyro (M,3), dt (M,); got {a.shape}, "
                         f"{g.shape}, {d.shape}")
    if a.shape[0] == 0 or np.any(d <= 0.0) or not (np.all(np.isfinite(a)) and np.all(np.isfinite(g))):
        raise ValueError("imu samples: need at least one finite sample and dt > 0")
    pim = gtsam.PreintegratedImuMeasurements(params, bias)
    for k in range(a.shape[0]):
        pim.integrateMeasurement(a[k], g[k], float(d[k]))
    return pim


def bias_random_walk_factor(key0: int, key1: int, dt: float, config: ImuConfig
                            ) -> gtsam.BetweenFactorConstantBias:
    """Bias between consecutive knots (dt seconds apart): zero-mean random walk."""
    sig = np.array([config.accel_bias_rw] * 3 + [config.gyro_bias_rw] * 3) * np.sqrt(dt)
    return gtsam.BetweenFactorConstantBias(key0, key1, gtsam.imuBias.ConstantBias(),
                                           gtsam.noiseModel.Diagonal.Sigmas(sig))
