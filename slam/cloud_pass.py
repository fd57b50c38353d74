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

import itertools
import multiprocessing as mp
from array import array
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from common.rig import Rig
from segmentation import Scanline
from slam.export import CloudPlyWriter, cloud_ply_writer
from slam.frontend.transients import TRANSIENT
from slam.heap import HeapKeeper
from slam.io.source import BagSource, Echo, StampWindow, StreamIndex
from slam.pipeline import SlamResult
from slam.prefetch import can_fork_reader, get_from_children
from slam.rerun_map import SegmentLines
from slam.trajectory.placement import place_points

FloatArray = NDArray[np.float64]

_PLACE_CHUNK = 4096  # cloud points per place_points call: its (m, 3, 3) temporaries stay in cache (~2x faster)
_EXPORT_BATCH = 1 << 18  # cloud points placed and written at a time (~10 MB of body points)


class _CloudBatch:
    """Scans' points (body frame) gathered until there are enough to place together; then placed
    in the world with the final trajectory, in chunks of ``_PLACE_CHUNK``, and written; after each
    batch the heap is trimmed when the process's resident memory has crept up (``HeapKeeper``:
    the pass's allocations, taken from an inherited, trimmed heap's free chunks, would otherwise
    make it grow with the walk)."""

    def __init__(self, res: SlamResult, writer: CloudPlyWriter) -> None:
        self._kt, self._T = res.knot_times, res.T_world_body
        self._writer = writer
        self._cols: list[tuple[FloatArray, NDArray[np.uint8], FloatArray, NDArray[np.int32]]] = []
        self._intensity: list[NDArray[np.float32]] = []
        self._ends: list[int] = []  # the batch's segments' first and last point indices
        self.n = 0  # points in the batch
        self.endpoints_world: list[FloatArray] = []  # (m, 3) per flushed batch
        self._heap = HeapKeeper()

    def add(self, points_body: FloatArray, scanner: int, times: FloatArray, plane_id: NDArray[np.int32],
            ends: list[int], intensity: NDArray[np.float32] | None = None) -> None:
        """A scan's points (body frame) with their times (s), plane ids and, for a writer with
        intensities, their intensities; ``ends`` indexes its segments' first and last points in
        the scan."""
        self._cols.append((points_body, np.full(times.shape[0], scanner, dtype=np.uint8), times, plane_id))
        if self._writer.intensity:
            self._intensity.append(intensity if intensity is not None
                                   else np.full(times.shape[0], np.nan, dtype=np.float32))
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
        self._writer.write(pw, sc, tm, pid, np.concatenate(self._intensity) if self._writer.intensity else None)
        self.endpoints_world.append(pw[np.asarray(self._ends, dtype=np.int64)])
        self._cols, self._ends, self._intensity, self.n = [], [], [], 0
        del pb, sc, tm, pid, pw
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
    """What one part of the cloud pass found: its points' count and its associated segments
    (scan stamps, plane ids, end points in the world frame, (m, 3), two rows per segment)."""

    count: int
    seg_stamp: FloatArray  # (k,)
    seg_pid: NDArray[np.int32]  # (k,)
    endpoints_world: FloatArray


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


