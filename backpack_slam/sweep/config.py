"""The experiment configuration (``configs/experiments/*.yaml``): the grid of a sweep.

A sweep is the Cartesian product of its axes::

    segmenter variants x worlds x noise levels x calibration errors x seeds

Each segmenter entry is a method with fixed ``params`` and an optional ``grid`` of
swept parameters (a list of values, or a range ``{start, stop, num}`` with both ends
included); an entry expands into one variant per combination of its grid values.
Every key is validated on load (``common.config.load``): an unknown key, a bad
value, an unknown segmenter, parameter or world is an error naming the file and the key.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

from pydantic import Field, field_validator, model_validator

from common.config import ConfigError, StrictModel, load, resolve_config
from simulation.run import SimulationConfig
from slam.config import SlamConfig


class ParamRange(StrictModel):
    """``num`` values from ``start`` to ``stop``, both included (``numpy.linspace``)."""

    start: float
    stop: float
    num: int = Field(ge=1, le=1000)

    def values(self) -> list[float]:
        if self.num == 1:
            return [self.start]
        step = (self.stop - self.start) / (self.num - 1)
        # rounded so that 0.007 + 2 * 0.002 prints as 0.011 in tables and hashes
        return [round(self.start + i * step, 12) for i in range(self.num)]


class SegmenterEntry(StrictModel):
    """One segmenter family: a method, fixed parameters and swept parameters."""

    method: str
    name: str | None = Field(default=None, description="label in the report (default: method and fixed params)")
    params: dict[str, Any] = Field(default_factory=dict)
    grid: dict[str, list[Any] | ParamRange] = Field(default_factory=dict)

    @field_validator("grid")
    @classmethod
    def _non_empty(cls, v: dict[str, list[Any] | ParamRange]) -> dict[str, list[Any] | ParamRange]:
        for k, vals in v.items():
            if isinstance(vals, list) and not vals:
                raise ValueError(f"grid '{k}' has no values")
        return v

    @model_validator(mode="after")
    def _valid(self) -> SegmenterEntry:
        from segmentation import segmenter_class

        cls = segmenter_class(self.method)  # ValueError naming the method and the known ones
        both = set(self.params) & set(self.grid)
        if both:
            raise ValueError(f"parameter(s) {sorted(both)} both fixed in params and swept in grid")
        for p in self.expand():
            cls.make_params(**p)  # ValueError naming a bad parameter or value
        return self

    @property
    def label(self) -> str:
        if self.name:
            return self.name
        fixed = " ".join(f"{k}={v}" for k, v in sorted(self.params.items()))
        return f"{self.method} {fixed}".strip()

    def expand(self) -> list[dict[str, Any]]:
        """Every parameter set of this entry: ``params`` merged with each grid combination."""
        keys = sorted(self.grid)
        axes = [g.values() if isinstance(g, ParamRange) else list(g) for g in (self.grid[k] for k in keys)]
        return [dict(self.params) | dict(zip(keys, combo, strict=True)) for combo in itertools.product(*axes)]


class CalibrationError(StrictModel):
    """A perturbation of the tilted scanners' extrinsics given to SLAM (the simulation uses
    the true rig): a rotation of ``rotation_deg`` about a random axis and a translation of
    ``translation_m`` along a random direction, both drawn from the cell's seed."""

    rotation_deg: float = Field(default=0.0, ge=0, le=45)
    translation_m: float = Field(default=0.0, ge=0, le=1)


class SegmentationMetricsConfig(StrictModel):
    """The per-beam comparison of each segmenter with the simulator's ground truth."""

    scans_per_scanner: int = Field(default=40, ge=0, description="scans sampled evenly per scanner (0: skip)")
    gt_min_run: int = Field(default=10, ge=1, description="ground-truth runs shorter than this (beams) are unlabelled")
    tolerance: int = Field(default=2, ge=0, description="boundary match tolerance (beams)")


class ExperimentConfig(StrictModel):
    """A sweep: axes, the simulation and SLAM settings shared by every cell."""

    name: str = Field(min_length=1)
    description: str = ""
    rig: str = "itc_backpack"
    duration: float = Field(gt=0, description="s walked per simulated run")
    seeds: list[int] = Field(min_length=1)
    worlds: list[str] = Field(min_length=1)
    noise: list[float] = Field(default_factory=lambda: [0.003], min_length=1, description="range sigma (m)")
    calibration: list[CalibrationError] = Field(default_factory=lambda: [CalibrationError()], min_length=1)
    segmenters: list[SegmenterEntry] = Field(min_length=1)
    simulation: SimulationConfig = Field(default_factory=lambda: SimulationConfig())
    slam: SlamConfig = Field(default_factory=lambda: SlamConfig())
    segmentation_metrics: SegmentationMetricsConfig = Field(default_factory=lambda: SegmentationMetricsConfig())
    keep_runs: bool = Field(default=False, description="keep every run folder (cloud, map) under DIR/runs/")

    @field_validator("noise")
    @classmethod
    def _noise(cls, v: list[float]) -> list[float]:
        for x in v:
            if not (math.isfinite(x) and x >= 0):
                raise ValueError(f"noise {x}: must be a finite range sigma >= 0 (m)")
        return v

    @field_validator("worlds")
    @classmethod
    def _worlds(cls, v: list[str]) -> list[str]:
        for w in v:
            resolve_config("worlds", w)  # ConfigError naming the world and the known ones
        return v

    @field_validator("rig")
    @classmethod
    def _rig(cls, v: str) -> str:
        resolve_config("rig", v)
        return v

    @field_validator("seeds")
    @classmethod
    def _unique_seeds(cls, v: list[int]) -> list[int]:
        if len(set(v)) != len(v):
            raise ValueError("seeds must be unique")
        return v

    @field_validator("simulation")
    @classmethod
    def _sim_axes(cls, v: SimulationConfig) -> SimulationConfig:
        # the axes set these per cell; a value here would be silently ignored
        owned = {"world", "rig", "seed", "duration"} & v.model_fields_set
        if owned:
            raise ValueError(f"'{sorted(owned)[0]}' is set by the sweep's axes; remove it here")
        return v

    @field_validator("slam")
    @classmethod
    def _slam_axes(cls, v: SlamConfig) -> SlamConfig:
        if "segmenter" in v.model_fields_set:
            raise ValueError("'segmenter' is set by the sweep's 'segmenters'; remove it here")
        return v

def load_experiment(path: str | Path) -> ExperimentConfig:
    """An ExperimentConfig from YAML; every error names the file and the key."""
    try:
        return load(ExperimentConfig, path)
    except ConfigError:
        raise
    except ValueError as e:  # raised outside pydantic's validation (defensive)
        raise ConfigError(f"{path}: {e}") from None
