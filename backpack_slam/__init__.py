"""backpack-slam: the command-line interface and the Python API (``run``, ``simulate``,
``evaluate``; see :mod:`backpack_slam.api`), the top layer that wires segmentation, simulation,
slam and calibration together.

The API is imported when first used, not with the package: ``python -m backpack_slam.cli``
then reaches its signal handlers within milliseconds (a SIGINT during the seconds of numpy,
scipy and numba imports was a traceback, a SIGTERM an exit by the signal)."""

import os
from typing import TYPE_CHECKING, Any

# numpy's BLAS threads cost far more than they give on the small dense systems of the front end
# (and the sweep runs cells in parallel processes): set before numpy loads (the API imports it)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

if TYPE_CHECKING:
    from backpack_slam.api import Health, Result, evaluate, run, simulate

__all__ = ["Health", "Result", "evaluate", "run", "simulate"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from backpack_slam import api

        return getattr(api, name)
    raise AttributeError(f"module 'backpack_slam' has no attribute {name!r}")
