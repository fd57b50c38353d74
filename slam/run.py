"""``run_slam``: a bag in, the run folder out (the I/O edge around ``slam.pipeline``).

Outputs in ``out_dir`` (written into a temporary sibling folder that replaces
``out_dir`` only when complete, so an interrupted run leaves no half-written
output):

- ``trajectory.tum``: ``T_world_body`` at every knot (evo-compatible TUM);
- ``planes.json``: id, normal, d (``n . x + d = 0``), extent polygon, number
  of segments, 3x3 covariance (normal tangent, d), kind;
- ``segments.npz``: one row per segment with its plane (-1 = unassociated);
- ``cloud.ply``: every valid point placed by the final trajectory and the
  rig's extrinsics (world frame), with scanner index, time and plane id;
- ``map.rrd``: the rerun recording; ``summary.json``: config, counts,
  timings, residual statistics, peak memory after the estimation and after the export.

The cloud is written as it is placed, never held: the export's memory does not grow with the
walk's length (beyond the segments' end points and the recording's capped subsets).
"""

from __future__ import annotations

import multiprocessing as mp
import resource
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from common.atomic import atomic_dir
from common.rig import Rig
from slam.config import SlamConfig
from slam.export import (
    CloudPlyWriter,
    PlaneRecord,
    cloud_ply_writer,
    make_segment_table,
    read_cloud_ply,
    write_cloud_ply,
    write_planes_json,
    write_segments_npz,
    write_summary_json,
    write_trajectory_tum,
)
from slam.imu_feed import ImuSamples
from slam.io.bag import read_imu, read_scans, topics
from slam.io.errors import input_error
from slam.pipeline import SlamResult, SlamRunner
from slam.prefetch import can_fork_reader, get_from_children, prepared_scans
from slam.rerun_map import MapOptions, SegmentLines, view_of_cloud_ply, write_map_rrd
from slam.trajectory.placement import place_points

FloatArray = NDArray[np.float64]


def bag_time_range(path: str | Path) -> tuple[float, float]:
    """(start, end) log time of a bag in seconds."""
    from rosbags.highlevel import AnyReader

    from slam.io.bag import _bag_path

    with AnyReader([_bag_path(path)]) as r:
        return r.start_time * 1e-9, r.end_time * 1e-9


IMU_FRAMES = ("", "body", "base_link", "imu")  # frame ids taken as the rig's body frame
_PLACE_CHUNK = 4096  # cloud points per place_points call: its (m, 3, 3) temporaries stay in cache (~2x faster)
_EXPORT_BATCH = 1 << 18  # cloud points placed and written at a time (~10 MB of body points)


def load_imu(bag: str | Path, cfg: SlamConfig, t_start: float, t_end: float) -> ImuSamples | None:
    """The bag's IMU samples for the run (``cfg.imu.use``: auto = when the bag has the topic and it
    covers the scans); None when the run goes without. Errors name the bag and the topic."""
    ic = cfg.imu
    if ic.use == "off":
        return None
    if ic.topic not in topics(bag):
        if ic.use == "on":
            raise input_error(bag, "has no IMU messages (imu.use is 'on')", ic.topic)
        return None
    series = read_imu(bag, ic.topic)
    if series.frame_id not in IMU_FRAMES:
        raise input_error(bag, f"IMU frame '{series.frame_id}' is not the body frame ({', '.join(IMU_FRAMES[1:])})",
                          ic.topic)
    try:
        samples = ImuSamples(series.times, series.linear_acceleration, series.angular_velocity,
                             instantaneous=ic.samples == "instantaneous")
    except ValueError as e:
        raise input_error(bag, str(e), ic.topic) from None
    if not samples.covers(t_start, t_end - 0.05):
        if ic.use == "on":
            raise input_error(bag, f"IMU samples do not cover the scans ({t_start:.2f}-{t_end:.2f} s) without gaps",
                              ic.topic)
        return None
    return samples


