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
    """Rows (point (3,) body frame, fraction (1,), sigma (1,)) by (knot interval, plane id)."""

    def __init__(self, knots: KnotMirror, stats: RunStats) -> None:
        self._knots = knots
        self._stats = stats
        self._rows: dict[tuple[int, int], list[tuple[FloatArray, FloatArray, FloatArray]]] = {}

    def segment(self, segs: ScanSegments, j: int, pid: int) -> None:
        """Segment ``j`` of the scan observes plane ``pid``: its two virtual points."""
        idx, alpha = self._knots.fractions(segs.virtual_times[j])
        for q in range(2):
            self._rows.setdefault((int(idx[q]), pid), []).append(
                (segs.virtual_body[j, q], np.array([alpha[q]]), np.array([segs.virtual_sigma[j]]))
            )

    def point(self, brk: Break, pid: int) -> None:
        """A break observes the edge plane ``pid``."""
        idx, alpha = self._knots.fractions(np.array([brk.time]))
        self._rows.setdefault((int(idx[0]), pid), []).append((brk.point_body, alpha, np.array([brk.sigma])))
        self._stats.edge_observations += 1

    def flush(self, sink: MapSink) -> None:
        """Hand every block to the back end and start empty."""
        for (knot, pid), rows in self._rows.items():
            pts = np.array([r[0] for r in rows])
            al = np.concatenate([r[1] for r in rows])
            sg = np.concatenate([r[2] for r in rows])
            sink.add_observations(knot, pid, pts, al, sg)
            self._stats.observation_blocks += 1
        self._rows = {}
