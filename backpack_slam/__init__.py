"""backpack-slam: the command-line interface and the Python API (``run``, ``simulate``,
``evaluate``; see :mod:`backpack_slam.api`), the top layer that wires segmentation, simulation,
slam and calibration together."""

import os

# numpy's BLAS threads cost far more than they give on the small dense systems of the front end
# (and the sweep runs cells in parallel processes): set before numpy loads (the API imports it)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from backpack_slam.api import Health, Result, evaluate, run, simulate

__all__ = ["Health", "Result", "evaluate", "run", "simulate"]