MEMORY_DEFINITION = ("peak resident memory (ru_maxrss, GB) of the process so far, after the estimation "
                     "(runner.result) and after the export; it never decreases, so the stage whose "
                     "figure rises is the one that sets the peak")


TIMINGS_DEFINITION = ("seconds per stage; 'segmentation' and 'frontend' (lifting into the body frame, deskew, the "
                      "scan-only edge tests) are spent in the reader process when parallel.reader is on, overlapped "
                      "with the estimator's stages; 'export' is elapsed time (its cloud pass split across "
                      "parallel.export_processes); 'wall' is the whole run's elapsed time")


def peak_rss_gb() -> float:
    """The peak resident memory of this process so far (GB): ``ru_maxrss``, KiB on Linux and
    bytes on macOS."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak * (1 if sys.platform == "darwin" else 1024) / 1e9


def run_slam(
    bag: str | Path,
    rig: Rig,
    cfg: SlamConfig,
    out_dir: str | Path,
    progress: bool = True,
    voxel: float | None = None,
) -> dict[str, Any]:
    """Run SLAM on ``bag`` with ``rig`` and ``cfg``; write the run folder; return the summary."""
    t_wall = time.perf_counter()
    out = Path(out_dir)
    read_scans(bag, rig=rig).close()  # checks the bag and its topics before anything is written
    t_start, t_end = bag_time_range(bag)
    imu = load_imu(bag, cfg, t_start, t_end)
    runner = SlamRunner(rig, cfg, imu)
    scans = prepared_scans(bag, rig, cfg, imu, process=cfg.parallel.reader)
    bar = tqdm(
        total=round(t_end - t_start, 2),
        desc="slam",
        disable=not progress,
        leave=False,
        bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s of data [{elapsed}<{remaining}]",
    )
    last = t_start
    for scan in scans:
        runner.add_prepared(scan)
        if scan.stamp - last >= 0.5:
            bar.update(round(scan.stamp - last, 2))
            last = scan.stamp
    bar.close()
    runner.finish()
    res = runner.result(batch=cfg.backend.final_batch)
    memory = {"peak_rss_gb_after_estimation": peak_rss_gb()}

    with atomic_dir(out) as tmp:
        t0 = time.perf_counter()
        summary = _write_outputs(tmp, bag, rig, cfg, res, runner, progress, voxel)
        res.timings["export"] = time.perf_counter() - t0
        memory["peak_rss_gb_after_export"] = peak_rss_gb()
        summary["memory"] = {k: round(v, 3) for k, v in memory.items()} | {"definition": MEMORY_DEFINITION}
        summary["timings"] = {k: round(v, 3) for k, v in res.timings.items()}
        summary["timings"]["wall"] = round(time.perf_counter() - t_wall, 3)
        summary["timings_definition"] = TIMINGS_DEFINITION
        summary["data_duration"] = t_end - t_start
        summary["realtime_factor"] = (t_end - t_start) / max(summary["timings"]["wall"], 1e-9)
        write_summary_json(tmp / "summary.json", summary)
    return summary


def _plane_records(res: SlamResult, runner: SlamRunner, with_cov: bool) -> list[PlaneRecord]:
    recs = []
    for pid, n, d in zip(res.plane_ids, res.plane_normals, res.plane_offsets, strict=True):
        p = res.plane_map.planes[int(pid)]
        cov = None
        if with_cov:
            try:
                cov = runner.backend.plane_covariance(int(pid))
            except (ValueError, RuntimeError):
                cov = None
        recs.append(
            PlaneRecord(
                id=int(pid),
                normal=np.asarray(n),
                d=float(d),
                polygon=res.plane_map.polygon(int(pid)),
                kind=runner.kind_name(int(pid)),
                n_segments=int(p.n_segments),
                covariance=cov,
            )
        )
    return recs


class _CloudBatch:
    """Scans' points (body frame) gathered until there are enough to place together; then placed
    in the world with the final trajectory, in chunks of ``_PLACE_CHUNK``, and written."""

    def __init__(self, res: SlamResult, writer: CloudPlyWriter) -> None:
        self._kt, self._T = res.knot_times, res.T_world_body
        self._writer = writer
        self._cols: list[tuple[FloatArray, NDArray[np.uint8], FloatArray, NDArray[np.int32]]] = []
        self._ends: list[int] = []  # the batch's segments' first and last point indices
        self.n = 0  # points in the batch
        self.endpoints_world: list[FloatArray] = []  # (m, 3) per flushed batch

    def add(self, points_body: FloatArray, scanner: int, times: FloatArray, plane_id: NDArray[np.int32],
            ends: list[int]) -> None:
        """A scan's points (body frame) with their times (s) and plane ids; ``ends`` indexes
        its segments' first and last points in the scan."""
        self._cols.append((points_body, np.full(times.shape[0], scanner, dtype=np.uint8), times, plane_id))
        self._ends.extend(self.n + e for e in ends)
        self.n += times.shape[0]
        if self.n >= _EXPORT_BATCH:
            self.flush()

    def flush(self) -> None:
        if not self._cols:
            return
        pb, sc, tm, pid = (np.concatenate(c) for c in zip(*self._cols, strict=True))
        pw = np.empty_like(pb)
        for a in range(0, self.n, _PLACE_CHUNK):
            b = min(a + _PLACE_CHUNK, self.n)
            pw[a:b] = place_points(self._kt, self._T, tm[a:b], pb[a:b])
        self._writer.write(pw, sc, tm, pid)
        self.endpoints_world.append(pw[np.asarray(self._ends, dtype=np.int64)])
        self._cols, self._ends, self.n = [], [], 0


