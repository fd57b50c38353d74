"""The back-end configuration of the default ``SlamConfig()``, for the tests: the one translation
the runner uses (``slam.params.backend_config``)."""

from __future__ import annotations

from slam.backend import BackendConfig
from slam.config import SlamConfig
from slam.params import backend_config


def backend_defaults(imu: bool = False) -> BackendConfig:
    """``BackendConfig`` of ``SlamConfig()``; with ``imu`` its IMU part as with an IMU present."""
    return backend_config(SlamConfig(), imu)
