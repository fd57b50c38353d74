"""The 2D scanner model (Hokuyo UTM-30LX by default) on a moving rig.

Geometry: beam ``i`` of a scan stamped ``t`` (the time of its first beam) leaves
the scanner at angle ``angle_min + i * angle_increment`` in the scanner's scan
plane (z = 0 of frame ``scanner``) at time ``t + i * time_increment`` (the mirror
turns continuously: 1440 steps per 25 ms turn, the 1081 beams take 18.75 ms).
Every ray's origin and direction come from the true trajectory at that beam's
time: ``T_world_scanner(t_i) = T_world_body(t_i) @ T_body_scanner``.

Measurement model (``ScannerNoiseConfig``), applied in this order:

1. mixed pixels: where two neighbouring beams of a scan jump in depth by more than
   ``mixed_jump``, with probability ``mixed_prob`` one of the two (chosen at random)
   returns a range uniformly between foreground and background;
2. range noise: Gaussian, ``sigma = (range_sigma + range_sigma_per_m * r) *
   (1 + incidence_sigma * (1 / cos(incidence) - 1))``;
3. dropouts: with probability ``clip(1 - cos(incidence) / grazing_cos, 0, 1)`` at grazing
   incidence, and ``dropout_rate`` everywhere;
4. quantisation to ``quantization`` (1 mm).

Invalid returns follow the LaserScan convention: ``inf`` for no return (nothing
hit, or beyond ``range_max``), ``NaN`` for a dropout or a return closer than
``range_min``. Per-beam ground truth: the plane id and object kind of the surface
that produced a valid return; ``-1`` (``NO_RETURN``) for an invalid return,
``MIXED`` (-2) for a mixed pixel (its point lies on no surface; kind -1).

Time: ``ScannerConfig.time_offset`` is the scanner clock's offset: the stamps it
writes are the true times plus ``time_offset`` (0 in the default rig).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numba
import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from common.config import StrictModel
from common.rig import ScannerConfig
from simulation.trajectory import Trajectory, _rodrigues

FloatArray = NDArray[np.float64]
NO_RETURN = -1
MIXED = -2


class ScannerNoiseConfig(StrictModel):
    """Measurement errors of the scanner; ``enabled: false`` gives exact ranges."""

    enabled: bool = True
    range_sigma: float | None = Field(default=None, ge=0, description="range noise std (m); None: the scanner model's (3 mm)")
    range_sigma_per_m: float = Field(default=0.0, ge=0, description="extra noise std per metre of range")
    incidence_sigma: float = Field(default=0.0, ge=0, description="noise growth with 1/cos(incidence) - 1")
    grazing_cos: float = Field(default=math.cos(math.radians(80.0)), ge=0, le=1, description="cos(incidence) below which returns start to drop out")
    dropout_rate: float = Field(default=0.0, ge=0, le=1, description="probability of a random dropout per beam")
    mixed_prob: float = Field(default=0.5, ge=0, le=1, description="probability of a mixed pixel at a depth jump")
    mixed_jump: float = Field(default=0.05, gt=0, description="depth difference of neighbours that makes a jump (m)")
    quantization: float = Field(default=0.001, ge=0, description="range resolution (m); 0: none")


class RayHits(Protocol):
    range: NDArray[Any]
    plane_id: NDArray[Any]
    kind: NDArray[Any]
    cos_incidence: NDArray[Any]


class Raycaster(Protocol):
    def cast(self, origins_world: FloatArray, directions_world: FloatArray) -> RayHits: ...


@dataclass(frozen=True, eq=False)
class ScanBlock:
    """Consecutive scans of one scanner: ``stamps`` (S,) true first-beam times (s),
    ``ranges`` (S, B) float32 as written to LaserScan, ``plane_id`` (S, B) int32 and
    ``kind`` (S, B) int8 per-beam ground truth."""

    stamps: FloatArray
    ranges: NDArray[np.float32]
    plane_id: NDArray[np.int32]
    kind: NDArray[np.int8]


def scanner_directions(scanner: ScannerConfig) -> FloatArray:
    """(B, 3) unit beam directions in the scanner frame."""
    a = scanner.scanner_model.beam_angles()
    return np.column_stack((np.cos(a), np.sin(a), np.zeros_like(a)))


@numba.njit(cache=True)
def _beam_rays(
    stamps: Any,
    time_increment: float,
    dirs_scanner: Any,
    R_bs: Any,
    t_bs: Any,
    t0: float,
    dt: float,
    rotations: Any,
    rotvecs: Any,
    positions: Any,
    origins: Any,
    directions: Any,
) -> None:
    n_scans = stamps.shape[0]
    n_beams = dirs_scanner.shape[0]
    n = positions.shape[0]
    # beam directions in the body frame
    d_body = np.empty((n_beams, 3))
    for b in range(n_beams):
        for i in range(3):
            d_body[b, i] = R_bs[i, 0] * dirs_scanner[b, 0] + R_bs[i, 1] * dirs_scanner[b, 1] + R_bs[i, 2] * dirs_scanner[b, 2]
    E = np.empty((3, 3))
    R = np.empty((3, 3))
    for s in range(n_scans):
        for b in range(n_beams):
            t = stamps[s] + b * time_increment
            u = (t - t0) / dt
            k = math.floor(u)
            k = min(max(k, 0), n - 2)
            f = u - k
            _rodrigues(f * rotvecs[k, 0], f * rotvecs[k, 1], f * rotvecs[k, 2], E)
            for i in range(3):
                for j in range(3):
                    R[i, j] = rotations[k, i, 0] * E[0, j] + rotations[k, i, 1] * E[1, j] + rotations[k, i, 2] * E[2, j]
            row = s * n_beams + b
            for i in range(3):
                p = (1.0 - f) * positions[k, i] + f * positions[k + 1, i]
                origins[row, i] = p + R[i, 0] * t_bs[0] + R[i, 1] * t_bs[1] + R[i, 2] * t_bs[2]
                directions[row, i] = R[i, 0] * d_body[b, 0] + R[i, 1] * d_body[b, 1] + R[i, 2] * d_body[b, 2]


def beam_rays(traj: Trajectory, scanner: ScannerConfig, stamps: FloatArray) -> tuple[FloatArray, FloatArray]:
    """World-frame ray origins and unit directions (S*B, 3) of scans with true first-beam
    times ``stamps`` (S,), each beam posed at its own time on ``traj``."""
    model = scanner.scanner_model
    st = np.ascontiguousarray(stamps, dtype=np.float64)
    if st.size:
        t_last = float(st.max()) + (model.n_beams - 1) * model.time_increment
        if st.min() < traj.times[0] - 1e-9 or t_last > traj.times[-1] + 1e-9:
            raise ValueError(
                f"scanner '{scanner.name}': beam times [{st.min():.4f}, {t_last:.4f}] s are outside the "
                f"trajectory [{traj.times[0]:.4f}, {traj.times[-1]:.4f}] s"
            )
    T = scanner.T_body_scanner.matrix()
    m = st.size * model.n_beams
    origins = np.empty((m, 3))
    directions = np.empty((m, 3))
    _beam_rays(
        st,
        float(model.time_increment),
        scanner_directions(scanner),
        np.ascontiguousarray(T[:3, :3]),
        np.ascontiguousarray(T[:3, 3]),
        *traj.kernel_args(),
        origins,
        directions,
    )
    return origins, directions


def apply_measurement(
    ranges: FloatArray,
    plane_id: NDArray[np.integer],
    kind: NDArray[np.integer],
    cos_incidence: FloatArray,
    scanner: ScannerConfig,
    noise: ScannerNoiseConfig,
    rng: np.random.Generator,
) -> tuple[NDArray[np.float32], NDArray[np.int32], NDArray[np.int8]]:
    """Turn true ranges (S, B) (inf on a miss) into measured LaserScan ranges and per-beam truth.

    Returns (ranges float32, plane_id int32, kind int8), all (S, B); see the module doc.
    """
    model = scanner.scanner_model
    r = np.array(ranges, dtype=np.float64)
    pid = np.array(plane_id, dtype=np.int32)
    knd = np.array(kind, dtype=np.int8)
    hit = np.isfinite(r)
    dropped = np.zeros(r.shape, dtype=bool)
    if noise.enabled:
        # 1. mixed pixels at depth jumps between neighbouring beams
        if noise.mixed_prob > 0 and r.shape[1] > 1:
            a, b = r[:, :-1], r[:, 1:]
            both = hit[:, :-1] & hit[:, 1:]
            with np.errstate(invalid="ignore"):
                jump = both & (np.abs(a - b) > noise.mixed_jump)
            js, jb = np.nonzero(jump & (rng.random(jump.shape) < noise.mixed_prob))
            if js.size:
                which = jb + (rng.random(js.size) < 0.5)
                lo = np.minimum(r[js, jb], r[js, jb + 1])
                hi = np.maximum(r[js, jb], r[js, jb + 1])
                r[js, which] = lo + rng.random(js.size) * (hi - lo)
                pid[js, which] = MIXED
                knd[js, which] = -1
        # 2. range noise
        sigma0 = model.range_sigma if noise.range_sigma is None else noise.range_sigma
        cos_i = np.clip(np.nan_to_num(np.asarray(cos_incidence, dtype=np.float64), nan=1.0), 1e-3, 1.0)
        sigma = (sigma0 + noise.range_sigma_per_m * np.where(hit, r, 0.0)) * (1.0 + noise.incidence_sigma * (1.0 / cos_i - 1.0))
        r = r + rng.standard_normal(r.shape) * sigma
        # 3. dropouts at grazing incidence and at random
        p_drop = np.clip(1.0 - cos_i / noise.grazing_cos, 0.0, 1.0) if noise.grazing_cos > 0 else np.zeros(r.shape)
        p_drop = 1.0 - (1.0 - p_drop) * (1.0 - noise.dropout_rate)
        dropped = hit & (rng.random(r.shape) < p_drop)
        # 4. quantisation
        if noise.quantization > 0:
            r = np.round(r / noise.quantization) * noise.quantization
    out = r.astype(np.float32)
    with np.errstate(invalid="ignore"):
        far = ~hit | (r > model.range_max)
        near = hit & (r < model.range_min)
    out[far] = np.inf
    out[near | (dropped & ~far)] = np.nan
    invalid = far | near | dropped
    pid[invalid] = NO_RETURN
    knd[invalid] = -1
    return out, pid, knd


def simulate_scans(
    raycaster: Raycaster,
    traj: Trajectory,
    scanners: list[ScannerConfig],
    stamps: list[FloatArray],
    noise: ScannerNoiseConfig,
    rng: np.random.Generator,
) -> list[ScanBlock]:
    """Scans of several scanners (true first-beam times ``stamps[i]`` for ``scanners[i]``),
    cast in one batch. Same rng state, same scans."""
    origins: list[FloatArray] = []
    dirs: list[FloatArray] = []
    for sc, st in zip(scanners, stamps, strict=True):
        o, d = beam_rays(traj, sc, st)
        origins.append(o)
        dirs.append(d)
    hits = raycaster.cast(np.concatenate(origins), np.concatenate(dirs))
    blocks = []
    start = 0
    for sc, st in zip(scanners, stamps, strict=True):
        nb = sc.scanner_model.n_beams
        shape = (st.size, nb)
        sl = slice(start, start + st.size * nb)
        start = sl.stop
        rg, pid, knd = apply_measurement(
            np.asarray(hits.range[sl]).reshape(shape),
            np.asarray(hits.plane_id[sl]).reshape(shape),
            np.asarray(hits.kind[sl]).reshape(shape),
            np.asarray(hits.cos_incidence[sl]).reshape(shape),
            sc,
            noise,
            rng,
        )
        blocks.append(ScanBlock(np.asarray(st, dtype=np.float64), rg, pid, knd))
    return blocks
