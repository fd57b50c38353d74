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
    """Rows (point (3,) body frame, fraction, sigma) by (knot interval, plane id), kept as three
    lists per block."""

    def __init__(self, knots: KnotMirror, stats: RunStats) -> None:
        self._knots = knots
        self._stats = stats
        self._rows: dict[tuple[int, int], tuple[list[FloatArray], list[float], list[float]]] = {}

    def segment(self, segs: ScanSegments, j: int, pid: int) -> None:
        """Segment ``j`` of the scan observes plane ``pid``: its two virtual points."""
        self.segments(segs, np.array([j], dtype=np.int64), [pid])

    def segments(self, segs: ScanSegments, js: NDArray[np.int64], pids: list[int]) -> None:
        """Segments ``js`` of the scan observe planes ``pids`` (one each), in that order: the rows
        of as many :meth:`segment` calls, with one knot lookup for all of them."""
        if js.size == 0:
            return
        idx, alpha = self._knots.fractions(segs.virtual_times[js].ravel())
        knot, frac, sigma = idx.tolist(), alpha.tolist(), segs.virtual_sigma[js].tolist()
        for q, (j, pid) in enumerate(zip(js.tolist(), pids, strict=True)):
            for e in range(2):
                pts, al, sg = self._rows.setdefault((knot[2 * q + e], pid), ([], [], []))
                pts.append(segs.virtual_body[j, e])
                al.append(frac[2 * q + e])
                sg.append(sigma[q])

    def point(self, brk: Break, pid: int) -> None:
        """A break observes the edge plane ``pid``."""
        idx, alpha = self._knots.fractions(np.array([brk.time]))
        pts, al, sg = self._rows.setdefault((int(idx[0]), pid), ([], [], []))
        pts.append(brk.point_body)
        al.append(float(alpha[0]))
        sg.append(float(brk.sigma))
        self._stats.edge_observations += 1

    def flush(self, sink: MapSink) -> None:
        """Hand every block to the back end and start empty."""
        for (knot, pid), (pts, al, sg) in self._rows.items():
            sink.add_observations(knot, pid, np.array(pts), np.array(al), np.array(sg))
            self._stats.observation_blocks += 1
        self._rows = {}
