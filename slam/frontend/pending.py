"""Scans between their arrival and the end of their use: the front end's queues.

A scan's segments wait (*pending*) until the knot after their last beam is processed; then they
are *ready*: tracked against the map with the scans of the tracking window (*recent*),
associated, and kept (*done*) while the pool of unassociated segments may still make planes
from them. Older scans are compacted to their segment rows (scanner, scan, beam range, plane),
which the result reports.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam.frontend.edges import Break
from slam.frontend.observations import ScanSegments

FloatArray = NDArray[np.float64]


@dataclass
class PendingScan:
    """A scan's segments waiting for (or done with) association; ``plane_ids`` per segment (-1:
    none), ``t_end`` its last beam's time (s)."""

    serial: int
    segs: ScanSegments
    t_end: float
    plane_ids: NDArray[np.int64]
    loose_ids: NDArray[np.int64] | None = None  # the tracking pre-association's plane ids
    # breaks matched to known edges by the tracking pre-association: body points, times, edge ids, sigmas
    loose_edges: tuple[FloatArray, FloatArray, NDArray[np.int64], FloatArray] | None = None
    # the scan-only part of the edge tests (``frontend.scan_prep.scan_edge_tests``), asked of the
    # wall segments by both the tracking pre-association and the observation
    edge_tests: dict[tuple[int, int], Any] = field(default_factory=dict)
    # the breaks found last with these plane ids and hosts (the tracking pre-association's are
    # mostly the observation's: only their world placement changes with the tracked trajectory)
    breaks_memo: tuple[bytes, dict[int, int], list[Break]] | None = None


SegmentRows = tuple[NDArray[Any], ...]  # scanner, scan index, stamp, first beam, last beam, plane id


class ScanQueues:
    """The pending, recent (tracking window) and done scans, and the compacted rows of older ones."""

    def __init__(self) -> None:
        self.pending: list[PendingScan] = []
        self.recent: list[PendingScan] = []  # ready scans within the tracking window
        self.done: list[PendingScan] = []  # associated scans still within reach of the pool
        self._rows: list[SegmentRows] = []  # compacted segment rows of older scans
        self._serial = 0

    def add(self, segs: ScanSegments, edge_tests: dict[tuple[int, int], Any]) -> None:
        """Queue a scan's segments (its edge tests are handed over with them)."""
        self.pending.append(PendingScan(self._serial, segs, float(segs.times.max()),
                                        np.full(segs.n_segments, -1, dtype=np.int64), edge_tests=edge_tests))
        self._serial += 1

    def last_end(self) -> float | None:
        """The latest last-beam time of the pending scans, None without any."""
        return max((p.t_end for p in self.pending), default=None)

    def take_ready(self, t: float) -> list[PendingScan]:
        """Remove and return the pending scans whose beams all end by ``t`` (s)."""
        ready = [p for p in self.pending if p.t_end <= t]
        self.pending = [p for p in self.pending if p.t_end > t]
        return ready

    def track(self, ready: list[PendingScan], t_lo: float) -> list[PendingScan]:
        """Add ``ready`` to the recent scans and drop those ending before ``t_lo``; returns them."""
        self.recent.extend(ready)
        self.recent = [p for p in self.recent if p.t_end >= t_lo]
        return self.recent

    def by_serial(self) -> dict[int, PendingScan]:
        """The done scans by serial."""
        return {p.serial: p for p in self.done}

    def compact(self, horizon: float) -> None:
        """Keep only the segment rows of the done scans that end before ``horizon`` (s)."""
        n_old = 0
        while n_old < len(self.done) and self.done[n_old].t_end < horizon:
            n_old += 1
        if n_old:
            self._rows.append(_rows_of(self.done[:n_old]))
            del self.done[:n_old]

    def segment_rows(self, resolve: Callable[[int], int]) -> dict[str, NDArray[Any]]:
        """Every scan's segment rows, sorted by scanner, scan and first beam, with plane ids
        resolved through the merges (``resolve``: id -> current id); the dtypes of segments.npz
        (int32 but for the int64 scan index and the float64 stamp)."""
        parts = [*self._rows, _rows_of(self.done + self.pending)]
        scanner, scan_index, stamp, first, last, pid = (np.concatenate(c) for c in zip(*parts, strict=True))
        order = np.lexsort((first, scan_index, scanner))
        pid = pid[order]
        ids, inverse = np.unique(pid, return_inverse=True)  # each plane id resolved once
        resolved = np.array([resolve(int(i)) if i >= 0 else -1 for i in ids], dtype=np.int32)
        return {
            "scanner": scanner[order].astype(np.int32),
            "scan_index": scan_index[order].astype(np.int64),
            "stamp": stamp[order],
            "first_beam": first[order],
            "last_beam": last[order],
            "plane_id": resolved[inverse.reshape(-1)] if ids.size else pid,
        }


def _rows_of(recs: list[PendingScan]) -> SegmentRows:
    """The compacted rows of ``recs``: scanner int16, scan index, first and last beam and plane id
    int32, stamp float64 (26 B a segment; an hour's walk has about 2.7 M)."""
    if not recs:
        z = np.zeros(0, dtype=np.int32)
        return z.astype(np.int16), z, np.zeros(0), z, z, z
    counts = np.array([r.segs.n_segments for r in recs], dtype=np.int64)
    return (
        np.repeat(np.array([r.segs.scanner for r in recs], dtype=np.int16), counts),
        np.repeat(np.array([r.segs.scan_index for r in recs], dtype=np.int32), counts),
        np.repeat(np.array([r.segs.stamp for r in recs], dtype=np.float64), counts),
        np.concatenate([r.segs.first_beam for r in recs]).astype(np.int32),
        np.concatenate([r.segs.last_beam for r in recs]).astype(np.int32),
        np.concatenate([r.plane_ids for r in recs]).astype(np.int32),
    )
