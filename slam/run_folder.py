"""What a run writes into its folder from its result (``slam.export`` holds the formats):
trajectory.tum and segments.npz (:func:`write_tables`), cloud.ply and the cloud shown in map.rrd
(:func:`write_cloud_outputs`), planes.json with the outlines from the final map where that pass
placed the segments (:func:`write_planes`), and summary.json's record (:class:`RunSummary`,
with the run's counts as one :class:`RunCounts`).
"""

from __future__ import annotations

import shutil
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from common.atomic import OutputFileError
from common.rig import Rig
from slam.cloud_pass import write_cloud
from slam.config import SlamConfig
from slam.export import (
    PlaneRecord,
    cloud_row_bytes,
    make_segment_table,
    read_cloud_ply,
    write_cloud_ply,
    write_planes_json,
    write_segments_npz,
    write_trajectory_tum,
)
from slam.frontend.planemap import KIND_NAMES
from slam.health import Health
from slam.io.source import BagSource, StreamIndex
from slam.pipeline import SlamResult
from slam.plane_extents import ExtentRule, Outline, final_extents
from slam.rerun_map import CloudView, MapOptions, SegmentLines

FloatArray = NDArray[np.float64]

MEMORY_DEFINITION = ("peak resident memory (ru_maxrss, GB) of the process so far, after the estimation "
                     "(runner.result) and after the export; it never decreases, so the stage whose "
                     "figure rises is the one that sets the peak")

PACE_DEFINITION = ("rows [data s since the log's start, wall s, CPU s] every 10 s of data while the scans are "
                   "estimated (the final batch and the export not included): wall and CPU (user + system, of "
                   "the estimator and its live reader and back-end processes) since the first scan")

TIMINGS_DEFINITION = ("seconds per stage; 'segmentation' and 'frontend' (lifting into the body frame, deskew, the "
                      "scan-only edge tests) are spent in the reader process when parallel.reader is on, overlapped "
                      "with the estimator's stages; 'export' is elapsed time (its cloud pass split across "
                      "parallel.export_processes); 'wall' is the whole run's elapsed time")


def plane_records(res: SlamResult, covariances: dict[int, FloatArray],
                  outlines: Mapping[int, Outline] | None = None) -> list[PlaneRecord]:
    """The estimated planes (world frame) with their kinds, ``covariances`` and outlines: from
    ``outlines`` (the final map's, :func:`final_outlines`) where given, else the front end's."""
    recs = []
    for pid, n, d in zip(res.plane_ids, res.plane_normals, res.plane_offsets, strict=True):
        p = res.plane_map.planes[int(pid)]
        final = None if outlines is None else outlines.get(int(pid))
        recs.append(
            PlaneRecord(
                id=int(pid),
                normal=np.asarray(n),
                d=float(d),
                polygon=final.polygon if final is not None else res.plane_map.polygon(int(pid)),
                kind=KIND_NAMES[p.kind],
                n_segments=int(p.n_segments),
                covariance=covariances.get(int(pid)),
                outline="final_map" if final is not None else "front_end",
                regions=() if final is None else final.regions,
            )
        )
    return recs


def final_outlines(res: SlamResult, cfg: SlamConfig, segments: SegmentLines) -> dict[int, Outline]:
    """The planes' outlines from the final map (:func:`slam.plane_extents.final_extents`) given
    the associated segments' end points the cloud pass placed (world frame)."""
    o = cfg.output
    planes = [(int(pid), np.asarray(n), float(d))
              for pid, n, d in zip(res.plane_ids, res.plane_normals, res.plane_offsets, strict=True)]
    return final_extents(segments.endpoints_world, segments.plane_id, planes,
                         ExtentRule(o.extent_cell, o.extent_min_segments, o.extent_gate, o.extent_rms, o.extent_gap),
                         segments.rms)


def write_tables(out: Path, res: SlamResult) -> None:
    """trajectory.tum and segments.npz into ``out`` (and trajectory_online.tum, the window's
    estimate before the final batch, when there was one)."""
    write_trajectory_tum(out / "trajectory.tum", res.knot_times, res.T_world_body)
    if res.T_world_body_online is not None:
        write_trajectory_tum(out / "trajectory_online.tum", res.knot_times, res.T_world_body_online)
    rows = res.segment_rows
    table = make_segment_table(res.scanner_names, rows["scanner"], rows["scan_index"], rows["stamp"],
                               rows["first_beam"], rows["last_beam"], rows["plane_id"])
    write_segments_npz(out / "segments.npz", table)


