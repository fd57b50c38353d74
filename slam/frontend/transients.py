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

from collections.abc import Callable, Container
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from segmentation.scanline import beam_cos_sin
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
    by the current knots (``knots``; ``T_body_scanner`` (4, 4) per scanner). ``fixed()`` gives
    the planes that must stay (merged with another, or holding ties: removing them would take
    other planes' constraints along)."""

    def __init__(self, params: TransientParams, pmap: PlaneMap, knots: KnotMirror, T_body_scanner: list[FloatArray],
                 fixed: Callable[[], Container[int]]) -> None:
        self.params = params
        self._pmap = pmap
        self._knots = knots
        self._T_body_scanner = T_body_scanner
        self._fixed = fixed
        self.through: dict[int, int] = {}
        self.returned: dict[int, int] = {}
        # per plane: its samples in its (u, v) frame, sorted by u (``_samples_uv``)
        self._samples: dict[int, tuple[int, FloatArray, FloatArray, FloatArray]] = {}

    def _samples_uv(self, plane: Plane) -> tuple[FloatArray, FloatArray]:
        """The points the plane's extent was grown by in its (u, v) frame, sorted by u (the
        coordinates a 2D tree of them would hold), rebuilt when samples were added (the list
        only grows) or the plane's axes changed."""
        n = len(plane.samples)
        hit = self._samples.get(plane.id)
        if hit is None or hit[0] != n or hit[1] is not plane.u:
            pts = np.concatenate(plane.samples)
            su, sv = pts @ plane.u, pts @ plane.v
            order = np.argsort(su, kind="stable")
            hit = (n, plane.u, su[order], sv[order])
            self._samples[plane.id] = hit
        return hit[2], hit[3]

    def candidates(self) -> list[int]:
        """The planes on probation."""
        probation = self.params.probation
        young = [p.id for p in self._pmap.active_planes() if p.n_segments < probation]
        if not young:
            return young
        fixed = self._fixed()
        return [pid for pid in young if pid not in fixed]

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
        # the beams to test of every scan, in the world frame
        segs_list = [p.segs for p in scans]
        cos_a, sin_a = zip(*(beam_cos_sin(segs.beam_angles) for segs in segs_list), strict=True)
        beam_start = np.zeros(len(segs_list) + 1, dtype=np.int64)
        np.cumsum([segs.beam_angles.shape[0] for segs in segs_list], out=beam_start[1:])
        T_world_scanner = np.array([self._knots.pose_at(segs.stamp) @ self._T_body_scanner[segs.scanner]
                                    for segs in segs_list])
        dirs, ranges, bounds, origins = bk.strided_beams_world(
            np.concatenate(cos_a), np.concatenate(sin_a), np.concatenate([segs.beam_ranges for segs in segs_list]),
            np.concatenate([segs.beam_valid for segs in segs_list]), beam_start, T_world_scanner, pr.beam_step)
        if bounds.shape[0] == 1:
            return []
        # per scan and plane: the crossings, and those within ``near`` of one of the plane's
        # samples whose return lies beyond the margin (through) or not (on)
        samples = [self._samples_uv(pl) for pl in planes]
        sample_start = np.zeros(len(planes) + 1, dtype=np.int64)
        np.cumsum(np.array([su.size for su, _ in samples], dtype=np.int64), out=sample_start[1:])
        n_cross, through, on = bk.see_through_counts(
            dirs, ranges, bounds, origins, normals, offsets, us, vs,
            np.concatenate([np.empty(0), *(su for su, _ in samples)]),
            np.concatenate([np.empty(0), *(sv for _, sv in samples)]), sample_start,
            pr.margin, pr.near, MIN_RANGE, MIN_COS)
        # the counts, scan by scan: a plane is found transient on the counts up to its scan (a
        # plane whose counts a scan left unchanged was already tested after an earlier scan)
        plane_ids = [pl.id for pl in planes]
        through_sum = np.cumsum(through, axis=0) + np.array([self.through.get(pid, 0) for pid in plane_ids],
                                                            dtype=np.int64)
        on_sum = np.cumsum(on, axis=0) + np.array([self.returned.get(pid, 0) for pid in plane_ids], dtype=np.int64)
        for q in np.flatnonzero(n_cross.any(axis=0)).tolist():
            self.through[plane_ids[q]] = int(through_sum[-1, q])
            self.returned[plane_ids[q]] = int(on_sum[-1, q])
        transient = (through_sum >= pr.min_through) & (through_sum > pr.ratio * on_sum)
        # after the first scan every plane on probation, after the others the planes whose counts changed
        found: list[int] = []
        row = {pid: q for q, pid in enumerate(plane_ids)}
        for pid in ids:
            r = row.get(pid)
            if (self._transient(pid) if r is None else bool(transient[0, r])) and pid not in found:
                found.append(pid)
        for q in np.nonzero((n_cross[1:] != 0) & transient[1:])[1].tolist():
            pid = plane_ids[q]
            if pid not in found:
                found.append(pid)
        return found

    def _transient(self, pid: int) -> bool:
        """Whether plane ``pid``'s counts so far make it a transient."""
        pr = self.params
        return self.through.get(pid, 0) >= pr.min_through and self.through[pid] > pr.ratio * self.returned.get(pid, 0)
