"""The cloud's second pass over the bag: every valid point placed in the world with the final
trajectory and written to a cloud.ply as it comes (so the cloud is never held), with the plane
id of the associated segment covering its beam (and its return's intensity when the recording's
scans carry intensities), and those segments' end points (world frame) for display.

The pass can be cut into consecutive parts of the scan stream, by stamp windows
(``slam.io.source.StampWindow``): this process writes the first into the cloud.ply, forked
processes (each with its own ``BagSource``) write the others as bare rows beside it, appended in
order at the end; the file is the same byte for byte as one pass's.
"""

from __future__ import annotations

import contextlib
import itertools
import multiprocessing as mp
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from common.rig import Rig
from segmentation import Scanline
from slam import cloud_kernels as ck
from slam.export import CloudPlyWriter, CloudRecord, PointCounter, PointSink, cloud_ply_writer
from slam.forked import can_fork_reader, die_with_parent, get_from_children, stop_children
from slam.frontend.transients import TRANSIENT
from slam.heap import HeapKeeper
from slam.io.source import BagSource, Echo, StampWindow, StreamIndex
from slam.pipeline import SlamResult
from slam.rerun_map import (
    CloudView,
    CloudViewPicker,
    MapOptions,
    SegmentLines,
    joined_view,
    view_of_cloud_ply,
    view_strides,
)
from slam.trajectory.placement import place_points

FloatArray = NDArray[np.float64]

_PLACE_CHUNK = 4096  # cloud points per place_points call: its poses and points stay in cache (~1.2x faster)
_EXPORT_BATCH = 1 << 18  # cloud points placed and written at a time (~10 MB of body points)


