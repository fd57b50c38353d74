"""The Python API: the same functions the command line calls.

    import backpack_slam as bs
    result = bs.run("walk.bag", out="walk_slam")          # rig from the bag's /tf_static
    result.health.verdict, result.times, result.T_world_body.shape
    for chunk in result.cloud():                           # world-frame points, a chunk at a time
        ...
    sim = bs.simulate("office", "itc_backpack", duration=60, out="office.bag")
    report = bs.evaluate(bs.run(sim.bag, out="office_slam").run_dir, sim.gt)

Frames: ``T_world_body`` maps body-frame points into the SLAM world (the first pose, levelled);
planes are ``n . x + d = 0`` in that world. Errors are ``ValueError`` subclasses with one-line
messages naming the input (a rig that does not match the recording, a bag without scans, ...).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Health:
    """The run's verdict on its own estimate: ``ok``, ``degraded`` or ``failed``, and one line
    per problem."""

    verdict: str
    problems: list[str]


@dataclass(frozen=True)
class Result:
    """A finished run: the trajectory (``times`` (K,), ``T_world_body`` (K, 4, 4)), the planes
    (ids, unit normals (P, 3), offsets (P,)), the health verdict, the summary and the run folder."""

    run_dir: Path
    times: FloatArray
    T_world_body: FloatArray
    plane_ids: NDArray[np.int64]
    plane_normals: FloatArray
    plane_offsets: FloatArray
    health: Health
    summary: dict[str, Any]

    @property
    def files(self) -> dict[str, Path]:
        """The run folder's files by name."""
        return {p.name: p for p in sorted(self.run_dir.iterdir()) if p.is_file()}

    def cloud(self, chunk: int = 1 << 20) -> Iterator[Any]:
        """The cloud (world frame), ``chunk`` points at a time: records with ``points_world``,
        ``scanner``, ``time`` and ``plane_id`` (the cloud is never held whole)."""
        from slam.export import iter_cloud_ply

        return iter_cloud_ply(self.run_dir / "cloud.ply", chunk)


def run(bag: str | Path, rig: str | Path | Any | None = None, config: str | Path | Any | None = None,
        segmenter: str | None = None, out: str | Path | None = None, urdf: str | Path | None = None,
        params: dict[str, Any] | None = None, progress: bool = False) -> Result:
    """SLAM on ``bag``: ``rig`` a name, a YAML path, a ``common.rig.Rig`` or None (built from the
    bag's transforms or ``urdf``); ``config`` a YAML path, a ``SlamConfig`` or None (defaults);
    ``segmenter`` and ``params`` override the configured segmenter. Writes the run folder ``out``
    (default: ``<bag>_slam`` beside the bag) and returns its :class:`Result`."""
    from common.rig import Rig, resolve_rig
    from slam.config import SlamConfig, load_slam_config, with_segmenter
    from slam.export import read_planes_json, read_trajectory_tum
    from slam.run import run_slam

    rig_obj = rig if isinstance(rig, Rig) or rig is None else resolve_rig(rig)
    cfg = config if isinstance(config, SlamConfig) else load_slam_config(config)
    cfg = with_segmenter(cfg, segmenter, params or {})
    run_dir = Path(out) if out is not None else Path(bag).with_name(Path(bag).stem + "_slam")
    summary = run_slam(bag, rig_obj, cfg, run_dir, progress=progress, urdf=urdf)
    times, T = read_trajectory_tum(run_dir / "trajectory.tum")
    planes = read_planes_json(run_dir / "planes.json")
    h = summary["health"]
    return Result(
        run_dir=run_dir, times=times, T_world_body=T,
        plane_ids=np.array([p.id for p in planes], dtype=np.int64),
        plane_normals=np.array([p.normal for p in planes], dtype=np.float64).reshape(-1, 3),
        plane_offsets=np.array([p.d for p in planes], dtype=np.float64),
        health=Health(h["verdict"], [f"{p['severity']}: {p['message']}" for p in h["problems"]]),
        summary=summary,
    )


def simulate(world: str | Path = "demo", rig: str | Path = "itc_backpack", duration: float = 60.0, seed: int = 1,
             out: str | Path = "run.bag", **config: Any) -> Any:
    """Simulate a walk through ``world`` with ``rig`` into the bag ``out`` and its ground truth
    ``<out>.gt/``; keyword arguments are ``simulation.run.SimulationConfig`` keys (``imu=True``,
    ``noise={"range_sigma": 0.01}``, ``people={"walkers": 4}``, ``gait={"start_speed": 1.0}``, ...).
    Returns ``simulation.run.SimulationResult`` (``.bag``, ``.gt``)."""
    from simulation.run import SimulationConfig
    from simulation.run import simulate as _simulate

    cfg = SimulationConfig.model_validate({"duration": duration, "seed": seed, **config})
    return _simulate(world, rig, out=out, config=cfg, progress=False)


def evaluate(run_dir: str | Path, gt: str | Path, write: bool = True) -> Any:
    """Evaluate a run folder against a simulator ground truth (``<bag>.gt``): ATE/RPE, plane and
    cloud errors, association. With ``write``, ``eval.json`` and the plots go into the run folder.
    Returns ``slam.evaluate.EvalResult``."""
    from slam.eval_plots import write_plots
    from slam.evaluate import evaluate as _evaluate
    from slam.evaluate import write_eval_json

    res = _evaluate(run_dir, gt)
    if write:
        write_eval_json(Path(run_dir) / "eval.json", res)
        write_plots(res, Path(run_dir))
    return res