@dataclass
class _CloudPart:
    """What one part of the cloud pass found: its points' count and its associated segments
    (scan stamps, plane ids, end points in the world frame, (m, 3), two rows per segment)."""

    count: int
    seg_stamp: list[float]
    seg_pid: list[int]
    endpoints_world: FloatArray


def _cloud_part(bag: str | Path, rig: Rig, res: SlamResult, writer: CloudPlyWriter, lo: int, hi: int,
                bar: Any = None) -> _CloudPart:
    """Scans ``lo:hi`` of the bag's scan stream (the rig's topics, stamp order) placed in the
    world with the final trajectory and written with ``writer`` as they come.

    Points are placed a batch of scans at a time, in chunks of ``_PLACE_CHUNK`` (``place_points``
    gives every point the same numbers however the points are batched), so the parts of a split
    pass, concatenated, are the whole pass's cloud byte for byte."""
    names = res.scanner_names
    index = {n: i for i, n in enumerate(names)}
    T_bs = [s.T_body_scanner.matrix() for s in rig.scanners]
    rows = res.segment_rows
    # plane id per (scanner, scan index): beam ranges of its segments
    key = rows["scanner"].astype(np.int64) * (1 << 40) + rows["scan_index"].astype(np.int64)
    order = np.argsort(key, kind="stable")
    key_sorted = key[order]
    kt = res.knot_times
    seg_stamp: list[float] = []
    seg_pid: list[int] = []
    counters = [0] * len(names)
    batch = _CloudBatch(res, writer)
    for ordinal, line in enumerate(read_scans(bag, rig=rig)):
        if ordinal >= hi:
            break
        s = index[line.scanner_id]
        si = counters[s]
        counters[s] += 1
        if ordinal < lo:
            continue
        if bar is not None:
            bar.update(1)
        if line.n_valid == 0:
            continue
        times = line.times[line.valid_index]
        inside = (times >= kt[0]) & (times <= kt[-1])
        if not inside.any():
            continue
        p2 = line.points_xy[inside]
        p_s = np.column_stack((p2, np.zeros(p2.shape[0])))
        p_b = p_s @ T_bs[s][:3, :3].T + T_bs[s][:3, 3]
        if res.deskew is not None:
            p_b = res.deskew.apply(p_b, times[inside])
        beams = line.valid_index[inside]
        plane = np.full(beams.shape[0], -1, dtype=np.int32)
        ends: list[int] = []  # the scan's segments' first and last points
        k = s * (1 << 40) + si
        lo_k, hi_k = np.searchsorted(key_sorted, [k, k + 1])
        for r in order[lo_k:hi_k]:
            if rows["plane_id"][r] >= 0:
                m = np.flatnonzero((beams >= rows["first_beam"][r]) & (beams <= rows["last_beam"][r]))
                if m.size:
                    plane[m] = rows["plane_id"][r]
                    seg_stamp.append(line.stamp)
                    ends.extend((int(m[0]), int(m[-1])))
                    seg_pid.append(int(rows["plane_id"][r]))
        batch.add(p_b, s, times[inside], plane, ends)
    batch.flush()
    endpoints = np.concatenate(batch.endpoints_world) if batch.endpoints_world else np.zeros((0, 3))
    return _CloudPart(writer.count, seg_stamp, seg_pid, endpoints)


