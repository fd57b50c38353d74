"""The back-end configuration of the default ``SlamConfig()``, for the tests: the values the SLAM
runner gives the back end (``slam.pipeline.SlamRunner.__init__``; a test checks they agree)."""

from __future__ import annotations

import numpy as np

from slam.backend import BackendConfig, RobustKernel
from slam.config import SlamConfig
from slam.motion import ImuConfig, MotionPriorConfig


def backend_defaults(imu: bool = False) -> BackendConfig:
    """``BackendConfig`` of ``SlamConfig()``; with ``imu`` its IMU part as with an IMU present."""
    cfg = SlamConfig()
    be, ic = cfg.backend, cfg.imu
    dt = 1.0 / cfg.trajectory.knot_rate
    imu_config = ImuConfig(
        accel_noise_density=ic.accel_noise,
        gyro_noise_density=ic.gyro_noise,
        accel_bias_rw=ic.accel_bias_walk,
        gyro_bias_rw=ic.gyro_bias_walk,
        bias_prior_sigmas=(ic.accel_bias_prior, ic.gyro_bias_prior),
        gravity=ic.gravity,
        integration_sigma=ic.integration_sigma,
        velocity_prior_sigma=1.0,
        T_body_imu=None,
    )
    return BackendConfig(
        kernel=RobustKernel(be.robust, be.robust_k),
        motion=MotionPriorConfig(q_ang=be.motion_sigma_angacc**2 * dt, q_lin=be.motion_sigma_acc**2 * dt),
        initial_velocity_sigmas=(3.0, 3.0),
        datum="position_yaw",
        datum_sigma=1e-6,
        datum_tilt_sigma=0.1,
        relinearize_threshold=be.relinearize_threshold,
        relinearize_skip=be.relinearize_skip,
        plane_relinearize_factor=10.0,
        lm_max_iterations=50,
        lm_relative_tolerance=1e-4,
        robust_schedule=(30.0, 10.0, 3.0),
        horizontal_sigma=np.radians(be.horizontal_prior_deg),
        vertical_sigma=np.radians(be.vertical_prior_deg),
        imu=imu_config if imu else None,
        use_motion_prior=not imu or ic.motion_prior,
        coalesce_blocks=be.solver == "window",
        solver=be.solver,
        window_knots=round(be.window_seconds / dt),
        window_iterations=be.window_iterations,
        isam2_iterations=be.isam2_iterations,
        isam2_fallback_iterations=5,
    )
