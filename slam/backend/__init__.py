"""The SLAM back end: body poses at knots and world planes in one gtsam factor graph."""

from slam.backend.facade import Backend, BackendConfig, ObservationBlock, OptimizeSummary
from slam.backend.factors import RobustKernel

__all__ = ["Backend", "BackendConfig", "ObservationBlock", "OptimizeSummary", "RobustKernel"]