class _SegmentRows:
    """The run's associated segments (``SlamResult.segment_rows``) ordered by (scanner, scan
    index), for the plane ids of a batch of scans' points (:func:`slam.cloud_kernels.segment_planes`)."""

    def __init__(self, rows: Mapping[str, NDArray[Any]]) -> None:
        key = rows["scanner"].astype(np.int64) * (1 << 40) + rows["scan_index"].astype(np.int64)
        self.order = np.argsort(key, kind="stable")
        self.key_sorted = np.ascontiguousarray(key[self.order])
        self.first = np.ascontiguousarray(rows["first_beam"], dtype=np.int64)
        self.last = np.ascontiguousarray(rows["last_beam"], dtype=np.int64)
        self.plane = np.ascontiguousarray(rows["plane_id"], dtype=np.int64)

    def ranges(self, scanner: NDArray[np.int64], scan_index: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Each scan's rows: ``order[lo:hi]``."""
        k = scanner * (1 << 40) + scan_index
        return (np.searchsorted(self.key_sorted, k).astype(np.int64),
                np.searchsorted(self.key_sorted, k + 1).astype(np.int64))


class _CloudBatch:
    """Scans gathered until they hold enough points to handle together: their valid points within
    the knots lifted into the body frame (and deskewed), given the plane ids of their associated
    segments, placed in the world with the final trajectory, written, and picked for the
    recording's view; after each batch the heap is trimmed when the process's resident memory
    has crept up (``HeapKeeper``: the pass's allocations, taken from an inherited, trimmed heap's
    free chunks, would otherwise make it grow with the walk).

    Every number is computed point by point (the body frame by one small matrix product per
    scan, as before), so the cloud is the same however the scans are batched."""

    def __init__(self, res: SlamResult, rig: Rig, writer: PointSink, picker: CloudViewPicker | None) -> None:
        self._kt, self._T, self._deskew = res.knot_times, res.T_world_body, res.deskew
        self._T_bs = [s.T_body_scanner.matrix() for s in rig.scanners]
        self._rows = _SegmentRows(res.segment_rows)
        self._normals, self._offsets = plane_table(res)
        self._writer = writer
        self._picker = picker
        self._scans: list[Scanline] = []
        self._scanner: list[int] = []
        self._scan_index: list[int] = []
        self.n = 0  # valid returns in the batch
        self.endpoints_world: list[FloatArray] = []  # (m, 3) per flushed batch
        self.seg_stamp: list[FloatArray] = []
        self.seg_pid: list[NDArray[np.int32]] = []
        self.seg_rms: list[NDArray[np.float32]] = []
        self._heap = HeapKeeper()

    def add(self, line: Scanline, scanner: int, scan_index: int) -> None:
        """A scan (its scanner's index in the rig and the scan's ordinal among that scanner's)."""
        if line.n_valid == 0:
            return
        self._scans.append(line)
        self._scanner.append(scanner)
        self._scan_index.append(scan_index)
        self.n += line.n_valid
        if self.n >= _EXPORT_BATCH:
            self.flush()

    def flush(self) -> None:
        scans = self._scans
        if not scans:
            return
        counts = np.array([line.n_valid for line in scans], dtype=np.int64)
        slot = np.repeat(np.arange(len(scans), dtype=np.int64), counts)
        times = np.concatenate([line.times[line.valid_index] for line in scans])
        beams = np.concatenate([line.valid_index for line in scans]).astype(np.int64, copy=False)
        xy = np.concatenate([line.points_xy for line in scans])
        scanner = np.repeat(np.array(self._scanner, dtype=np.int32), counts)
        inten = None
        if self._writer.intensity:
            inten = np.concatenate([line.intensities[line.valid_index] if line.intensities is not None
                                    else np.full(line.n_valid, np.nan, dtype=np.float32) for line in scans])
        inside = (times >= self._kt[0]) & (times <= self._kt[-1])
        if not inside.all():
            slot, times, beams, xy, scanner = slot[inside], times[inside], beams[inside], xy[inside], scanner[inside]
            inten = None if inten is None else inten[inside]
        if times.size:
            scan_start = np.searchsorted(slot, np.arange(len(scans) + 1)).astype(np.int64)
            p_b = np.empty((times.size, 3))
            # a product per scan: a small one gets the same bits from BLAS however many threads it
            # has (a batch-sized one would start them: two export processes on two cores crawl)
            for j, a, b in zip(self._scanner, scan_start[:-1].tolist(), scan_start[1:].tolist(), strict=True):
                if b > a:
                    T = self._T_bs[j]
                    p_b[a:b] = np.column_stack((xy[a:b], np.zeros(b - a))) @ T[:3, :3].T + T[:3, 3]
            if self._deskew is not None:
                p_b = self._deskew.apply(p_b, times)
            lo, hi = self._rows.ranges(np.array(self._scanner, dtype=np.int64), np.array(self._scan_index, dtype=np.int64))
            plane, seg_scan, seg_pid, ends = ck.segment_planes(
                beams, scan_start, lo, hi, self._rows.order, self._rows.first, self._rows.last, self._rows.plane,
                TRANSIENT)
            p_w = np.empty_like(p_b)
            for a in range(0, times.size, _PLACE_CHUNK):
                b = min(a + _PLACE_CHUNK, times.size)
                p_w[a:b] = place_points(self._kt, self._T, times[a:b], p_b[a:b])
            self._writer.write(p_w, scanner, times, plane, inten)
            if self._picker is not None:
                self._picker.take(CloudRecord(p_w, scanner, times, plane))
            self.endpoints_world.append(p_w[ends])
            self.seg_stamp.append(np.array([line.stamp for line in scans], dtype=np.float64)[seg_scan])
            self.seg_pid.append(seg_pid.astype(np.int32))
            self.seg_rms.append(segment_rms(p_w, ends, seg_pid, self._normals, self._offsets))
        self._scans, self._scanner, self._scan_index, self.n = [], [], [], 0
        self._heap.check()


@dataclass(frozen=True)
class CloudPart:
    """Scans ``lo:hi`` of the scan stream (ordinals; ``hi`` None: to the end) and the scans each
    scanner has before them (``first_scan_index``); ``window`` selects them from the bag (None:
    the whole stream, one part)."""

    lo: int
    hi: int | None
    first_scan_index: tuple[int, ...]
    window: StampWindow | None


@dataclass
class CloudPartResult:
    """What one part of the cloud pass found: its points' count, its associated segments (scan
    stamps, plane ids, end points in the world frame, (m, 3), two rows per segment, their points'
    RMS distance to their plane) and, when
    asked, the points it picked for the recording's view."""

    count: int
    seg_stamp: FloatArray  # (k,)
    seg_pid: NDArray[np.int32]  # (k,)
    endpoints_world: FloatArray
    seg_rms: NDArray[np.float32]  # (k,) m, each segment's points' RMS distance to its plane
    view: CloudViewPicker | None = None  # the recording's view of the part, when picked


def plane_table(res: SlamResult) -> tuple[FloatArray, FloatArray]:
    """The final planes' normals (P, 3) and offsets (P,) (world frame) as rows indexed by plane
    id, NaN for the ids without an estimate (merged or taken out)."""
    ids = np.asarray(res.plane_ids, dtype=np.int64)
    n = int(ids.max()) + 1 if ids.size else 0
    normals, offsets = np.full((n, 3), np.nan), np.full(n, np.nan)
    if ids.size:
        normals[ids] = np.asarray(res.plane_normals, dtype=np.float64).reshape(-1, 3)
        offsets[ids] = np.asarray(res.plane_offsets, dtype=np.float64)
    return normals, offsets


def segment_rms(points_world: FloatArray, ends: NDArray[np.int64], seg_plane: NDArray[np.integer],
                normals: FloatArray, offsets: FloatArray) -> NDArray[np.float32]:
    """Per associated segment (its first and last point ``ends[2k]``, ``ends[2k + 1]`` of
    ``points_world`` (n, 3), world frame, and its plane ``seg_plane[k]``, a row of ``normals``
    (P, 3) and ``offsets`` (P,): :func:`plane_table`), the root mean square distance (m) of its
    points to its plane; NaN where the plane has no row or its row is NaN. (numpy: a compiled
    kernel would be one more to load in each of the pass's processes, ~50 MB apiece.)"""
    m = seg_plane.shape[0]
    if m == 0:
        return np.zeros(0, dtype=np.float32)
    first, last = ends[0::2], ends[1::2]
    size = last - first + 1
    plane = np.asarray(seg_plane, dtype=np.int64)
    known = (plane >= 0) & (plane < offsets.shape[0])
    row = np.where(known, plane, 0)
    starts = np.concatenate(([0], np.cumsum(size)[:-1]))
    idx = np.repeat(first - starts, size) + np.arange(int(size.sum()))  # each segment's points, in order
    seg = np.repeat(np.arange(m), size)
    r = np.einsum("ij,ij->i", points_world[idx], normals[row[seg]]) + offsets[row[seg]]
    out = np.sqrt(np.add.reduceat(r * r, starts) / size)
    out[~known] = np.nan
    return out.astype(np.float32)


def plan_parts(index: StreamIndex | None, scanner_names: list[str], processes: int) -> list[CloudPart]:
    """The stream cut into at most ``processes`` parts of about as many scans, each cut between
    two different stamps; one part without a window when the stream's ``index`` is unknown or
    was not in stamp order (its scans could not be found again by stamp)."""
    if index is None or index.lag_ns is None or not index.in_stamp_order() or processes <= 1:
        return [CloudPart(0, None, (0,) * len(scanner_names), None)]
    n, stamps = len(index), index.stamps
    cuts = [0]
    for i in range(1, processes):
        c = max(round(i * n / processes), cuts[-1] + 1)
        while c < n and stamps[c - 1] == stamps[c]:
            c += 1
        if c < n:
            cuts.append(c)
    cuts.append(n)
    which = {name: s for s, name in enumerate(scanner_names)}
    counts = [0] * len(scanner_names)
    parts = []
    for lo, hi in itertools.pairwise(cuts):
        start = stamps[lo] if lo > 0 else None
        stop = stamps[hi] if hi < n else None
        parts.append(CloudPart(lo, hi, tuple(counts), StampWindow(start, stop, index.lag_ns)))
        for sid in index.scanner_ids[lo:hi]:
            counts[which[sid]] += 1
    return parts


def cloud_part(scans: Iterable[Scanline], part: CloudPart, rig: Rig, res: SlamResult, writer: PointSink,
               bar: Any = None, picker: CloudViewPicker | None = None) -> CloudPartResult:
    """The part's scans (``scans``, in stream order) placed in the world with the final trajectory
    and written with ``writer`` as they come; with a ``picker``, the recording's view picked from
    them.

    Points are handled a batch of scans at a time (every point gets the same numbers however the
    points are batched), so the parts of a split pass, concatenated, are the whole pass's cloud
    byte for byte."""
    index = {n: i for i, n in enumerate(res.scanner_names)}
    counters = list(part.first_scan_index)
    batch = _CloudBatch(res, rig, writer, picker)
    n_scans = 0
    for line in scans:
        n_scans += 1
        s = index[line.scanner_id]
        batch.add(line, s, counters[s])
        counters[s] += 1
        if bar is not None:
            bar.update(1)
    batch.flush()
    if part.hi is not None and n_scans != part.hi - part.lo:
        raise RuntimeError(f"cloud pass: scans {part.lo}:{part.hi} of the stream came back as {n_scans} scans")
    endpoints = np.concatenate(batch.endpoints_world) if batch.endpoints_world else np.zeros((0, 3))
    seg_stamp = np.concatenate(batch.seg_stamp) if batch.seg_stamp else np.zeros(0)
    seg_pid = np.concatenate(batch.seg_pid) if batch.seg_pid else np.zeros(0, dtype=np.int32)
    seg_rms = np.concatenate(batch.seg_rms) if batch.seg_rms else np.zeros(0, dtype=np.float32)
    return CloudPartResult(writer.count, seg_stamp, seg_pid, endpoints, seg_rms, picker)


def _part_process(i: int, part: CloudPart, bag: Path, rig: Rig, res: SlamResult, rows_path: Path | None, q: Any,
                  echo: Echo, intensity: bool, strides: tuple[int, int] | None, parent: int) -> None:
    """A forked export process (of ``parent``): part ``i`` of the cloud pass, read from its own
    ``BagSource`` of ``bag``, written as bare PLY rows (with intensities or without) to
    ``rows_path`` (None: only counted), its view picked at ``strides`` (None: none); ``(i, its
    CloudPartResult or the exception)`` goes on ``q``."""
    die_with_parent(parent)
    try:
        with BagSource(bag) as source, contextlib.ExitStack() as stack:
            writer: PointSink = PointCounter(intensity)
            if rows_path is not None:
                f = stack.enter_context(rows_path.open("wb"))
                writer = CloudPlyWriter(f, str(rows_path), header=False, intensity=intensity)
            picker = None if strides is None else CloudViewPicker(*strides)
            q.put((i, cloud_part(source.scans(rig=rig, window=part.window, echo=echo, record=False), part, rig, res,
                                 writer, picker=picker)))
    except BaseException as e:  # raised in the parent
        q.put((i, e))


def _next_part(bag: Path, q: Any, procs: list[Any]) -> tuple[int, CloudPartResult]:
    """The next result of the export processes; their exception is raised here."""
    i, result = get_from_children(q, procs, f"{bag}: the cloud export processes")
    if isinstance(result, BaseException):
        raise result
    return i, result


def scans_have_intensities(source: BagSource, rig: Rig, echo: Echo) -> bool:
    """Whether the first scan of any of the rig's topics carries intensities."""
    for s in rig.scanners:
        stream = source.scans(topics=[s.topic], rig=rig, echo=echo)
        try:
            first = next(stream, None)
        finally:
            stream.close()
        if first is not None and first.intensities is not None:
            return True
    return False


def write_cloud(source: BagSource, rig: Rig, res: SlamResult, ply: Path, index: StreamIndex | None,
                progress: bool, processes: int = 1, *, echo: Echo,
                view: MapOptions | None = None, keep_points: bool = True) -> tuple[int, SegmentLines, CloudView | None]:
    """The second pass over ``source``'s scans (their stream's ``index``, see :func:`plan_parts`;
    a MultiEchoLaserScan's ``echo`` of each beam, the run's ``input.echo``): every valid point
    placed in the world and written to the cloud.ply ``ply``, with an intensity property when the
    scans carry intensities (``index.intensities``; without an index, when the first scan of a
    topic does); returns the number of points, the associated segments' end points (world
    frame) and, with ``view``'s caps, the recording's :class:`CloudView` (picked as the points
    are written when the ``index`` tells how many there can be, at strides from that count; else
    from the file after the pass).

    With ``processes`` > 1 (and fork available, see ``slam.forked.can_fork_reader``) the pass
    is cut into that many parts, the first written here and the others by forked processes.

    Without ``keep_points`` nothing is written (``ply`` is not made): the points are counted, and
    the segments and the recording's view (which then needs the ``index``) are what the pass gives."""
    names = res.scanner_names
    if len(names) > 256:
        raise ValueError(f"{source.path}: {len(names)} scanners, at most 256 fit a cloud's scanner index")
    intensity = index.intensities if index is not None else scans_have_intensities(source, rig, echo)
    parts = plan_parts(index, names, processes if can_fork_reader() else 1)
    ctx = mp.get_context("fork") if len(parts) > 1 else None
    q: Any = ctx.Queue() if ctx is not None else None
    procs = []
    # the other parts' bare rows until they are joined (None: a part that keeps no point)
    row_files = [ply.with_name(f".{ply.stem}.part{i}.rows") if keep_points else None for i in range(1, len(parts))]
    strides = None if view is None or index is None else view_strides(index.points, view)
    if not keep_points and view is not None and strides is None:
        raise ValueError(f"{source.path}: a cloud pass that keeps no points picks the recording's view only with the "
                         "stream's index")
    try:
        if ctx is not None:
            for i, path in enumerate(row_files, start=1):
                p = ctx.Process(target=_part_process, name=f"backpack-slam-cloud-{i}", daemon=True,
                                args=(i, parts[i], source.path, rig, res, path, q, echo, intensity, strides, os.getpid()))
                p.start()
                procs.append(p)
        with contextlib.ExitStack() as stack:
            ply_writer = stack.enter_context(cloud_ply_writer(ply, intensity=intensity)) if keep_points else None
            writer: PointSink = ply_writer if ply_writer is not None else PointCounter(intensity)
            first = parts[0]
            desc = "cloud" if len(parts) == 1 else f"cloud (part 1 of {len(parts)})"
            total = None if first.hi is None else first.hi - first.lo
            with tqdm(total=total, desc=desc, disable=not progress, leave=False) as bar:
                scans = source.scans(rig=rig, window=first.window, echo=echo, record=False)  # no per-scan index
                found = [cloud_part(scans, first, rig, res, writer, bar,
                                    picker=None if strides is None else CloudViewPicker(*strides))]
            others = dict(_next_part(source.path, q, procs) for _ in procs)
            for i, path in enumerate(row_files, start=1):
                if ply_writer is not None and path is not None:
                    ply_writer.append_rows(path, others[i].count)
                found.append(others[i])
            n_points = sum(part.count for part in found)
    finally:
        stop_children(procs)
        for path in row_files:
            if path is not None:
                path.unlink(missing_ok=True)
    lines = SegmentLines(
        np.concatenate([part.seg_stamp for part in found]).astype(np.float64),
        np.concatenate([part.endpoints_world for part in found]).reshape(-1, 2, 3),
        np.concatenate([part.seg_pid for part in found]).astype(np.int32),
        np.concatenate([part.seg_rms for part in found]).astype(np.float32),
    )
    shown = None
    if view is not None and n_points:
        pickers = [part.view for part in found if part.view is not None and part.view.n]
        shown = joined_view(pickers) if strides is not None else view_of_cloud_ply(ply, view)
    return n_points, lines, shown
