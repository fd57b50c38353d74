"""Planes of things that move (people walking by), found by the scans that pass through them.

A walker seen by a side scanner is a vertical line; the walker's front, as the walker moves
along it, stays on one vertical plane, so the front end's pool makes a plane of a walker as it
makes one of a wall, and associates the walker's later segments with it. What tells the two
apart is what happens after the walker has gone: the scans then pass through the plane where it
was seen and return from the wall behind it. A static surface is never seen through.

So every young plane (fewer than ``probation`` segments: a walker passes within a second or
two) is tested against the beams of each scan that cross the plane where it was seen: within
``near`` of one of the points its extent was grown by (in the plane; its 0.25 m extent cells
reach past its ends and into its doorways), grazing beams left out. Such a beam *passes through*
it when its return lies more than ``margin`` behind the plane (along the normal), and *returns
from* it otherwise. A beam that passes a surface's edge within ``near`` of its last points
crosses it too: a few beams per scan, against the many that return from the surface (a door
set 1-2 cm into its wall or a board on it is crossed only 1-2 cm before the wall's return, well
inside ``margin``).

A plane through which ``min_through`` beams passed, more than ``ratio`` times the beams it
returned, is a transient: the runner takes it out of the map and the back end, and its
segments are marked (``TRANSIENT`` in place of a plane id).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from slam.frontend import batch_kernels as bk
from slam.frontend.knots import KnotMirror
from slam.frontend.pending import PendingScan
from slam.frontend.planemap import Plane, PlaneMap

FloatArray = NDArray[np.float64]

TRANSIENT = -2  # the plane id a segment of a transient plane is marked with (-1: no plane)
MIN_RANGE = 0.3  # m, beams crossing a plane closer to the scanner than this are not counted (the operator)
MIN_COS = 0.3  # beams more grazing than this (cosine of the incidence) are not counted


@dataclass(frozen=True)
class TransientParams:
    """See the module doc: ``probation`` segments, ``margin`` and ``near`` (m), ``min_through``
    beams and ``ratio``; ``beam_step``: every this-many-th beam of a scan is tested. ``use``
    off: no test."""

    use: bool
    probation: int
    margin: float
    near: float
    min_through: int
    ratio: float
    beam_step: int


class TransientFilter:
    """The see-through test of the young planes of ``pmap`` (module doc), with the scans placed
    by the current knots (``knots``; ``T_body_scanner`` (4, 4) per scanner). ``fixed`` says
    which planes must stay (merged with another, or holding ties: removing them would take
    other planes' constraints along)."""

    def __init__(self, params: TransientParams, pmap: PlaneMap, knots: KnotMirror, T_body_scanner: list[FloatArray],
                 fixed: Callable[[int], bool]) -> None:
        self.params = params
        self._pmap = pmap
        self._knots = knots
        self._T_body_scanner = T_body_scanner
        self._fixed = fixed
        self.through: dict[int, int] = {}
        self.returned: dict[int, int] = {}
        self._trees: dict[int, tuple[int, FloatArray, cKDTree]] = {}  # per plane: its samples' 2D tree

    def _tree(self, plane: Plane) -> cKDTree:
        """The 2D tree (the plane's (u, v) frame) of the points the plane's extent was grown by,
        rebuilt when samples were added (the list only grows) or the plane's axes changed."""
        n = len(plane.samples)
        hit = self._trees.get(plane.id)
        if hit is None or hit[0] != n or hit[1] is not plane.u:
            pts = np.concatenate(plane.samples)
            hit = (n, plane.u, cKDTree(np.column_stack((pts @ plane.u, pts @ plane.v))))
            self._trees[plane.id] = hit
        return hit[2]

    def candidates(self) -> list[int]:
        """The planes on probation."""
        return [p.id for p in self._pmap.active_planes()
                if p.n_segments < self.params.probation and not self._fixed(p.id)]

    def check(self, scans: list[PendingScan]) -> list[int]:
        """Count the beams of ``scans`` through and on each plane on probation; returns the planes
        found transient (still in the map: the caller takes them out)."""
        pr = self.params
        if not pr.use or not scans:
            return []
        ids = self.candidates()
        if not ids:
            return []
        planes = [pl for pl in (self._pmap.planes[pid] for pid in ids) if pl.active and pl.samples]
        normals = np.array([pl.normal for pl in planes]).reshape(-1, 3)
        offsets = np.array([pl.d for pl in planes])
        us = np.array([pl.u for pl in planes]).reshape(-1, 3)
        vs = np.array([pl.v for pl in planes]).reshape(-1, 3)
        # per scan with beams to test: the crossings of every plane (``plane_crossings``: start
        # per plane, points in its (u, v) frame, whether the return lies beyond the margin)
        crossings: list[tuple[NDArray[np.int64], FloatArray, NDArray[np.bool_]]] = []
        for p in scans:
            segs = p.segs
            valid = np.flatnonzero(segs.beam_valid)[:: pr.beam_step]
            if valid.size == 0:
                continue
            T = self._knots.pose_at(segs.stamp) @ self._T_body_scanner[segs.scanner]
            a = segs.beam_angles[valid]
            r = segs.beam_ranges[valid].astype(np.float64)
            dirs = np.column_stack((np.cos(a), np.sin(a))) @ T[:3, :2].T  # (m, 3) world frame
            crossings.append(bk.plane_crossings(np.ascontiguousarray(dirs), r, np.ascontiguousarray(T[:3, 3]),
                                                normals, offsets, us, vs, pr.margin, MIN_RANGE, MIN_COS))
        if not crossings:
            return []
        # per scan and plane: the crossings within ``near`` of one of the plane's samples whose
        # return lies beyond the margin (through) or not (on); one tree query per plane over all
        # the scans' crossings
        n_cross = np.diff(np.array([c[0] for c in crossings]), axis=1)  # (scans, planes)
        ends = np.cumsum(n_cross, axis=0)
        through = np.zeros(n_cross.shape, dtype=np.int64)
        on = np.zeros(n_cross.shape, dtype=np.int64)
        for q in np.flatnonzero(n_cross.sum(axis=0)).tolist():
            uv = np.concatenate([c[1][c[0][q] : c[0][q + 1]] for c in crossings])
            far = np.concatenate([c[2][c[0][q] : c[0][q + 1]] for c in crossings])
            d, _ = self._tree(planes[q]).query(uv, distance_upper_bound=pr.near)
            near = np.isfinite(d)
            for out, hit in ((through, near & far), (on, near & ~far)):
                csum = np.concatenate(([0], np.cumsum(hit)))
                out[:, q] = csum[ends[:, q]] - csum[ends[:, q] - n_cross[:, q]]
        # the counts, scan by scan: a plane is found transient on the counts up to its scan (a
        # plane whose counts a scan left unchanged was already tested after an earlier scan)
        found: list[int] = []
        for i in range(n_cross.shape[0]):
            changed = np.flatnonzero(n_cross[i]).tolist()
            for q in changed:
                pid = planes[q].id
                self.through[pid] = self.through.get(pid, 0) + int(through[i, q])
                self.returned[pid] = self.returned.get(pid, 0) + int(on[i, q])
            for pid in ids if i == 0 else [planes[q].id for q in changed]:
                if pid not in found and self.through.get(pid, 0) >= pr.min_through \
                        and self.through[pid] > pr.ratio * self.returned.get(pid, 0):
                    found.append(pid)
        return found
