"""Door and board edges as a feature of the front end: breaks found per scan
(``frontend.edge_finder``) observe edge planes (``frontend.edges.EdgeMap``), pending breaks
cluster into new edges, duplicates are tied together.

The runner holds an :class:`EdgeTracker` with ``edges.use`` on and a :class:`NoEdges` with it
off: the same calls, the second does nothing.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from slam.frontend.blocks import ObservationBlocks
from slam.frontend.edge_finder import BreakFinder
from slam.frontend.edges import EdgeMap, EdgeParams, along_wall
from slam.frontend.knots import KnotMirror
from slam.frontend.pending import PendingScan
from slam.frontend.planemap import PlaneMap
from slam.frontend.ports import MapSink
from slam.result import RunStats

FloatArray = NDArray[np.float64]
# rows for the tracker: points (m, 3) body frame, knot interval within the window (m,), fraction
# (m,), their planes' normals (m, 3) and offsets (m,) world frame, sigmas (m,)
TrackRows = tuple[FloatArray, NDArray[np.int64], FloatArray, FloatArray, FloatArray, FloatArray]


class EdgeFeature(Protocol):
    """What the runner asks of the edges (see :class:`EdgeTracker`)."""

    def tracks(self) -> bool: ...

    def match_loose(self, p: PendingScan, hosts: dict[int, int]) -> None: ...

    def tracking_rows(self, recent: list[PendingScan], k0: int) -> list[TrackRows]: ...

    def observe(self, p: PendingScan, ids: NDArray[np.int64], hosts: dict[int, int], now: float,
                blocks: ObservationBlocks) -> None: ...

    def create(self, now: float) -> None: ...

    def refresh(self, now: float) -> None: ...

    def count(self) -> int: ...


class EdgeTracker:
    """Edges of the map's walls (``pmap``) placed with the current knots (``knots``); new edge
    planes, their ties and observations go to ``sink``, counts to ``stats``."""

    def __init__(self, params: EdgeParams, pmap: PlaneMap, knots: KnotMirror, T_body_scanner: list[FloatArray],
                 range_sigma: list[float], sink: MapSink, stats: RunStats) -> None:
        self.params = params
        self.emap = EdgeMap(params, pmap.resolve, generation=lambda: pmap.merges)
        self.finder = BreakFinder(params, pmap, knots, T_body_scanner, range_sigma)
        self._pmap = pmap
        self._knots = knots
        self._sink = sink
        self._stats = stats

    def tracks(self) -> bool:
        """Whether there are edges for the tracker's pre-association."""
        return bool(self.emap.edges)

    def match_loose(self, p: PendingScan, hosts: dict[int, int]) -> None:
        """Match the breaks of a ready scan (with its pre-association's plane ids) to known edges
        with the tracking gate; kept in ``p.loose_edges`` for the tracker."""
        assert p.loose_ids is not None
        rows = []
        for brk in self.finder.breaks(p, p.loose_ids, hosts):
            edge = self.emap.match(brk, gate=self.params.tracking_gate)
            if edge is not None:
                rows.append((brk.point_body, brk.time, edge.id, brk.sigma))
        if rows:
            p.loose_edges = (
                np.array([r[0] for r in rows]),
                np.array([r[1] for r in rows]),
                np.array([r[2] for r in rows], dtype=np.int64),
                np.array([r[3] for r in rows]),
            )

    def tracking_rows(self, recent: list[PendingScan], k0: int) -> list[TrackRows]:
        """The recent scans' loosely matched breaks within the window from knot ``k0``, against
        their edges' current estimates (one block of rows for all the scans, none without)."""
        held = [p.loose_edges for p in recent if p.loose_edges is not None]
        if not held:
            return []
        # all the scans' breaks in one block, in scan order (the tracker concatenates the blocks)
        e_pts, e_t, e_ids, e_sig = (np.concatenate(c) for c in zip(*held, strict=True))
        idx, alpha = self._knots.fractions(e_t)
        inside = idx >= k0
        if not inside.any():
            return []
        edges = [self.emap.edges[self.emap.root(i)] for i in e_ids[inside].tolist()]
        return [(e_pts[inside], idx[inside] - k0, alpha[inside], np.array([e.normal for e in edges]),
                 np.array([e.d for e in edges]), e_sig[inside])]

    def observe(self, p: PendingScan, ids: NDArray[np.int64], hosts: dict[int, int], now: float,
                blocks: ObservationBlocks) -> None:
        """Each break of the scan (plane ids ``ids``) observes its edge plane, or waits in the
        edge map's pending list."""
        for brk in self.finder.breaks(p, ids, hosts):
            edge = self.emap.match(brk)
            if edge is None:
                self.emap.pending.append(brk)
                continue
            blocks.point(brk, edge.id)
            edge.n_obs += 1
            edge.last_seen_time = now

    def create(self, now: float) -> None:
        """New edge planes from clusters of pending breaks: vertical, tied perpendicular to the wall."""
        self.emap.expire(now)
        for members, u in self.emap.cluster():
            b0 = members[0]
            host = self._pmap.resolve(b0.host)
            n_e = along_wall(self._pmap.planes[host].normal)
            z = [float(b.point_world[2]) for b in members]
            edge = self.emap.add(host, b0.step, b0.side, n_e, u, now, (min(z), max(z)))
            anchor = np.mean([b.point_world for b in members], axis=0)
            self._sink.add_plane(edge.id, n_e, -u, vertical=True, anchor=anchor)
            self._sink.add_perpendicular(host, edge.id, self.params.perpendicular_sigma)
            blocks = ObservationBlocks(self._knots, self._stats)
            for b in members:
                blocks.point(b, edge.id)
            blocks.flush(self._sink)
            edge.n_obs = len(members)
            self._stats.edges_created += 1

    def refresh(self, now: float) -> None:
        """Copy the recently seen edges' estimates in and tie duplicated edges together."""
        for e in self.emap.active():
            if now - e.last_seen_time < 5.0:
                e.normal, e.d = self._sink.plane(e.id)
        sigma = self.params.link_sigma
        for keep, drop in self.emap.duplicates():
            self._sink.link_planes(keep.id, drop.id, sigma, sigma)
            drop.merged_into = keep.id
            keep.z_range = (min(keep.z_range[0], drop.z_range[0]), max(keep.z_range[1], drop.z_range[1]))
            keep.n_obs += drop.n_obs
            keep.last_seen_time = max(keep.last_seen_time, drop.last_seen_time)
            self._stats.edges_merged += 1

    def count(self) -> int:
        """The active (not merged) edges."""
        return len(self.emap.active())


class NoEdges:
    """The edge feature switched off (``edges.use``): no breaks, no edges."""

    def tracks(self) -> bool:
        return False

    def match_loose(self, p: PendingScan, hosts: dict[int, int]) -> None:
        return None

    def tracking_rows(self, recent: list[PendingScan], k0: int) -> list[TrackRows]:
        return []

    def observe(self, p: PendingScan, ids: NDArray[np.int64], hosts: dict[int, int], now: float,
                blocks: ObservationBlocks) -> None:
        return None

    def create(self, now: float) -> None:
        return None

    def refresh(self, now: float) -> None:
        return None

    def count(self) -> int:
        return 0


def edge_feature(params: EdgeParams | None, pmap: PlaneMap, knots: KnotMirror, T_body_scanner: list[FloatArray],
                 range_sigma: list[float], sink: MapSink, stats: RunStats) -> EdgeFeature:
    """An :class:`EdgeTracker` with ``params``, :class:`NoEdges` without (``edges.use`` off)."""
    if params is None:
        return NoEdges()
    return EdgeTracker(params, pmap, knots, T_body_scanner, range_sigma, sink, stats)
