"""The back end's settings and the records its solves return."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from slam.backend.factors import RobustKernel
from slam.motion import ImuConfig, MotionPriorConfig

SolverName = Literal["window", "isam2"]


@dataclass(frozen=True)
class BackendConfig:
    """Back-end settings (validated on construction; a bad value is a ValueError naming it). No
    field has a default: the values come from the YAML model (``slam.config``).

    kernel: per-point robust kernel of the observation blocks.
    motion: constant-velocity prior densities; ``use_motion_prior`` switches it off.
    initial_velocity_sigmas: (rad/s, m/s) of the weak prior on the first interval's motion.
    datum: ``"pose"`` fixes the first knot; ``"position_yaw"`` fixes its position and rotation
        about the body z axis only (with horizontal-plane priors giving the vertical).
    datum_sigma: sigma (rad and m) of the datum prior.
    datum_tilt_sigma: sigma (rad) on the first knot's roll and pitch with ``position_yaw``: loose, so
        the horizontal-plane priors level the map, yet finite so the system stays well conditioned.
    vertical_sigma, horizontal_sigma: sigmas [rad] of the wall verticality and floor/ceiling
        horizontality priors.
    relinearize_threshold, relinearize_skip: iSAM2 relinearisation settings.
    plane_relinearize_factor: iSAM2 relinearisation threshold of planes, as a multiple of
        ``relinearize_threshold`` (the poses').
    lm_max_iterations, lm_relative_tolerance: a solve's iterations and stopping rule (relative
        error decrease), per stage.
    batch_relative_tolerance: the stopping rule of :meth:`Backend.batch_optimize`'s solves (the
        final batch), in place of ``lm_relative_tolerance`` (the window's).
    robust_schedule: kernel-threshold multipliers of the stages that precede the nominal one in a
        graduated batch (a redescending kernel at 3 sigma from an initial guess that is
        centimetres off would treat every point as an outlier).
    imu: IMU noise and mounting; None without an IMU.
    coalesce_blocks: a block added on the (knot, plane) of a block not yet summarised joins it
        (one factor instead of two: the per-factor cost dominates small blocks); the returned
        block id is then the joint block's and the earlier id is gone.
    solver: the incremental solver :meth:`Backend.step` runs: ``"window"`` (fixed-lag window,
        older blocks summarised) or ``"isam2"``.
    window_knots: knots before the newest that a window step re-estimates.
    window_iterations: Gauss-Newton iterations of a window step.
    isam2_iterations: iSAM2 steps per :meth:`Backend.step`.
    isam2_fallback_iterations: batch iterations taken when an iSAM2 step fails even after a rebuild.
    batch_section_knots: a walk of more knots has its final batch (and plane covariances) solved in
        time-ordered sections of at most this many knots (:mod:`slam.backend.sections`).
    batch_whole_knots: a walk of at most this many knots is solved whole all the same (faster: the
        sections' separator and passes cost a third more CPU on the 10-minute office walk).
    batch_cache_bytes: how much a sectioned final batch keeps from one pass to the next: the
        sections' eliminations first, then their factors (estimated from their points); what does
        not fit is eliminated or built again.
    batch_heap_slack_bytes: a pass over the sections trims the C heap whenever its resident memory
        has risen by this much since the last trim (0: after every section).
    fold_links_in_window: :meth:`Backend.step` first merges the planes linked since the last step
        (:meth:`Backend.fold_links`) instead of carrying the links to the end of the run.
    """

    kernel: RobustKernel
    motion: MotionPriorConfig
    use_motion_prior: bool
    initial_velocity_sigmas: tuple[float, float]
    datum: Literal["pose", "position_yaw"]
    datum_sigma: float
    datum_tilt_sigma: float
    vertical_sigma: float
    horizontal_sigma: float
    relinearize_threshold: float
    relinearize_skip: int
    plane_relinearize_factor: float
    lm_max_iterations: int
    lm_relative_tolerance: float
    robust_schedule: tuple[float, ...]
    imu: ImuConfig | None
    coalesce_blocks: bool
    solver: SolverName
    window_knots: int
    window_iterations: int
    isam2_iterations: int
    isam2_fallback_iterations: int
    batch_section_knots: int
    batch_cache_bytes: int
    batch_heap_slack_bytes: int
    fold_links_in_window: bool
    batch_whole_knots: int
    batch_relative_tolerance: float

    def __post_init__(self) -> None:
        if self.datum not in ("pose", "position_yaw"):
            raise ValueError(f"datum: expected 'pose' or 'position_yaw', got {self.datum!r}")
        if self.solver not in ("window", "isam2"):
            raise ValueError(f"solver: expected 'window' or 'isam2', got {self.solver!r}")
        for name in ("datum_sigma", "datum_tilt_sigma", "vertical_sigma", "horizontal_sigma",
                     "relinearize_threshold", "plane_relinearize_factor", "lm_relative_tolerance",
                     "batch_relative_tolerance"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f"{name}: must be > 0, got {v}")
        if min(self.initial_velocity_sigmas) <= 0.0:
            raise ValueError(f"initial_velocity_sigmas: must be > 0, got {self.initial_velocity_sigmas}")
        if any(not (s >= 1.0) for s in self.robust_schedule):
            raise ValueError(f"robust_schedule: multipliers must be >= 1, got {self.robust_schedule}")
        for name in ("relinearize_skip", "lm_max_iterations", "window_iterations", "isam2_iterations",
                     "isam2_fallback_iterations", "batch_section_knots"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: must be >= 1, got {getattr(self, name)}")
        if self.batch_whole_knots < 0:
            raise ValueError(f"batch_whole_knots: must be >= 0, got {self.batch_whole_knots}")
        if self.batch_heap_slack_bytes < 0:
            raise ValueError(f"batch_heap_slack_bytes: must be >= 0, got {self.batch_heap_slack_bytes}")
        if self.batch_cache_bytes < 0:
            raise ValueError(f"batch_cache_bytes: must be >= 0, got {self.batch_cache_bytes}")
        if self.window_knots < 0:
            raise ValueError(f"window_knots: must be >= 0, got {self.window_knots}")


@dataclass(frozen=True)
class OptimizeSummary:
    """Outcome of a batch or window solve: errors (0.5 sum of squares incl. robust losses),
    iterations and wall time [s]."""

    initial_error: float
    final_error: float
    iterations: int
    seconds: float


@dataclass(frozen=True)
class StepReport:
    """Outcome of :meth:`Backend.step`: whether a solve ran (it needs two knots), and how often
    iSAM2 was rebuilt after a failed step and fell back to a few batch iterations (0 for the
    window solver)."""

    solved: bool
    rebuilds: int
    fallbacks: int
