"""Cells of a sweep: the grid of an ExperimentConfig expanded, each with its content hashes.

A cell is everything one SLAM run needs, as plain JSON-able values, so that it pickles to a
worker process or a Dask worker unchanged. ``sim_key`` hashes what the simulation depends on
(world and rig files' contents included), so every segmenter of a (world, noise, seed) shares
one bag; ``cell_id`` hashes the whole cell and is the key by which a sweep resumes.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from backpack_slam.sweep.config import ExperimentConfig
from common.config import resolve_config


def content_hash(data: Any, n: int = 16) -> str:
    """Hex digest of the canonical JSON of ``data`` (sorted keys), ``n`` characters."""
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:n]


def file_hash(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


@dataclass(frozen=True)
class Cell:
    """One run of the grid (every value plain JSON)."""

    world: str
    seed: int
    duration: float
    noise: float
    calib_rotation_deg: float
    calib_translation_m: float
    segmenter: str  # the family's label
    method: str
    params: dict[str, Any]  # every parameter given (fixed and swept)
    swept: dict[str, Any]  # the swept ones only
    rig: str
    simulation: dict[str, Any]  # a full SimulationConfig dump (world, seed, duration, noise set)
    slam: dict[str, Any]  # a full SlamConfig dump (segmenter set)
    segmentation_metrics: dict[str, Any]
    inputs: dict[str, str] = field(default_factory=dict)  # hashes of the world and rig files
    keep_runs: bool = False

    @property
    def sim_key(self) -> str:
        return content_hash({"simulation": self.simulation, "inputs": self.inputs})

    @property
    def cell_id(self) -> str:
        return content_hash(
            {
                "sim": self.sim_key,
                "slam": self.slam,
                "calibration": [self.calib_rotation_deg, self.calib_translation_m],
                "segmentation_metrics": self.segmentation_metrics,
            }
        )

    @property
    def variant(self) -> str:
        """Family and swept values, e.g. ``ror combined sigma=0.0095``."""
        swept = " ".join(f"{k}={v}" for k, v in sorted(self.swept.items()))
        return f"{self.segmenter} {swept}".strip()

    def describe(self) -> dict[str, Any]:
        """The cell's axes as result-table columns."""
        return {
            "cell_id": self.cell_id,
            "sim_key": self.sim_key,
            "world": self.world,
            "seed": self.seed,
            "duration": self.duration,
            "noise": self.noise,
            "calib_rotation_deg": self.calib_rotation_deg,
            "calib_translation_m": self.calib_translation_m,
            "segmenter": self.segmenter,
            "method": self.method,
            "variant": self.variant,
            "params": json.dumps(self.params, sort_keys=True),
            "swept": json.dumps(self.swept, sort_keys=True),
        }


def plan_cells(cfg: ExperimentConfig) -> list[Cell]:
    """Every cell of the grid, grouped by simulation (so that a bag's cells run together)."""
    rig_file = resolve_config("rig", cfg.rig)
    cells: list[Cell] = []
    for world in cfg.worlds:
        inputs = {"world": file_hash(resolve_config("worlds", world)), "rig": file_hash(rig_file)}
        for noise in cfg.noise:
            for seed in cfg.seeds:
                sim = cfg.simulation.model_dump(mode="json") | {
                    "world": world,
                    "rig": cfg.rig,
                    "seed": seed,
                    "duration": cfg.duration,
                }
                sim["noise"] = sim["noise"] | {"range_sigma": noise}
                for cal in cfg.calibration:
                    for entry in cfg.segmenters:
                        for params in entry.expand():
                            slam = cfg.slam.model_dump(mode="json")
                            slam["segmenter"] = {"method": entry.method, "params": params}
                            cells.append(
                                Cell(
                                    world=world,
                                    seed=seed,
                                    duration=cfg.duration,
                                    noise=noise,
                                    calib_rotation_deg=cal.rotation_deg,
                                    calib_translation_m=cal.translation_m,
                                    segmenter=entry.label,
                                    method=entry.method,
                                    params=params,
                                    swept={k: params[k] for k in sorted(entry.grid)},
                                    rig=cfg.rig,
                                    simulation=sim,
                                    slam=slam,
                                    segmentation_metrics=cfg.segmentation_metrics.model_dump(mode="json"),
                                    inputs=inputs,
                                    keep_runs=cfg.keep_runs,
                                )
                            )
    ids = [c.cell_id for c in cells]
    if len(set(ids)) != len(ids):
        raise ValueError(f"experiment '{cfg.name}': {len(ids) - len(set(ids))} duplicated cell(s) in the grid")
    return cells
