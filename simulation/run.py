"""One simulation run: world + rig + walking operator -> a ROS bag and its ground-truth folder.

``simulate`` streams the run in chunks of ``SimulationConfig.chunk`` seconds: for each
chunk it poses every beam on the true trajectory, casts the rays, applies the scanner's
measurement model, writes the messages to the bag and appends the per-beam ground truth
to disk, so memory does not grow with the duration.

Output, for ``out = run.bag``: the ROS1 bag file ``run.bag``, or the ROS2 bag directory
``run`` (a directory named ``*.bag`` would be read as ROS1 by rosbags), and

``run.gt/`` beside it:
  - ``trajectory.tum``: ``T_world_body`` (``t tx ty tz qx qy qz qw``, the bag's clock);
  - ``mesh.ply``, ``planes.json``: the world (``World.write_mesh`` / ``write_planes``);
  - ``beams.npz``: per scanner ``<name>_stamps`` (n_scans,) header stamps (s, as in the
    bag), ``<name>_plane_id`` (n_scans, n_beams) int32 and ``<name>_kind`` int8 (see
    ``simulation.scanner``: -1 invalid return, -2 mixed pixel);
  - ``imu.npz`` (with ``--imu``): the true biases;
  - ``people.npz`` when the scene has people (``simulation.people``): their tracks (P, T, 2)
    at ``times`` (absolute, as the bag), heights and radius; their beams have plane id -3;
  - ``rig.yaml`` (the true rig), ``meta.json`` (world, rig, seed, duration, config, counts).

Everything is written under temporary names and renamed when complete.
Clock: the simulation runs from 0 s; every stamp written is ``start_time`` + that.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
import uuid
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Literal

import numpy as np
import yaml
from numpy.typing import NDArray
from pydantic import Field
from tqdm import tqdm

from common.config import StrictModel, load
from common.rig import Rig, resolve_rig
from simulation.bag import BagWriter, seconds_to_ns
from simulation.imu import ImuConfig, simulate_imu
from simulation.people import PeopleConfig, make_people
from simulation.scanner import ScannerNoiseConfig, apply_measurement, beam_rays
from simulation.trajectory import GaitConfig, Trajectory, walk_trajectory

Format = Literal["ros1", "ros2"]
STAGES = ("trajectory", "ray casting", "noise", "serialisation", "writing")


class Silence(StrictModel):
    """A scanner that sends nothing for a while (a loose cable, a driver restart)."""

    scanner: str
    start: float = Field(ge=0, description="s after the start of the recording")
    duration: float = Field(gt=0, description="s")


class SimulationConfig(StrictModel):
    """Every knob of a run (YAML under ``configs/simulation/``); the seed drives every draw."""

    world: str = "demo"
    rig: str = "itc_backpack"
    duration: float = Field(default=60.0, gt=0, description="s")
    seed: int = 0
    format: Format = "ros1"
    imu: bool = False
    start_time: float = Field(default=1_700_000_000.0, ge=0, description="absolute time of simulation t = 0 (s)")
    chunk: float = Field(default=2.0, gt=0, le=60, description="seconds simulated per chunk")
    scanner_phase: list[float] | None = Field(
        default=None, description="first-scan time per scanner (s, in [0, scan period)); None: drawn from the seed"
    )
    gait: GaitConfig = Field(default_factory=GaitConfig)
    noise: ScannerNoiseConfig = Field(default_factory=ScannerNoiseConfig)
    imu_noise: ImuConfig = Field(default_factory=ImuConfig)
    people: PeopleConfig = Field(default_factory=PeopleConfig)
    silences: list[Silence] = Field(default_factory=list)


def load_simulation_config(path: str | Path) -> SimulationConfig:
    """A SimulationConfig from YAML (errors name the file and the key)."""
    return load(SimulationConfig, path)


def bag_path_for(out: str | Path, fmt: Format) -> Path:
    """Where the bag goes: ``out`` itself, except that a ROS2 bag (a directory) must not end in
    ``.bag`` (rosbags' AnyReader would take it for a ROS1 file): ``run.bag`` -> ``run``."""
    p = Path(out)
    return p.with_suffix("") if fmt == "ros2" and p.suffix == ".bag" else p


def gt_dir_for(out: str | Path) -> Path:
    """``run.bag`` -> ``run.gt`` (beside the bag)."""
    p = Path(out)
    return p.with_name((p.stem if p.suffix else p.name) + ".gt")


@dataclass
class SimulationResult:
    bag: Path
    gt: Path
    counts: dict[str, int]
    seconds: dict[str, float]
    wall_time: float
    n_rays: int
    meta: dict[str, Any] = field(default_factory=dict)


class _NpyStream:
    """An .npy file written row block by row block (final shape known up front)."""

    def __init__(self, path: Path, shape: tuple[int, ...], dtype: Any) -> None:
        self.path = path
        self.dtype = np.dtype(dtype)
        self.shape = shape
        self.f: BinaryIO = open(path, "wb")
        np.lib.format.write_array_header_1_0(
            self.f, {"descr": np.lib.format.dtype_to_descr(self.dtype), "fortran_order": False, "shape": shape}
        )
        self.rows = 0

    def append(self, block: NDArray[Any]) -> None:
        b = np.ascontiguousarray(block, dtype=self.dtype)
        self.f.write(b.tobytes())
        self.rows += b.shape[0]

    def close(self) -> None:
        self.f.close()
        if self.rows != self.shape[0]:
            raise RuntimeError(f"{self.path.name}: wrote {self.rows} rows, expected {self.shape[0]}")


def scan_stamps(rig: Rig, duration: float, phases: list[float]) -> list[NDArray[np.float64]]:
    """True first-beam times (simulation clock) of every scan that starts before ``duration``."""
    out = []
    for sc, ph in zip(rig.scanners, phases, strict=True):
        period = sc.scanner_model.scan_period
        n = max(0, math.ceil((duration - ph) / period))
        out.append(ph + period * np.arange(n, dtype=np.float64))
    return out


def simulate(
    world: Any,
    rig: Rig | str | Path,
    duration: float | None = None,
    seed: int | None = None,
    out: str | Path = "run.bag",
    fmt: Format | None = None,
    imu: bool | None = None,
    noise: ScannerNoiseConfig | None = None,
    config: SimulationConfig | None = None,
    progress: bool = True,
    raycaster: Any = None,
) -> SimulationResult:
    """Simulate a walk through ``world`` (a World or a name/path) with ``rig`` and write
    the bag ``out`` and its ground truth ``<out>.gt/``. Explicit arguments override ``config``."""
    t_start = time.perf_counter()
    cfg = config or SimulationConfig()
    upd: dict[str, Any] = {}
    for key, val in (("duration", duration), ("seed", seed), ("format", fmt), ("imu", imu), ("noise", noise)):
        if val is not None:
            upd[key] = val
    cfg = SimulationConfig.model_validate({**cfg.model_dump(), **{k: v.model_dump() if hasattr(v, "model_dump") else v for k, v in upd.items()}})
    if isinstance(world, str | Path):
        from simulation.world import load_world

        world = load_world(world)
    rig_obj = rig if isinstance(rig, Rig) else resolve_rig(rig)
    if raycaster is None:
        from simulation.raycast import Raycaster

        raycaster = Raycaster(world)
    out_path = bag_path_for(out, cfg.format)
    gt_path = gt_dir_for(out_path)
    if not out_path.parent.is_dir():
        raise ValueError(f"{out_path}: the folder {out_path.parent} does not exist")
    if out_path.resolve() == gt_path.resolve():
        raise ValueError(f"{out_path}: the output name must not end in .gt")
    seconds = dict.fromkeys(STAGES, 0.0)

    # trajectory, IMU, scan stamps
    t0 = time.perf_counter()
    max_period = max(s.scanner_model.scan_period for s in rig_obj.scanners)
    full = walk_trajectory(world.walk, cfg.duration + max_period + 0.05, cfg.seed, cfg.gait, floor_z=float(world.floor_z))
    keep = full.times <= cfg.duration + max_period + 1e-9
    traj = Trajectory(full.times[keep], full.positions[keep], full.quaternions[keep])
    imu_data = simulate_imu(traj, seed=cfg.seed + 7919, cfg=cfg.imu_noise) if cfg.imu else None
    if cfg.scanner_phase is not None:
        if len(cfg.scanner_phase) != len(rig_obj.scanners):
            raise ValueError(f"scanner_phase has {len(cfg.scanner_phase)} values for {len(rig_obj.scanners)} scanners")
        phases = list(cfg.scanner_phase)
    else:
        prng = np.random.default_rng([cfg.seed, 2])
        phases = [float(prng.uniform(0, s.scanner_model.scan_period)) for s in rig_obj.scanners]
    stamps = scan_stamps(rig_obj, cfg.duration, phases)
    names = [sc.name for sc in rig_obj.scanners]
    for quiet in cfg.silences:
        if quiet.scanner not in names:
            raise ValueError(f"silences: rig '{rig_obj.name}' has no scanner '{quiet.scanner}' (scanners: {', '.join(names)})")
        i = names.index(quiet.scanner)
        stamps[i] = stamps[i][(stamps[i] < quiet.start) | (stamps[i] >= quiet.start + quiet.duration)]
    people = make_people(cfg.people, world.walk, cfg.duration + max_period + 0.05, float(world.floor_z), cfg.seed)
    seconds["trajectory"] += time.perf_counter() - t0

    base = cfg.start_time
    base_ns = round(base * 1e9)
    tag = uuid.uuid4().hex[:8]
    gt_tmp = gt_path.parent / f".{gt_path.name}.{tag}.tmp"
    gt_tmp.mkdir()
    writer = BagWriter(out_path, cfg.format, rig_obj, imu=cfg.imu, imu_noise=(cfg.imu_noise.gyro_noise * math.sqrt(1 / traj.dt), cfg.imu_noise.accel_noise * math.sqrt(1 / traj.dt)))
    streams: dict[str, _NpyStream] = {}
    n_rays = 0
    try:
        writer.open()
        for sc, st in zip(rig_obj.scanners, stamps, strict=True):
            nb = sc.scanner_model.n_beams
            streams[f"{sc.name}_stamps"] = _NpyStream(gt_tmp / f"{sc.name}_stamps.npy", (st.size,), np.float64)
            streams[f"{sc.name}_plane_id"] = _NpyStream(gt_tmp / f"{sc.name}_plane_id.npy", (st.size, nb), np.int32)
            streams[f"{sc.name}_kind"] = _NpyStream(gt_tmp / f"{sc.name}_kind.npy", (st.size, nb), np.int8)
        t0 = time.perf_counter()
        writer.tf_static(base_ns)
        seconds["serialisation"] += time.perf_counter() - t0

        n_chunks = max(1, math.ceil(cfg.duration / cfg.chunk))
        bar = tqdm(total=round(cfg.duration, 3), unit="s", desc=f"simulate {world.name}", disable=not progress, leave=False)
        t_pose = seconds_to_ns(traj.times, base_ns)
        for c in range(n_chunks):
            lo, hi = c * cfg.chunk, (c + 1) * cfg.chunk if c < n_chunks - 1 else math.inf
            rng = np.random.default_rng([cfg.seed, 1, c])
            # rays of every scanner in the chunk, cast in one batch
            t0 = time.perf_counter()
            sel = [st[(st >= lo) & (st < hi)] for st in stamps]
            rays = [beam_rays(traj, sc, s) for sc, s in zip(rig_obj.scanners, sel, strict=True)]
            origins = np.concatenate([r[0] for r in rays])
            dirs = np.concatenate([r[1] for r in rays])
            del rays
            hits = raycaster.cast(origins, dirs)
            if people.count:
                beam_times = np.concatenate([(st_[:, None] + sc.scanner_model.beam_offsets()[None, :]).ravel()
                                             for sc, st_ in zip(rig_obj.scanners, sel, strict=True)])
                people.occlude(origins, dirs, beam_times, hits.range, hits.plane_id, hits.kind, hits.cos_incidence)
            n_rays += len(origins)
            del origins, dirs
            seconds["ray casting"] += time.perf_counter() - t0
            start = 0
            for sc, s in zip(rig_obj.scanners, sel, strict=True):
                t0 = time.perf_counter()
                nb = sc.scanner_model.n_beams
                shape = (s.size, nb)
                sl = slice(start, start + s.size * nb)
                start = sl.stop
                ranges, pid, kind = apply_measurement(
                    hits.range[sl].reshape(shape),
                    hits.plane_id[sl].reshape(shape),
                    hits.kind[sl].reshape(shape),
                    hits.cos_incidence[sl].reshape(shape),
                    sc,
                    cfg.noise,
                    rng,
                )
                seconds["noise"] += time.perf_counter() - t0
                t0 = time.perf_counter()
                header_ns = seconds_to_ns(s + sc.time_offset, base_ns)
                writer.scans(sc, header_ns, ranges)
                seconds["serialisation"] += time.perf_counter() - t0
                t0 = time.perf_counter()
                streams[f"{sc.name}_stamps"].append(header_ns * 1e-9)
                streams[f"{sc.name}_plane_id"].append(pid)
                streams[f"{sc.name}_kind"].append(kind)
                seconds["writing"] += time.perf_counter() - t0
            del hits
            t0 = time.perf_counter()
            in_chunk = (traj.times >= lo) & (traj.times < hi)
            writer.poses(t_pose[in_chunk], traj.positions[in_chunk], traj.quaternions[in_chunk])
            if imu_data is not None:
                writer.imu(t_pose[in_chunk], imu_data.gyro[in_chunk], imu_data.accel[in_chunk])
            seconds["serialisation"] += time.perf_counter() - t0
            w0 = writer.seconds["writing"]
            writer.flush()
            seconds["writing"] += writer.seconds["writing"] - w0
            bar.update(round(min(hi, cfg.duration) - lo, 3))
        bar.close()

        t0 = time.perf_counter()
        for stream in streams.values():
            stream.close()
        _zip_npy(gt_tmp / "beams.npz", [stream.path for stream in streams.values()])
        traj.write_tum(gt_tmp / "trajectory.tum", time_offset=base)
        world.write_mesh(gt_tmp / "mesh.ply")
        world.write_planes(gt_tmp / "planes.json")
        if imu_data is not None:
            np.savez(gt_tmp / "imu.npz", times=base + imu_data.times, gyro_bias=imu_data.gyro_bias, accel_bias=imu_data.accel_bias)
        if people.count:
            np.savez(gt_tmp / "people.npz", times=base + np.arange(people.tracks_xy.shape[1]) / people.rate,
                     tracks_xy=people.tracks_xy, heights=people.heights, radius=people.radius)
        (gt_tmp / "rig.yaml").write_text(yaml.safe_dump(rig_obj.model_dump(mode="json"), sort_keys=False))
        counts = dict(writer.counts)
        meta = {
            "world": world.name,
            "rig": rig_obj.name,
            "seed": cfg.seed,
            "duration": cfg.duration,
            "format": cfg.format,
            "bag": out_path.name,
            "start_time": base,
            "scanner_phase": dict(zip([s.name for s in rig_obj.scanners], phases, strict=True)),
            "counts": {"messages": counts, "scans": {s.name: int(st.size) for s, st in zip(rig_obj.scanners, stamps, strict=True)}, "rays": n_rays, "poses": len(traj.times)},
            # the config as run: the world and rig actually used, not the config's defaults
            "config": {**cfg.model_dump(mode="json"), "world": world.name, "rig": rig_obj.name},
            "conventions": {
                "ranges": "inf: no return (nothing hit or beyond range_max); NaN: dropout or closer than range_min",
                "plane_id": "-1: invalid return; -2: mixed pixel",
                "stamps": "header stamp = time of the first beam; beam i at stamp + i * time_increment",
            },
        }
        (gt_tmp / "meta.json").write_text(json.dumps(meta, indent=2))
        writer.close()
        if gt_path.exists():
            shutil.rmtree(gt_path)
        os.replace(gt_tmp, gt_path)
        seconds["writing"] += time.perf_counter() - t0
    except BaseException:
        writer.abort()
        for stream in streams.values():
            if not stream.f.closed:
                stream.f.close()
        shutil.rmtree(gt_tmp, ignore_errors=True)
        raise
    return SimulationResult(out_path, gt_path, counts, seconds, time.perf_counter() - t_start, n_rays, meta)


def _zip_npy(path: Path, files: list[Path], remove: Callable[[Path], None] = Path.unlink) -> None:
    """An uncompressed .npz from .npy files (streamed from disk), removing them."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as z:
        for f in files:
            z.write(f, arcname=f.name)
            remove(f)