def write_planes(out: Path, res: SlamResult, cfg: SlamConfig, segments: SegmentLines | None) -> list[PlaneRecord]:
    """planes.json into ``out``, the outlines from the final map when the cloud pass placed the
    ``segments`` (else the front end's); returns the planes written."""
    outlines = None if segments is None else final_outlines(res, cfg, segments)
    planes = plane_records(res, res.plane_covariances, outlines)
    write_planes_json(out / "planes.json", planes)
    return planes


@dataclass(frozen=True)
class CloudOutputs:
    """What the cloud pass left for the rest of the run: cloud.ply's number of points (0 when it
    is not written), and for map.rrd the cloud's view and the associated segments (world frame)."""

    points: int = 0
    view: CloudView | None = None
    segments: SegmentLines | None = None


def write_cloud_outputs(out: Path, source: BagSource, rig: Rig, cfg: SlamConfig, res: SlamResult,
                        index: StreamIndex | None, progress: bool, voxel: float | None) -> CloudOutputs:
    """cloud.ply into ``out`` (``output.cloud``; thinned to one point per ``voxel`` m, else
    ``output.voxel``, when given) and the view of every point for map.rrd (``output.rerun``), from
    one pass over ``source``'s scans (their stream's ``index``, see ``slam.cloud_pass``)."""
    if not (cfg.output.cloud or cfg.output.rerun):
        return CloudOutputs()
    v = voxel if voxel is not None else (cfg.output.voxel or None)
    # without cloud.ply the pass keeps no point (the recording's view is picked on the way, which
    # needs the stream's index; without it the view is read back from a file of every point)
    keep = cfg.output.cloud or index is None
    if index is not None and keep:
        check_cloud_space(out, index.points, index.intensities, cfg.parallel.export_processes, v is not None)
    # every point goes to a file as it is placed (the recording's view picked on the way); the
    # voxel thinning reads it back
    every = out / ("cloud.ply" if cfg.output.cloud and v is None else ".cloud_every_point.ply")
    n_every, lines, view = write_cloud(source, rig, res, every, index, progress, cfg.parallel.export_processes,
                                       echo=cfg.input.echo, view=MapOptions() if cfg.output.rerun else None,
                                       keep_points=keep)
    n_cloud = 0
    if cfg.output.cloud:
        n_cloud = n_every
        if v is not None:
            c = read_cloud_ply(every)
            n_cloud = write_cloud_ply(out / "cloud.ply", c.points_world, c.scanner, c.time, c.plane_id, voxel=v,
                                      intensity=c.intensity)
    if every.name != "cloud.ply":
        every.unlink(missing_ok=not keep)
    return CloudOutputs(n_cloud, view, lines)


def cloud_bytes_needed(points: int, intensity: bool, processes: int, thinned: bool) -> int:
    """Disk bytes the cloud pass needs at its peak for ``points`` points: the cloud.ply, beside it
    the rows the other ``processes - 1`` parts wrote until they are joined, and with ``thinned``
    (a voxel size) the thinned cloud beside the every-point file; 5 % and 64 MB of margin."""
    rows = points * cloud_row_bytes(intensity)
    peak = rows * (2.0 - 1.0 / max(1, processes)) + (rows if thinned else 0)
    return int(1.05 * peak) + (64 << 20)


def check_cloud_space(out: Path, points: int, intensity: bool, processes: int, thinned: bool) -> None:
    """An ``OutputFileError`` naming ``out`` when its file system has less free space than the
    cloud pass needs (:func:`cloud_bytes_needed`): at the start of the pass, not minutes into
    writing it (the run's folder is then not made at all)."""
    need = cloud_bytes_needed(points, intensity, processes, thinned)
    free = shutil.disk_usage(out).free
    if free < need:
        raise OutputFileError(
            f"{out}: not enough free disk space for the cloud: about {need / 1e9:.1f} GB needed ({points:,} points, "
            f"cloud.ply and its parts' rows until they are joined), {free / 1e9:.1f} GB free; free space, write "
            "elsewhere, or set output.cloud: false (or output.voxel)")


