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

    def _near_samples(self, plane: Plane, x: FloatArray) -> NDArray[np.bool_]:
        """Whether each point (m, 3) on the plane lies within ``near`` of one of the points
        the plane's extent was grown by (in the plane)."""
        n = sum(s.shape[0] for s in plane.samples)
        hit = self._trees.get(plane.id)
        if hit is None or hit[0] != n or hit[1] is not plane.u:
            pts = np.concatenate(plane.samples)
            hit = (n, plane.u, cKDTree(np.column_stack((pts @ plane.u, pts @ plane.v))))
            self._trees[plane.id] = hit
        d, _ = hit[2].query(np.column_stack((x @ plane.u, x @ plane.v)), distance_upper_bound=self.params.near)
        return np.isfinite(d)

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
        found: list[int] = []
        for p in scans:
            segs = p.segs
            valid = np.flatnonzero(segs.beam_valid)[:: pr.beam_step]
            if valid.size == 0:
                continue
            T = self._knots.pose_at(segs.stamp) @ self._T_body_scanner[segs.scanner]
            a = segs.beam_angles[valid]
            r = segs.beam_ranges[valid].astype(np.float64)
            dirs = np.column_stack((np.cos(a), np.sin(a))) @ T[:3, :2].T  # (m, 3) world frame
            o = T[:3, 3]
            for pid in ids:
                plane = self._pmap.planes[pid]
                if not plane.active or not plane.samples:
                    continue
                s = float(plane.normal @ o) + plane.d  # the scanner's signed distance from the plane
                den = dirs @ plane.normal
                # the returns' signed distances, positive on the scanner's side
                behind = (s + r * den) * np.sign(s)
                steep = np.abs(den) > MIN_COS  # a grazing beam's crossing is ill-defined
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = -s / den
                cross = steep & (t > MIN_RANGE) & np.isfinite(t) & (behind < pr.margin)
                if not cross.any():
                    continue
                k = np.flatnonzero(cross)
                x = o + t[k, None] * dirs[k]
                inside = self._near_samples(plane, x)
                through = int(np.count_nonzero(inside & (behind[k] < -pr.margin)))
                on = int(np.count_nonzero(inside & (behind[k] >= -pr.margin)))
                self.through[pid] = self.through.get(pid, 0) + through
                self.returned[pid] = self.returned.get(pid, 0) + on
            for pid in ids:
                if pid not in found and self.through.get(pid, 0) >= pr.min_through \
                        and self.through[pid] > pr.ratio * self.returned.get(pid, 0):
                    found.append(pid)
        return found
