"""What a SLAM run gives: the final estimates (world frame) and the run's statistics.

``SlamResult`` is complete: trajectory, planes with their marginal covariances, the plane map,
the segment-to-plane table and the run statistics as one typed record (``RunStats``, whose
:meth:`RunStats.to_dict` is what ``summary.json`` reports).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam.frontend.planemap import PlaneMap
from slam.trajectory.deskew import DeskewTable

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class BatchStats:
    """The final batch solve: errors (0.5 sum of squares with the robust losses), iterations, s."""

    initial_error: float
    final_error: float
    iterations: int
    seconds: float
    # how far the batch moved the trajectory's shape from the online estimate: the largest
    # difference (m) of the body-frame displacement over ``health.departure_window`` and its
    # time (s since the first knot); see :func:`slam.health.trajectory_departure`
    departure: float = 0.0
    departure_time: float = 0.0


@dataclass
class RunStats:
    """Counts of a run. The counters grow while it runs; ``knots`` to ``residuals`` are filled
    when the result is taken (``SlamRunner.result``)."""

    scans: int = 0
    segments: int = 0
    associated: int = 0  # segment observations made (at association, plane creation and adoption)
    planes_created: int = 0
    planes_merged: int = 0
    wall_layers_merged: int = 0  # of them: doors/boards found to be a second layer of their wall
    planes_transient: int = 0  # planes taken out as things that moved (people walking by)
    observation_blocks: int = 0
    updates: int = 0  # back-end updates (window solves or iSAM2 steps)
    skipped_scans: int = 0
    planes_rejected: int = 0
    planes_rejected_oblique: int = 0
    planes_parallel: int = 0  # doors and boards tied parallel to their wall
    wall_faces: int = 0
    isam2_rebuilds: int = 0
    isam2_fallbacks: int = 0
    imu_used: int = 0
    zero_velocity_updates: int = 0
    rest_idle_scans: int = 0  # a standing rig's repeated views left out (frontend.rest_observe_every)
    edges_created: int = 0
    edges_merged: int = 0
    edge_observations: int = 0
    trimmed_points: int = 0
    trimmed_blocks: int = 0
    knots: int = 0
    planes: int = 0
    edges: int = 0
    pool_dropped: int = 0
    singular_systems: list[str] = field(default_factory=list)
    batch: BatchStats | None = None
    residuals: dict[str, float] = field(default_factory=dict)
    # how the walk started (``frontend.initial_motion``): moving, speed (m/s), yaw rate (deg/s), ...
    initial_motion: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The statistics by name (``batch`` only after a final batch), as ``summary.json``
        reports them."""
        out = asdict(self)
        if self.batch is None:
            del out["batch"]
        return out

    def __getitem__(self, key: str) -> Any:
        """A statistic by its ``to_dict`` name."""
        return self.to_dict()[key]

    def get(self, key: str, default: Any = None) -> Any:
        """A statistic by its ``to_dict`` name, ``default`` when absent (``batch`` without a final batch)."""
        return self.to_dict().get(key, default)


class StageTimer:
    """Seconds spent per stage of a run, summed over calls."""

    def __init__(self) -> None:
        self.t: dict[str, float] = {}

    def add(self, name: str, since: float) -> float:
        """Add the time from ``since`` (``time.perf_counter``) to now to ``name``; returns now."""
        now = time.perf_counter()
        self.t[name] = self.t.get(name, 0.0) + now - since
        return now

    def add_seconds(self, name: str, seconds: float) -> None:
        """Add ``seconds`` measured elsewhere (another process) to ``name``."""
        self.t[name] = self.t.get(name, 0.0) + seconds


@dataclass
class SlamResult:
    """Final estimates and bookkeeping of a run (world frame).

    ``plane_covariances``: per plane id, the marginal covariance (3, 3) in the plane's retract
    coordinates (normal direction in its ``Unit3`` tangent, rad, then offset, m); a plane whose
    marginal the solver could not give is left out (and all of them when the result was taken
    without covariances). ``segment_rows``: per segment of every scan, its scanner, scan index,
    stamp, beam range and (resolved) plane id, sorted. ``deskew``: the gyro's rotation between
    knots (``slam.trajectory.deskew``) applied to body points, None without it.
    ``T_world_body_online``: the window's (online) poses of the same knots before the final batch,
    None when the result was taken without one."""

    knot_times: FloatArray
    T_world_body: FloatArray
    plane_ids: NDArray[np.int64]
    plane_normals: FloatArray
    plane_offsets: FloatArray
    plane_covariances: dict[int, FloatArray]
    plane_map: PlaneMap
    scanner_names: list[str]
    segment_rows: dict[str, NDArray[Any]]
    stats: RunStats
    timings: dict[str, float]
    deskew: DeskewTable | None
    T_world_body_online: FloatArray | None = None