@dataclass(frozen=True)
class RunCounts:
    """What a run counted (summary.json's ``counts``). Fields named as the runner's statistics
    are taken from them by name; ``isam2_updates`` (the runner's ``updates``: back-end updates)
    only under the iSAM2 solver (None, and left out of the summary, under the window solver)."""

    scans: int
    knots: int
    segments: int
    segments_associated: int
    planes: int
    planes_created: int
    planes_merged: int
    wall_layers_merged: int
    planes_transient: int
    planes_rejected: int
    planes_rejected_oblique: int
    observation_blocks: int
    wall_faces: int
    edges: int
    edges_created: int
    edges_merged: int
    edge_observations: int
    trimmed_points: int
    trimmed_blocks: int
    isam2_updates: int | None
    isam2_rebuilds: int
    isam2_fallbacks: int
    imu_used: int
    zero_velocity_updates: int
    rest_idle_scans: int
    cloud_points: int

    @classmethod
    def of(cls, res: SlamResult, solver: str, cloud_points: int) -> RunCounts:
        """The counts of a run's result (its statistics and segment rows) and its cloud."""
        derived: dict[str, Any] = {
            "segments_associated": int((res.segment_rows["plane_id"] >= 0).sum()),
            "isam2_updates": res.stats["updates"] if solver == "isam2" else None,
            "cloud_points": cloud_points,
        }
        return cls(**{f.name: derived[f.name] if f.name in derived else res.stats[f.name] for f in fields(cls)})

    def to_dict(self) -> dict[str, int]:
        return {f.name: v for f in fields(self) if (v := getattr(self, f.name)) is not None}


@dataclass(frozen=True)
class RunSummary:
    """summary.json: the run's inputs, counts, solver diagnostics, memory and timings (s), its health, the rig
    checks' notes, how the walk started (``start``: ``slam.frontend.initial_motion``) and each scanner's range
    noise (``noise``: ``slam.run.estimate_noise``)."""

    bag: str
    rig: str
    config: dict[str, Any]
    counts: RunCounts
    batch: dict[str, Any] | None
    singular_systems: dict[str, Any]
    residuals: dict[str, float] | None
    memory: dict[str, Any]
    timings: dict[str, float]
    timings_definition: str
    data_duration: float
    realtime_factor: float
    health: dict[str, Any]
    rig_checks: list[str]
    start: dict[str, Any]
    noise: dict[str, Any]
    pace: list[list[float]]
    pace_definition: str

    @classmethod
    def of(cls, bag: str | Path, rig: Rig, cfg: SlamConfig, res: SlamResult, cloud_points: int,
           memory: dict[str, float], wall: float, time_range: tuple[float, float], health: Health,
           rig_checks: list[str], noise: dict[str, Any] | None = None,
           pace: list[list[float]] | None = None) -> RunSummary:
        """The summary of a run on ``bag`` (log ``time_range``, s) that took ``wall`` s."""
        st = res.stats
        timings = {k: round(v, 3) for k, v in res.timings.items()} | {"wall": round(wall, 3)}
        duration = time_range[1] - time_range[0]
        return cls(
            bag=str(bag),
            rig=rig.name,
            config=cfg.model_dump(),
            counts=RunCounts.of(res, cfg.backend.solver, cloud_points),
            batch=st.get("batch"),
            singular_systems={"count": len(st["singular_systems"]), "first": st["singular_systems"][:5]},
            residuals=st.get("residuals"),
            memory={k: round(v, 3) for k, v in memory.items()} | {"definition": MEMORY_DEFINITION},
            timings=timings,
            timings_definition=TIMINGS_DEFINITION,
            data_duration=duration,
            realtime_factor=duration / max(timings["wall"], 1e-9),
            health=health.to_dict(),
            rig_checks=list(rig_checks),
            start=dict(st["initial_motion"]),
            noise=dict(noise or {}),
            pace=[list(r) for r in pace or []],
            pace_definition=PACE_DEFINITION,
        )

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)} | {"counts": self.counts.to_dict()}
