"""The rig: the scanners on the backpack, their models and extrinsics ``T_body_scanner``.

Frames: ``body`` is the rig frame (x forward, y left, z up); the reference
scanner defines it (its extrinsic is the identity). ``scanner_i`` has x along
the 0-rad beam and the scan plane at z = 0. ``T_body_scanner`` maps points
from the scanner frame to the body frame: ``p_body = R p_scanner + t``.
Rotations are given as roll, pitch, yaw in radians (``R = Rz(yaw) Ry(pitch)
Rx(roll)``). Covariances are 6x6 over (rotation, translation) tangent
coordinates, gtsam's Pose3 order.
"""

from __future__ import annotations

import math
from functools import cached_property
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from numpy.typing import NDArray
from pydantic import Field, field_validator, model_validator

from common.atomic import write_text
from common.config import StrictModel, load, resolve_config
from common.rotations import rpy_to_matrix

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class ScannerModel(StrictModel):
    """A 2D scanner's geometry, timing and noise.

    Beam i has angle ``angle_min + i * angle_increment`` and is taken at
    ``stamp + i * time_increment`` (a continuously turning mirror).
    """

    name: str = "utm30lx"
    n_beams: int = Field(1081, gt=1, le=100_000)
    angle_min: float = Field(-math.radians(135.0), ge=-2 * math.pi, le=2 * math.pi)
    angle_increment: float = Field(math.radians(0.25), gt=0, le=math.pi)
    scan_period: float = Field(0.025, gt=0, le=10.0, description="s per mirror turn (1 / scan rate)")
    time_increment: float = Field(0.025 / 1440.0, ge=0, le=1.0, description="s between beams")
    range_min: float = Field(0.1, ge=0)
    range_max: float = Field(30.0, gt=0, le=10_000.0)
    range_sigma: float = Field(0.003, ge=0, le=1.0, description="range noise standard deviation (m)")

    @model_validator(mode="after")
    def _consistent(self) -> ScannerModel:
        if self.range_min >= self.range_max:
            raise ValueError(f"range_min {self.range_min:g} must be below range_max {self.range_max:g}")
        if (self.n_beams - 1) * self.angle_increment > 2 * math.pi + 1e-9:
            raise ValueError(f"{self.n_beams} beams at {self.angle_increment:g} rad span more than a full turn")
        return self

    @property
    def angle_max(self) -> float:
        return self.angle_min + (self.n_beams - 1) * self.angle_increment

    def beam_angles(self) -> NDArray[np.float64]:
        return self.angle_min + self.angle_increment * np.arange(self.n_beams, dtype=np.float64)

    def beam_offsets(self) -> NDArray[np.float64]:
        """Time of each beam after the scan's stamp (s)."""
        return self.time_increment * np.arange(self.n_beams, dtype=np.float64)


MODELS: dict[str, ScannerModel] = {
    # Hokuyo UTM-30LX: 1081 beams over 270 deg, 40 Hz; the seed paper measured ~3 mm below 5 m
    "utm30lx": ScannerModel(),
    # the same scanner as published by Cartographer's backpack recordings: 1079 beams
    "utm30lx_1079": ScannerModel(name="utm30lx_1079", n_beams=1079, angle_min=-math.radians(134.75)),
    # Hokuyo URG-04LX: 726 beams (the driver's full sweep) at 0.3516 deg, 10 Hz, 0.02-5.6 m,
    # +-10 mm to 1 m and 1 % of range beyond: ~1 cm at indoor ranges
    "urg04lx": ScannerModel(name="urg04lx", n_beams=726, angle_min=-math.radians(127.62),
                            angle_increment=math.radians(360.0 / 1024.0), scan_period=0.1,
                            time_increment=0.1 / 1024.0, range_min=0.02, range_max=5.6, range_sigma=0.01),
    # SICK TiM571: 811 beams over 270 deg at 1/3 deg, 15 Hz, 0.05-25 m, ~20 mm statistical error
    "tim571": ScannerModel(name="tim571", n_beams=811, angle_min=-math.radians(135.0),
                           angle_increment=math.radians(1.0 / 3.0), scan_period=1.0 / 15.0,
                           time_increment=1.0 / 15.0 / 1080.0, range_min=0.05, range_max=25.0, range_sigma=0.02),
}
MessageType = Literal["LaserScan", "MultiEchoLaserScan"]