def cloud_part(scans: Iterable[Scanline], part: CloudPart, rig: Rig, res: SlamResult, writer: CloudPlyWriter,
               bar: Any = None) -> CloudPartResult:
    """The part's scans (``scans``, in stream order) placed in the world with the final trajectory
    and written with ``writer`` as they come.

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
    # typed buffers, not lists: an hour's walk has about 2.7 M associated segments (8 + 4 B each
    # here, ~60 B as Python floats and ints in a list)
    seg_stamp = array("d")
    seg_pid = array("i")
    counters = list(part.first_scan_index)
    batch = _CloudBatch(res, writer)
    n_scans = 0
    for line in scans:
        n_scans += 1
        s = index[line.scanner_id]
        si = counters[s]
        counters[s] += 1
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
            if rows["plane_id"][r] == TRANSIENT:  # a thing that moved (a person): marked, in no plane
                plane[(beams >= rows["first_beam"][r]) & (beams <= rows["last_beam"][r])] = TRANSIENT
            elif rows["plane_id"][r] >= 0:
                m = np.flatnonzero((beams >= rows["first_beam"][r]) & (beams <= rows["last_beam"][r]))
                if m.size:
                    plane[m] = rows["plane_id"][r]
                    seg_stamp.append(line.stamp)
                    ends.extend((int(m[0]), int(m[-1])))
                    seg_pid.append(int(rows["plane_id"][r]))
        batch.add(p_b, s, times[inside], plane, ends,
                  None if line.intensities is None else line.intensities[beams])
    batch.flush()
    if part.hi is not None and n_scans != part.hi - part.lo:
        raise RuntimeError(f"cloud pass: scans {part.lo}:{part.hi} of the stream came back as {n_scans} scans")
    endpoints = np.concatenate(batch.endpoints_world) if batch.endpoints_world else np.zeros((0, 3))
    return CloudPartResult(writer.count, np.frombuffer(seg_stamp, dtype=np.float64).copy(),
                           np.frombuffer(seg_pid, dtype=np.int32).copy(), endpoints)


def _part_process(i: int, part: CloudPart, bag: Path, rig: Rig, res: SlamResult, rows_path: Path, q: Any,
                  echo: Echo, intensity: bool) -> None:
    """A forked export process: part ``i`` of the cloud pass, read from its own ``BagSource`` of
    ``bag``, written as bare PLY rows (with intensities or without) to ``rows_path``; ``(i, its
    CloudPartResult or the exception)`` goes on ``q``."""
    try:
        with BagSource(bag) as source, rows_path.open("wb") as f:
            writer = CloudPlyWriter(f, str(rows_path), header=False, intensity=intensity)
            q.put((i, cloud_part(source.scans(rig=rig, window=part.window, echo=echo, record=False), part, rig, res, writer)))
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
                progress: bool, processes: int = 1, *, echo: Echo) -> tuple[int, SegmentLines]:
    """The second pass over ``source``'s scans (their stream's ``index``, see :func:`plan_parts`;
    a MultiEchoLaserScan's ``echo`` of each beam, the run's ``input.echo``): every valid point
    placed in the world and written to the cloud.ply ``ply``, with an intensity property when the
    scans carry intensities (``index.intensities``; without an index, when the first scan of a
    topic does); returns the number of points and the associated segments' end points (world
    frame).

    With ``processes`` > 1 (and fork available, see ``slam.prefetch.can_fork_reader``) the pass
    is cut into that many parts, the first written here and the others by forked processes."""
    names = res.scanner_names
    if len(names) > 256:
        raise ValueError(f"{source.path}: {len(names)} scanners, at most 256 fit a cloud's scanner index")
    intensity = index.intensities if index is not None else scans_have_intensities(source, rig, echo)
    parts = plan_parts(index, names, processes if can_fork_reader() else 1)
    ctx = mp.get_context("fork") if len(parts) > 1 else None
    q: Any = ctx.Queue() if ctx is not None else None
    procs = []
    row_files = [ply.with_name(f".{ply.stem}.part{i}.rows") for i in range(1, len(parts))]
    try:
        if ctx is not None:
            for i, path in enumerate(row_files, start=1):
                p = ctx.Process(target=_part_process, args=(i, parts[i], source.path, rig, res, path, q, echo, intensity),
                                name=f"backpack-slam-cloud-{i}", daemon=True)
                p.start()
                procs.append(p)
        with cloud_ply_writer(ply, intensity=intensity) as writer:
            first = parts[0]
            desc = "cloud" if len(parts) == 1 else f"cloud (part 1 of {len(parts)})"
            total = None if first.hi is None else first.hi - first.lo
            with tqdm(total=total, desc=desc, disable=not progress, leave=False) as bar:
                scans = source.scans(rig=rig, window=first.window, echo=echo, record=False)  # no per-scan index
                found = [cloud_part(scans, first, rig, res, writer, bar)]
            others = dict(_next_part(source.path, q, procs) for _ in procs)
            for i in range(1, len(parts)):
                writer.append_rows(row_files[i - 1], others[i].count)
                found.append(others[i])
            n_points = writer.count
    finally:
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
            proc.join()
        for path in row_files:
            path.unlink(missing_ok=True)
    lines = SegmentLines(
        np.concatenate([part.seg_stamp for part in found]).astype(np.float64),
        np.concatenate([part.endpoints_world for part in found]).reshape(-1, 2, 3),
        np.concatenate([part.seg_pid for part in found]).astype(np.int32),
    )
    return n_points, lines
