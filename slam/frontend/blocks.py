"""Observation blocks: the rows one step of the front end gives the back end, grouped by knot
interval and plane.

A segment observes its plane with its two virtual points (body frame), each in its own knot
interval at its fraction; a door edge's break observes its edge plane with one point. Rows of
one (interval, plane) become one block (``MapSink.add_observations``), in the order the keys
were first met.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slam.frontend.edges import Break
from slam.frontend.knots import KnotMirror
from slam.frontend.observations import ScanSegments
from slam.frontend.ports import MapSink
from slam.result import RunStats

FloatArray = NDArray[np.float64]


class ObservationBlocks:
    """Rows (point (3,) body frame, fraction, sigma) by (knot interval, plane id), kept as the
    chunks of rows of the calls (knots, plane ids, points, fractions, sigmas), grouped by block
    at :meth:`flush`."""

    def __init__(self, knots: KnotMirror, stats: RunStats) -> None:
        self._knots = knots
        self._stats = stats
        self._chunks: list[tuple[NDArray[np.int64], NDArray[np.int64], FloatArray, FloatArray, FloatArray]] = []

    def segment(self, segs: ScanSegments, j: int, pid: int) -> None:
        """Segment ``j`` of the scan observes plane ``pid``: its two virtual points."""
        self.segments(segs, np.array([j], dtype=np.int64), [pid])

    def segments(self, segs: ScanSegments, js: NDArray[np.int64], pids: list[int]) -> None:
        """Segments ``js`` of the scan observe planes ``pids`` (one each), in that order: the rows
        of as many :meth:`segment` calls, with one knot lookup for all of them."""
        if js.size == 0:
            return
        idx, alpha = self._knots.fractions(segs.virtual_times[js].ravel())
        self._chunks.append((np.asarray(idx, dtype=np.int64), np.repeat(np.asarray(pids, dtype=np.int64), 2),
                             segs.virtual_body[js].reshape(-1, 3), np.asarray(alpha, dtype=np.float64),
                             np.repeat(np.asarray(segs.virtual_sigma[js], dtype=np.float64), 2)))

    def point(self, brk: Break, pid: int) -> None:
        """A break observes the edge plane ``pid``."""
        idx, alpha = self._knots.fractions(np.array([brk.time]))
        self._chunks.append((np.asarray(idx, dtype=np.int64), np.array([pid], dtype=np.int64),
                             np.asarray(brk.point_body).reshape(1, 3), np.asarray(alpha, dtype=np.float64),
                             np.array([float(brk.sigma)])))
        self._stats.edge_observations += 1

    def flush(self, sink: MapSink) -> None:
        """Hand every block to the back end (in the order the blocks were first met, each with
        its rows in the order they came) and start empty."""
        if not self._chunks:
            return
        chunks, self._chunks = self._chunks, []
        knot = np.concatenate([c[0] for c in chunks])
        pid = np.concatenate([c[1] for c in chunks])
        pts = np.concatenate([c[2] for c in chunks])
        al = np.concatenate([c[3] for c in chunks])
        sg = np.concatenate([c[4] for c in chunks])
        order, starts, first = block_order(knot, pid)
        pts, al, sg = pts[order], al[order], sg[order]
        b = starts.tolist()
        knots, pids = knot[first].tolist(), pid[first].tolist()
        for i in range(len(knots)):
            sink.add_observations(knots[i], pids[i], pts[b[i] : b[i + 1]].copy(), al[b[i] : b[i + 1]].copy(),
                                  sg[b[i] : b[i + 1]].copy())
        self._stats.observation_blocks += len(knots)


def block_order(knot: NDArray[np.int64], pid: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64],
                                                                          NDArray[np.int64]]:
    """Rows (knot, plane id) (n,) grouped by key, the keys in the order they first occur, the
    rows of a key in their order: the rows' permutation (n,), each group's start in it (g + 1,)
    and each group's first row (g,)."""
    if knot.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, np.zeros(1, dtype=np.int64), empty
    lo = int(pid.min())
    keys = (knot - knot.min()) * (int(pid.max()) - lo + 1) + (pid - lo)  # one integer per (knot, plane id)
    _, first, inverse, counts = np.unique(keys, return_index=True, return_inverse=True, return_counts=True)
    rank = np.empty(first.size, dtype=np.int64)
    by_first = np.argsort(first, kind="stable")
    rank[by_first] = np.arange(first.size)
    order = np.argsort(rank[inverse.ravel()], kind="stable")
    starts = np.zeros(first.size + 1, dtype=np.int64)
    np.cumsum(counts[by_first], out=starts[1:])
    return order, starts, first[by_first]
