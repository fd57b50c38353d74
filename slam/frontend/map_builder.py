"""The plane life cycle: observation, creation from the pool, ties to a host, merges.

Associated segments extend their plane's extent and observe it; the others wait in the pool
(``frontend.plane_init``) from which new planes are made. A new plane is classified (wall,
floor, ceiling, other), must be observed well enough to fix its tilt, and may be tied to an
established plane (:class:`HostTies`): parallel to a wall it lies a few centimetres off (a
door set into it, a board on it), or parallel to the other face of its partition (a room's
wall and the corridor's). After every back-end update the recently seen planes take the new
estimates and planes that converged onto one surface merge (also how a loop closes).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from slam.frontend.blocks import ObservationBlocks
from slam.frontend.knots import KnotMirror
from slam.frontend.pending import PendingScan, ScanQueues
from slam.frontend.plane_init import NewPlane, PooledSegment, SegmentPool, on_plane, tilt_sigma
from slam.frontend.planemap import (
    HORIZONTAL_KINDS,
    KIND_CEILING,
    KIND_FLOOR,
    KIND_OTHER,
    KIND_WALL,
    PlaneMap,
    classify,
    is_other_face,
    merge_tolerance,
)
from slam.frontend.ports import MapSink
from slam.result import RunStats

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class MapParams:
    """The plane life cycle (``slam.params.map_params``; angles in radians, lengths in metres,
    see ``slam.config.FrontEndConfig``)."""

    min_segment_points: int  # a shorter unassociated segment is not pooled
    vertical_tolerance: float
    vertical_walls: bool
    min_support_oblique: int
    max_tilt_sigma: float
    extent_margin_cells: int
    host_min_segments: int
    parallel_max_angle: float
    parallel_max_offset: float
    parallel_sigma: float
    wall_faces: bool
    wall_thickness: tuple[float, float]
    wall_faces_sigma: float
    merge_angle: float
    merge_distance: float
    merge_drift_over: str
    merge_coobserved_max: float
    drift_rate: float
    drift_rate_vertical: float
    link_sigma: float
    child_merge_distance: float  # m, a tied door or board merges with its wall only nearer than this
    child_adopt_cells: int  # cells: a new door or board adopts pooled segments with both ends this near its extent
    distinct_offset: float  # m: parallel planes one scan's segments took this far apart are two surfaces (0: off)
    layer_merge_distance: float  # m: a child longer than child_max_length this near its wall is a layer of it (0: off)
    child_max_length: float  # m


class TieKind(Enum):
    """How a plane is tied parallel to its host: set into the wall behind its face (a door),
    standing in front of it (a board), or the wall's other face."""

    DOOR = "door"
    BOARD = "board"
    FACE = "face"


class HostTies:
    """Ties child plane -> host plane with their kind, resolved through the map's merges."""

    def __init__(self, pmap: PlaneMap) -> None:
        self._pmap = pmap
        self._ties: dict[int, tuple[int, TieKind]] = {}
        self._n_parallel = 0  # doors and boards
        # the doors' and boards' ties resolved through the merges, kept while no plane is merged or tied
        self._resolved: tuple[tuple[int, int], dict[int, int]] | None = None

    def tie(self, child: int, host: int, kind: TieKind) -> None:
        """Record that plane ``child`` was tied to ``host`` (raw ids)."""
        self._ties[child] = (host, kind)
        if kind is not TieKind.FACE:
            self._n_parallel += 1

    def kind_of(self, child: int) -> TieKind | None:
        """The kind of a (raw) plane's tie, None when it is tied to nothing."""
        tie = self._ties.get(child)
        return None if tie is None else tie[1]

    def children(self) -> dict[int, int]:
        """Current (merged) plane id -> its current host wall id, for the tied doors and boards.
        Merges can fold a door into the plane its wall was merged with and the other way round;
        of two planes tied either way the one with more segments is the wall (never a child)."""
        pmap = self._pmap
        state = (pmap.merges, self._n_parallel)
        if self._resolved is None or self._resolved[0] != state:
            out = {}
            for child, (host, kind) in self._ties.items():
                if kind is TieKind.FACE:
                    continue
                c, h = pmap.resolve(child), pmap.resolve(host)
                if c != h:
                    out[c] = h
            self._resolved = (state, out)
        planes = pmap.planes
        return {c: h for c, h in self._resolved[1].items() if planes[c].n_segments <= planes[h].n_segments}


