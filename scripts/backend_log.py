"""A run's back-end calls, recorded and replayed: the back end's cost measured on its own.

:func:`record` runs SLAM on a bag with ``slam.pipeline.Backend`` replaced by a subclass that logs
every public call (method name, copies of its arguments, its result) in order; :func:`replay`
makes the same calls on a fresh ``Backend`` of the code on ``sys.path`` and charges each call's
CPU time (``time.process_time``) to a stage (:data:`STAGES`). The front end's decisions are
fixed by the log, so two replays (two versions of the back end) do the same work; with the same
back-end arithmetic their estimates agree bit for bit.

The log is a pickle of ``{"config": BackendConfig, "calls": [(name, args, kwargs, result)],
"data_duration": s}``.
"""

from __future__ import annotations

import copy
import pickle
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

# stage of each Backend method in a replay
STAGES: dict[str, str] = {
    **dict.fromkeys(("add_pose", "add_imu", "add_velocity_prior", "add_plane", "add_observations",
                     "remove_observations", "merge_planes", "link_planes", "add_parallel", "add_perpendicular",
                     "remove_plane", "blocks_of_plane", "block"), "graph building"),
    "step": "window solves",
    **dict.fromkeys(("fold_links", "batch_optimize", "trim_observations", "error"), "final batch"),
    **dict.fromkeys(("plane_covariance", "pose_covariance", "residual_statistics"), "covariances, statistics"),
}
QUERY = "estimate queries"  # every other method (poses, planes, predictions, residuals)
ORDER = ("graph building", "window solves", QUERY, "final batch", "covariances, statistics")


def _public_methods(cls: type) -> list[str]:
    return [n for n, v in vars(cls).items() if callable(v) and not n.startswith("_")]


def record(bag: Path, log: Path, out: Path) -> dict[str, Any]:
    """Run SLAM (default config with the back end in this process, rig ``itc_backpack``) on ``bag``
    into ``out`` and write the back-end call log to ``log``; returns the run's summary."""
    import slam.backend_process
    from common.rig import resolve_rig
    from slam.backend import Backend
    from slam.config import SlamConfig
    from slam.run import run_slam

    calls: list[tuple[str, tuple[Any, ...], dict[str, Any], Any]] = []
    configs: list[Any] = []

    def wrap(name: str) -> Callable[..., Any]:
        orig = getattr(Backend, name)

        def method(self: Backend, *args: Any, **kwargs: Any) -> Any:
            a, k = copy.deepcopy(args), copy.deepcopy(kwargs)
            result = orig(self, *args, **kwargs)
            calls.append((name, a, k, result if isinstance(result, int) else None))
            return result

        return method

    class RecordingBackend(Backend):
        def __init__(self, config: Any) -> None:
            configs.append(config)
            super().__init__(config)

    for name in _public_methods(Backend):
        setattr(RecordingBackend, name, wrap(name))
    saved = slam.backend_process.Backend
    slam.backend_process.Backend = RecordingBackend  # type: ignore[misc]
    config = SlamConfig.model_validate({"backend": {"pipelined": False}})  # every call in this process, in order
    try:
        summary = run_slam(bag, resolve_rig("itc_backpack"), config, out, progress=False)
    finally:
        slam.backend_process.Backend = saved  # type: ignore[misc]
    with open(log, "wb") as f:
        pickle.dump({"config": configs[0], "calls": calls, "data_duration": summary["data_duration"]}, f)
    return summary


def warm_up(data: dict[str, Any]) -> None:
    """Compile the back end's numba kernels (a run's first calls and a short batch), so that a
    replay's CPU time is the work's, not the compiler's (a fresh tree has no numba cache)."""
    from slam.backend import Backend

    be = Backend(data["config"])
    steps = 0
    for name, args, kwargs, _ in data["calls"]:
        getattr(be, name)(*args, **kwargs)
        steps += name == "step"
        if steps == 2:
            break
    be.batch_optimize(1, graduated=False)


def load(log: Path) -> dict[str, Any]:
    with open(log, "rb") as f:
        data: dict[str, Any] = pickle.load(f)
    return data


def replay(data: dict[str, Any], profile: Path | None = None) -> dict[str, Any]:
    """Replay a call log (:func:`load`) on the ``Backend`` importable now; returns CPU seconds per
    stage, the call counts, the mismatched results (ids that differ from the recording), the
    data duration and the final estimate (poses, plane ids/normals/offsets). With ``profile``,
    cProfile stats of the replay (CPU time) are written there."""
    from slam.backend import Backend

    seconds = dict.fromkeys(ORDER, 0.0)
    counts = dict.fromkeys(ORDER, 0)
    mismatches = 0
    prof = None
    if profile is not None:
        import cProfile

        prof = cProfile.Profile(time.process_time)
        prof.enable()
    be = Backend(data["config"])
    clock = time.process_time
    for name, args, kwargs, result in data["calls"]:
        stage = STAGES.get(name, QUERY)
        t0 = clock()
        out = getattr(be, name)(*args, **kwargs)
        seconds[stage] += clock() - t0
        counts[stage] += 1
        if isinstance(result, int) and out != result:
            mismatches += 1
    if prof is not None:
        prof.disable()
        prof.dump_stats(str(profile))
    ids, normals, offsets = be.planes()
    return {"seconds": seconds, "counts": counts, "mismatches": mismatches, "data_duration": data["data_duration"],
            "poses": np.asarray(be.poses()), "plane_ids": ids, "normals": normals, "offsets": offsets}