def _cloud_part_process(part: int, bag: str | Path, rig: Rig, res: SlamResult, rows_path: Path, lo: int, hi: int,
                        q: Any) -> None:
    """A forked export process: part ``part`` of the cloud pass written as bare PLY rows to
    ``rows_path``; ``(part, its _CloudPart or the exception)`` goes on ``q``."""
    try:
        with rows_path.open("wb") as f:
            q.put((part, _cloud_part(bag, rig, res, CloudPlyWriter(f, str(rows_path), header=False), lo, hi)))
    except BaseException as e:  # raised in the parent
        q.put((part, e))


def _next_part(bag: str | Path, q: Any, procs: list[Any]) -> tuple[int, _CloudPart]:
    """The next result of the export processes; their exception is raised here."""
    part, result = get_from_children(q, procs, f"{bag}: the cloud export processes")
    if isinstance(result, BaseException):
        raise result
    return part, result


def _cloud(bag: str | Path, rig: Rig, res: SlamResult, ply: Path, progress: bool,
           processes: int = 1) -> tuple[int, SegmentLines]:
    """Second pass over the bag: every valid point placed in the world with the final
    trajectory and written to the cloud.ply ``ply`` as it comes (so that the cloud is never
    held), and the associated segments' end points (world frame) for display; returns the
    number of points and the segments.

    With ``processes`` > 1 (and fork available, see ``slam.prefetch.can_fork_reader``) the scan
    stream is cut into that many consecutive parts: this process writes the first into ``ply``,
    forked processes write the others as bare rows beside it, appended in order at the end; the
    file is the same byte for byte."""
    names = res.scanner_names
    if len(names) > 256:
        raise ValueError(f"{bag}: {len(names)} scanners, at most 256 fit a cloud's scanner index")
    n_scans = int(res.stats["scans"])
    if not can_fork_reader():
        processes = 1
    processes = max(1, min(processes, n_scans))
    cuts = [round(i * n_scans / processes) for i in range(processes + 1)]
    cuts[-1] = sys.maxsize  # the last part takes the rest of the stream
    ctx = mp.get_context("fork") if processes > 1 else None
    q: Any = ctx.Queue() if ctx is not None else None
    procs = []
    row_files = [ply.with_name(f".{ply.stem}.part{i}.rows") for i in range(1, processes)]
    try:
        if ctx is not None:
            for i, path in enumerate(row_files, start=1):
                p = ctx.Process(target=_cloud_part_process, args=(i, bag, rig, res, path, cuts[i], cuts[i + 1], q),
                                name=f"backpack-slam-cloud-{i}", daemon=True)
                p.start()
                procs.append(p)
        with cloud_ply_writer(ply) as writer:
            desc = "cloud" if processes == 1 else f"cloud (part 1 of {processes})"
            with tqdm(total=min(cuts[1], n_scans), desc=desc, disable=not progress, leave=False) as bar:
                parts = [_cloud_part(bag, rig, res, writer, cuts[0], cuts[1], bar)]
            others = dict(_next_part(bag, q, procs) for _ in procs)
            for i in range(1, processes):
                writer.append_rows(row_files[i - 1], others[i].count)
                parts.append(others[i])
            n_points = writer.count
    finally:
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
            proc.join()
        for path in row_files:
            path.unlink(missing_ok=True)
    lines = SegmentLines(
        np.asarray([t for part in parts for t in part.seg_stamp], dtype=np.float64),
        np.concatenate([part.endpoints_world for part in parts]).reshape(-1, 2, 3),
        np.asarray([i for part in parts for i in part.seg_pid], dtype=np.int32),
    )
    return n_points, lines