class MapBuilder:
    """The map's planes (``pmap``) and pool of unassociated segments (``pool``); planes, ties
    and observations go to ``sink``, counts to ``stats``; points are placed with ``knots``."""

    def __init__(self, params: MapParams, pmap: PlaneMap, pool: SegmentPool, knots: KnotMirror, sink: MapSink,
                 stats: RunStats) -> None:
        self.params = params
        self.pmap = pmap
        self.pool = pool
        self.ties = HostTies(pmap)
        self._knots = knots
        self._sink = sink
        self._stats = stats
        # pairs of plane ids that one scan's segments took as two surfaces (``_note_distinct``)
        self._distinct: set[frozenset[int]] = set()

    # ------------------------------------------------------------------ observation
    def observe(self, p: PendingScan, ids: NDArray[np.int64], v_world: FloatArray, e_world: FloatArray,
                T_body_scanner: FloatArray, now: float, blocks: ObservationBlocks,
                grows: NDArray[np.bool_] | None = None) -> None:
        """The scan's associated segments (plane ids ``ids``; -1: none, -2: held back as
        ambiguous) observe their planes and, where ``grows`` (default: all), extend them; the
        long enough unassociated others (-1) go to the pool. ``v_world``/``e_world`` (k, 2, 3)
        are the segments' virtual and end points placed in the world (``T_body_scanner``: the
        scan's scanner)."""
        segs = p.segs
        associated = np.flatnonzero(ids >= 0)
        pooled = np.flatnonzero((ids == -1) & (segs.n_points >= self.params.min_segment_points))
        # every 8th point of the associated segments (extents), every 12th of the pooled ones
        placed, bounds = self._knots.place_segments_flat(segs, np.concatenate((associated, pooled)),
                                                         np.repeat([8, 12], [associated.size, pooled.size]))
        pids = ids[associated].tolist()
        if self.params.distinct_offset > 0.0:
            self._note_distinct(set(pids))
        blocks.segments(segs, associated, pids)
        self.pmap.observe_segments(pids, placed, bounds[: associated.size + 1],
                                   np.ones(associated.size, dtype=np.bool_) if grows is None else grows[associated],
                                   now, self._knots.odometer)
        self._stats.associated += associated.size
        b = bounds.tolist()
        for i, j in enumerate(pooled.tolist(), start=associated.size):
            samples = placed[b[i] : b[i + 1]]
            v, e = v_world[j], e_world[j]
            d = e[1] - e[0]
            t_mid = float(segs.virtual_times[j].mean())
            T_mid = self._knots.pose_at(t_mid) @ T_body_scanner
            self.pool.add(
                PooledSegment(
                    ref=(p.serial, int(j)),
                    time=t_mid,
                    scan_serial=p.serial,
                    centroid=v.mean(axis=0),
                    direction=d / max(float(np.linalg.norm(d)), 1e-9),
                    endpoints=e,
                    samples=samples,
                    line=v,
                    scan_normal=T_mid[:3, 2],
                    origin=T_mid[:3, 3].copy(),
                )
            )

    def _note_distinct(self, pids: set[int]) -> None:
        """Record the pairs of ``pids`` (planes one scan's segments were associated with) that face
        the same way, parallel, with offsets more than ``distinct_offset`` apart: seen side by side
        from one pose, with the scan's common offset taken out by the association, they are two
        surfaces (a board and its wall), whatever the drift since either was made; :meth:`merge`
        then merges them only as a door or board with its wall. (A wall's duplicate made after a
        loop is seen instead of the old copy, not beside it.)"""
        if len(pids) < 2:
            return
        planes = self.pmap.planes
        cos_max = np.cos(self.params.merge_angle)
        ps = sorted(pids)
        for i, a in enumerate(ps):
            pa = planes[a]
            for b in ps[i + 1 :]:
                pb = planes[b]
                if float(pa.normal @ pb.normal) >= cos_max and abs(pa.d - pb.d) > self.params.distinct_offset:
                    self._distinct.add(frozenset((a, b)))

    # ------------------------------------------------------------------ creation
    def create_planes(self, now: float, queues: ScanQueues) -> None:
        """New planes from the pool (its segments belong to the done scans of ``queues``)."""
        mp = self.params
        self.pool.expire(now)
        new = self.pool.create_planes()
        if not new:
            return
        by_serial = queues.by_serial()
        body_z = float(self._knots.T[self._knots.n - 1, 2, 3])
        for plane in new:
            kind = classify(plane.normal, plane.d, body_z, mp.vertical_tolerance)
            vertical = plane.vertical_hypothesis or (mp.vertical_walls and kind == KIND_WALL)
            if kind == KIND_OTHER and len(plane.members) < mp.min_support_oblique:
                self._stats.planes_rejected += 1
                self._stats.planes_rejected_oblique += 1
                continue
            if not self._constrained(plane, by_serial, kind, vertical):
                self._stats.planes_rejected += 1
                continue
            pts = np.vstack([m.samples for m in plane.members])
            host = self._host_of(plane, pts)
            if host is not None:
                # a door set into its wall or a board on it: parallel to the wall by construction;
                # fitted alone, a patch a metre wide gets its heading wrong by up to a degree, and
                # along a corridor that tilt is the only thing "observing" the walking direction
                plane.normal = self.pmap.planes[host].normal.copy()
                plane.d = -float(np.mean(pts @ plane.normal))
            pl = self.pmap.add(plane.normal, plane.d, kind, now, self._knots.odometer)
            anchor = pts.mean(axis=0)
            self._sink.add_plane(
                pl.id,
                plane.normal,
                plane.d,
                horizontal=kind in (KIND_FLOOR, KIND_CEILING),
                vertical=vertical,
                anchor=anchor,
            )
            if host is not None:
                self._sink.add_parallel(host, pl.id, mp.parallel_sigma)
                # in front of the wall's face (along its normal, towards the side it is seen from): a board
                in_front = self.pmap.planes[host].d - plane.d > 0.0
                self.ties.tie(pl.id, host, TieKind.BOARD if in_front else TieKind.DOOR)
                self._stats.planes_parallel += 1
            elif kind == KIND_WALL and mp.wall_faces:
                face = self._other_face_of(plane.normal, pts)
                if face is not None:
                    self._sink.add_parallel(face, pl.id, mp.wall_faces_sigma)
                    self.ties.tie(pl.id, face, TieKind.FACE)
                    self._stats.wall_faces += 1
            blocks = ObservationBlocks(self._knots, self._stats)
            for m in plane.members:
                rec = by_serial.get(m.ref[0])
                if rec is None:
                    continue
                j = m.ref[1]
                rec.plane_ids[j] = pl.id
                blocks.segment(rec.segs, j, pl.id)
                self.pmap.extend(pl.id, m.samples)
                pl.n_segments += 1
            blocks.flush(self._sink)
            self._stats.planes_created += 1
            self._stats.associated += len(plane.members)
            self._adopt_pooled(pl.id, by_serial, child=host is not None)

    def _host_of(self, plane: NewPlane, pts: FloatArray) -> int | None:
        """The established plane a new one (its members' points ``pts``, world frame) lies on,
        parallel and a few centimetres off (a door in its wall, a board on it), or None.
        Established: ``host_min_segments`` segments."""
        mp = self.params
        cos_max = np.cos(mp.parallel_max_angle)
        best: tuple[float, int] | None = None
        for pid in self.pmap.active_ids():
            h = self.pmap.planes[int(pid)]
            if h.n_segments < mp.host_min_segments or float(h.normal @ plane.normal) < cos_max:
                continue
            off = float(np.max(np.abs(pts @ h.normal + h.d)))
            if off > mp.parallel_max_offset:
                continue
            if not self.pmap.overlaps(int(pid), pts, mp.extent_margin_cells):
                continue
            if best is None or off < best[0]:
                best = (off, int(pid))
        return None if best is None else best[1]

    def _other_face_of(self, normal: FloatArray, pts: FloatArray) -> int | None:
        """The established wall whose other face a new wall (``normal``, its members' points
        ``pts``, world frame) is: facing the opposite way, its points ``wall_thickness`` behind the
        wall's face and over its extent; the one with the most segments, or None."""
        mp = self.params
        cos_min = np.cos(mp.parallel_max_angle)
        best: tuple[int, int] | None = None
        for pid in self.pmap.active_ids():
            w = self.pmap.planes[int(pid)]
            if w.kind != KIND_WALL or w.n_segments < mp.host_min_segments:
                continue
            if not is_other_face(w.normal, w.d, normal, pts, cos_min, mp.wall_thickness):
                continue
            if not self.pmap.overlaps(int(pid), pts, mp.extent_margin_cells):
                continue
            if best is None or w.n_segments > best[0]:
                best = (w.n_segments, int(pid))
        return None if best is None else best[1]

    def _constrained(self, plane: NewPlane, by_serial: dict[int, PendingScan], kind: int, vertical: bool) -> bool:
        """Whether the members' observations (virtual points, as the back end will see them) fix
        the new plane's tilt to ``max_tilt_sigma``, given its horizontality/verticality prior:
        a thin strip of points (a door frame seen edge-on) leaves the solver a nearly singular
        plane, which makes iSAM2 fail."""
        if kind in (KIND_FLOOR, KIND_CEILING):
            return True  # both tilts held by the horizontality prior
        pts, sig = [], []
        for m in plane.members:
            rec = by_serial.get(m.ref[0])
            if rec is None:
                continue
            j = m.ref[1]
            pts.append(self._knots.place(rec.segs.virtual_body[j], rec.segs.virtual_times[j]))
            sig.append(np.repeat(rec.segs.virtual_sigma[j], 2))
        if len(pts) < 2:
            return False
        about = np.array([0.0, 0.0, 1.0]) if vertical else None
        return tilt_sigma(np.concatenate(pts), np.concatenate(sig), plane.normal, about) < self.params.max_tilt_sigma

    def _adopt_pooled(self, pid: int, by_serial: dict[int, PendingScan], child: bool = False) -> None:
        """Give a new plane the pooled segments that lie on it but were not among its seed group; a
        door or board (``child``) only those lying in its extent end to end (its wall's segments
        refused by the wall, a metre beside it, would otherwise stretch it along the wall)."""
        pl = self.pmap.planes[pid]
        taken = []
        blocks = ObservationBlocks(self._knots, self._stats)
        for m in self.pool.items:
            if abs(float(m.direction @ pl.normal)) > np.sin(np.radians(2.0)):
                continue
            if not on_plane(m, pl.normal, pl.d, self.pool.params):
                continue
            if not self.pmap.overlaps(pid, m.samples, self.params.extent_margin_cells):
                continue
            if child and not all(self.pmap.overlaps(pid, x[None], self.params.child_adopt_cells) for x in m.endpoints):
                continue
            rec = by_serial.get(m.ref[0])
            if rec is None:
                continue
            rec.plane_ids[m.ref[1]] = pid
            blocks.segment(rec.segs, m.ref[1], pid)
            self.pmap.extend(pid, m.samples)
            pl.n_segments += 1
            taken.append(m)
        if taken:
            blocks.flush(self._sink)
            self.pool.remove(taken)
            self._stats.associated += len(taken)

    # ------------------------------------------------------------------ after a back-end update
    def refresh(self, now: float) -> None:
        """Copy the recently seen planes' estimates in from the back end."""
        for pl in self.pmap.active_planes():
            if now - pl.last_seen_time < 5.0:
                n, d = self._sink.plane(pl.id)
                self.pmap.set_estimate(pl.id, n, d)

    def _layer_host(self, a: int, b: int, children: dict[int, int]) -> int | None:
        """The wall of the pair when the other plane, tied to it as a door or board, is a second
        layer of it instead: longer than any door or board (``child_max_length``) and within
        ``layer_merge_distance`` of the wall over its whole extent; else None. Such a layer takes
        the wall's segments (it is nearer them than the wall wherever the pose estimate leans its
        way), so the door edges along the wall are no longer found."""
        mp = self.params
        if mp.layer_merge_distance <= 0.0:
            return None
        for child, host in ((a, b), (b, a)):
            if children.get(child) == host and self.pmap.extent_length(child) > mp.child_max_length and \
                    self.pmap.max_distance_over(child, host) <= mp.layer_merge_distance:
                return host
        return None

    def merge(self, now: float) -> None:
        """Merge the recently seen planes with the planes they converged onto (the same facing,
        touching extents, offsets within the drift since they were seen): tied in the back end,
        folded into one in the map."""
        mp = self.params
        recent = [p for p in self.pmap.active_planes() if now - p.last_seen_time < 2.0]
        cos_max = np.cos(mp.merge_angle)
        # doors and boards with their wall, and with one another on one wall: distinct surfaces
        children = self.ties.children()
        tied = {frozenset(pair) for pair in children.items()}
        tied |= {frozenset((a, b)) for a, ha in children.items() for b, hb in children.items() if a != b and ha == hb}
        for a in recent:
            if not a.active:
                continue
            for b in list(self.pmap.active_planes()):  # a snapshot: merges below change the list
                if b.id == a.id or not b.active or not a.active:
                    continue
                if float(a.normal @ b.normal) < cos_max:  # same facing only: not the two faces of a wall
                    continue
                rate = mp.drift_rate_vertical if a.kind in HORIZONTAL_KINDS else mp.drift_rate
                if mp.merge_drift_over == "gap":
                    walked = self.pmap.unseen_between(a.id, b.id)
                else:
                    walked = max(0.0, self._knots.odometer - min(a.last_seen_odometer, b.last_seen_odometer))
                tol = merge_tolerance(mp.merge_distance, rate, walked, self.pmap.coobserved(a.id, b.id),
                                      mp.merge_coobserved_max)
                if not self.pmap.extents_touch(a.id, b.id, mp.extent_margin_cells):
                    continue
                # the offset difference over the smaller plane's extent (where both are seen), so
                # that a tilted plane (a door fitted with a bit of its wall) does not merge on the
                # strength of its centre alone
                small, big = (a, b) if len(a.cells) <= len(b.cells) else (b, a)
                dist = self.pmap.max_distance_over(small.id, big.id)
                host = self._layer_host(a.id, b.id, children)
                if host is None:
                    if dist > tol:
                        continue
                    # a door or board and its wall (or another child of it): one surface only when
                    # nearer than any door or board
                    pair = frozenset((a.id, b.id))
                    if (pair in tied or pair in self._distinct) and dist > min(mp.child_merge_distance, tol):
                        continue
                    keep, drop = (a, b) if a.n_segments >= b.n_segments else (b, a)
                else:
                    keep, drop = (a, b) if a.id == host else (b, a)
                    self._stats.wall_layers_merged += 1
                self._sink.link_planes(keep.id, drop.id, mp.link_sigma, mp.link_sigma)
                self.pmap.merge(keep.id, drop.id)
                self._stats.planes_merged += 1