class Extrinsic(StrictModel):
    """``T_body_scanner``: translation (m) and roll/pitch/yaw (rad)."""

    translation: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    rpy: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    covariance: list[list[float]] | None = None

    @field_validator("covariance")
    @classmethod
    def _cov_shape(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        if v is not None:
            a = np.asarray(v, dtype=float)
            if a.shape != (6, 6) or not np.allclose(a, a.T):
                raise ValueError("must be a symmetric 6x6 matrix over (rotation, translation)")
        return v

    def matrix(self) -> NDArray[np.float64]:
        """The 4x4 homogeneous transform."""
        T = np.eye(4)
        T[:3, :3] = rpy_to_matrix(*self.rpy)
        T[:3, 3] = self.translation
        return T


class ScannerConfig(StrictModel):
    """One scanner on the rig: its topic, model, mounting ``T_body_scanner`` and clock offset.

    ``frame_id`` is the scanner's frame in the bag's transforms (default: its name);
    ``message`` the type it is recorded as (the simulator writes it; the readers take either).
    """

    name: str
    topic: str
    model: str | ScannerModel = "utm30lx"
    T_body_scanner: Extrinsic = Field(default_factory=Extrinsic)
    time_offset: float = 0.0
    frame_id: str | None = None
    message: MessageType = "LaserScan"

    @property
    def frame(self) -> str:
        """The scanner's frame name in the bag's transforms."""
        return self.frame_id or self.name

    @field_validator("model")
    @classmethod
    def _known_model(cls, v: str | ScannerModel) -> str | ScannerModel:
        if isinstance(v, str) and v not in MODELS:
            raise ValueError(f"unknown scanner model '{v}'; known: {', '.join(MODELS)}")
        return v

    @cached_property
    def scanner_model(self) -> ScannerModel:
        return MODELS[self.model] if isinstance(self.model, str) else self.model


class ImuMount(StrictModel):
    """The rig's IMU: its topic and frame. Its axes are the body frame's (the usual backpack
    set-up, where the body frame is the IMU's: Cartographer's base_link = imu_link)."""

    topic: str = "/imu"
    frame_id: str = "body"


class Rig(StrictModel):
    """Three (or any number of) 2D scanners rigidly mounted on the backpack.

    ``body_frame`` names the body frame in the bag's transforms; ``reference`` is the scanner
    whose extrinsic calibration holds fixed (usually the body's origin, ``T_body_scanner = I``).
    """

    name: str
    reference: str = Field(description="name of the scanner that defines the body frame")
    scanners: list[ScannerConfig] = Field(min_length=1)
    body_frame: str = "body"
    imu: ImuMount = Field(default_factory=ImuMount)

    @model_validator(mode="after")
    def _check(self) -> Rig:
        names = [s.name for s in self.scanners]
        if len(set(names)) != len(names):
            raise ValueError("scanner names must be unique")
        topics = [s.topic for s in self.scanners]
        if len(set(topics)) != len(topics):
            raise ValueError(f"scanner topics must be unique (each scanner records on its own topic): {topics}")
        if self.reference not in names:
            raise ValueError(f"reference '{self.reference}' is not one of the scanners {names}")
        return self

    def scanner(self, name: str) -> ScannerConfig:
        for s in self.scanners:
            if s.name == name:
                return s
        raise KeyError(f"rig '{self.name}' has no scanner '{name}'")

    def by_topic(self) -> dict[str, ScannerConfig]:
        return {s.topic: s for s in self.scanners}


def rig_yaml(rig: Rig, header: str = "") -> str:
    """The rig as YAML (``header`` lines as comments first): what :func:`load_rig` reads back."""
    text = yaml.safe_dump(rig.model_dump(mode="json", exclude_defaults=True), sort_keys=False,
                          default_flow_style=None, width=120)
    return "".join(f"# {line}\n" for line in header.splitlines()) + text


def write_rig(path: str | Path, rig: Rig, header: str = "") -> Path:
    """Write ``rig`` as YAML to ``path`` atomically."""
    return write_text(path, rig_yaml(rig, header))


def load_rig(path: str | Path) -> Rig:
    """Load and validate a rig YAML file (errors name the file and the key)."""
    return load(Rig, path)


def resolve_rig(name_or_path: str | Path) -> Rig:
    """A rig name (``configs/rig/<name>.yaml``) or a YAML path -> the validated Rig."""
    return load_rig(resolve_config("rig", name_or_path))
