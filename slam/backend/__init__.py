"""The SLAM back end: body poses at knots and world planes in one gtsam factor graph
(:class:`Backend`, a facade over the parts in this package; see :mod:`slam.backend.facade`)."""

from slam.backend.blocks import ObservationBlock
from slam.backend.config import BackendConfig, OptimizeSummary, StepReport
from slam.backend.facade import Backend
from slam.backend.factors import RobustKernel

__all__ = ["Backend", "BackendConfig", "ObservationBlock", "OptimizeSummary", "RobustKernel", "StepReport"]