def _write_outputs(
    out: Path,
    bag: str | Path,
    rig: Rig,
    cfg: SlamConfig,
    res: SlamResult,
    runner: SlamRunner,
    progress: bool,
    voxel: float | None,
) -> dict[str, Any]:
    write_trajectory_tum(out / "trajectory.tum", res.knot_times, res.T_world_body)
    planes = _plane_records(res, runner, with_cov=True)
    write_planes_json(out / "planes.json", planes)
    rows = res.segment_rows
    table = make_segment_table(
        res.scanner_names, rows["scanner"], rows["scan_index"], rows["stamp"], rows["first_beam"], rows["last_beam"], rows["plane_id"]
    )
    write_segments_npz(out / "segments.npz", table)
    n_cloud = 0
    view = None
    lines = None
    if cfg.output.cloud or cfg.output.rerun:
        v = voxel if voxel is not None else (cfg.output.voxel or None)
        # every point goes to a file as it is placed; the recording and the voxel thinning
        # read it back (the recording a chunk at a time)
        every = out / ("cloud.ply" if cfg.output.cloud and v is None else ".cloud_every_point.ply")
        n_every, lines = _cloud(bag, rig, res, every, progress, cfg.parallel.export_processes)
        if cfg.output.rerun and n_every > 0:
            view = view_of_cloud_ply(every, MapOptions())
        if cfg.output.cloud:
            n_cloud = n_every
            if v is not None:
                c = read_cloud_ply(every)
                n_cloud = write_cloud_ply(out / "cloud.ply", c.points_world, c.scanner, c.time, c.plane_id, voxel=v)
        if every.name != "cloud.ply":
            every.unlink()
    if cfg.output.rerun:
        write_map_rrd(
            out / "map.rrd",
            times=res.knot_times,
            T_world_body=res.T_world_body,
            planes=planes,
            cloud=view,
            scanner_names=res.scanner_names,
            segments=lines,
            options=MapOptions(),
        )
    st = res.stats
    return {
        "bag": str(bag),
        "rig": rig.name,
        "config": cfg.model_dump(),
        "counts": {
            "scans": st["scans"],
            "knots": st["knots"],
            "segments": st["segments"],
            "segments_associated": int((rows["plane_id"] >= 0).sum()),
            "planes": st["planes"],
            "planes_created": st["planes_created"],
            "planes_merged": st["planes_merged"],
            "planes_rejected": st["planes_rejected"],
            "planes_rejected_oblique": st["planes_rejected_oblique"],
            "observation_blocks": st["observation_blocks"],
            "wall_faces": st["wall_faces"],
            "edges": st["edges"],
            "edges_created": st["edges_created"],
            "edges_merged": st["edges_merged"],
            "edge_observations": st["edge_observations"],
            "trimmed_points": st["trimmed_points"],
            "trimmed_blocks": st["trimmed_blocks"],
            "isam2_updates": st["updates"],
            "isam2_rebuilds": st["isam2_rebuilds"],
            "isam2_fallbacks": st["isam2_fallbacks"],
            "imu_used": st["imu_used"],
            "zero_velocity_updates": st["zero_velocity_updates"],
            "cloud_points": n_cloud,
        },
        "batch": st.get("batch"),
        "singular_systems": {"count": len(st["singular_systems"]), "first": st["singular_systems"][:5]},
        "residuals": st.get("residuals"),
    }
