"""The sweep's simulation cache: one bag and ground-truth folder per simulation hash.

``DIR/cache/<sim_key>/run.bag`` and ``run.gt/``. Safe under concurrency (processes on one
machine or Dask workers sharing the folder): an exclusive ``flock`` on ``<sim_key>.lock``
makes the other workers wait instead of simulating the same run, and the run is written into
a temporary folder renamed into place when complete, so a crash never leaves a half-written
entry (a folder that exists is complete).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

BAG_NAME = "run.bag"


@dataclass(frozen=True)
class CachedSimulation:
    bag: Path
    gt: Path
    cached: bool  # True when an earlier cell had already simulated it
    seconds: float  # wall time of the simulation (0 when cached) or of the wait for it


@contextmanager
def file_lock(path: Path) -> Iterator[None]:
    """An exclusive advisory lock held for the block (blocks until free)."""
    with open(path, "a+") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def cached_simulation(cache_dir: str | Path, sim_key: str, sim_config: dict[str, Any]) -> CachedSimulation:
    """The bag of ``sim_config`` (a SimulationConfig dump), simulated on first use."""
    from simulation.run import SimulationConfig, bag_path_for, gt_dir_for, simulate

    cfg = SimulationConfig.model_validate(sim_config)
    root = Path(cache_dir)
    root.mkdir(parents=True, exist_ok=True)
    entry = root / sim_key
    bag = bag_path_for(entry / BAG_NAME, cfg.format)
    t0 = time.perf_counter()
    if entry.is_dir():
        return CachedSimulation(bag, gt_dir_for(bag), True, 0.0)
    with file_lock(root / f"{sim_key}.lock"):
        if entry.is_dir():  # simulated by another worker while we waited
            return CachedSimulation(bag, gt_dir_for(bag), True, time.perf_counter() - t0)
        tmp = root / f".{sim_key}.tmp-{uuid.uuid4().hex[:8]}"
        try:  # made inside: an interrupt right after the mkdir still removes it
            tmp.mkdir()
            simulate(cfg.world, cfg.rig, out=tmp / BAG_NAME, config=cfg, progress=False)
            os.replace(tmp, entry)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return CachedSimulation(bag, gt_dir_for(bag), False, time.perf_counter() - t0)
