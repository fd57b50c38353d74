"""Association of line segments (world frame) to map planes.

A segment ``s`` with centroid ``c``, unit direction ``u`` and two virtual
points ``v1, v2`` (see ``observations``) lies on plane ``(n, d)`` when

* its direction lies in the plane: ``|n . u|`` is small against the
  direction's uncertainty (angle test),
* its points are near the plane: ``n . c + d`` is small against the combined
  uncertainty of the segment, the plane, the current pose estimate and the
  drift accumulated since the plane was last seen (distance test, which thus
  grows with the distance walked: the loop-closing search gate),
* it overlaps the plane's known extent (dilated), so that coplanar walls of
  different rooms are not confused.

The squared Mahalanobis distance combines the two tests; the best candidate
under the chi-square gate wins, and a segment with a second candidate also
under the gate on a *different* surface (offset differing by more than the
gate) is ambiguous and left unassociated.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from slam.frontend import assoc_scan_kernels as ask
from slam.frontend import kernels as fk
from slam.frontend.knots import KnotMirror
from slam.frontend.observations import ScanSegments
from slam.frontend.parallel_choice import (
    NONE,
    ChoiceParams,
    ChoiceScalars,
    choice_scalars,
    local_scalars,
)
from slam.frontend.pending import PendingScan
from slam.frontend.planemap import KIND_WALL, Plane, PlaneMap

FloatArray = NDArray[np.float64]
CHI2_2DOF_99 = 9.21


@dataclass(frozen=True)
class WorldSegments:
    """Segments placed in the world by the current trajectory estimate (k rows)."""

    centroid: FloatArray  # (k, 3)
    direction: FloatArray  # (k, 3) unit
    endpoints: FloatArray  # (k, 2, 3)
    sigma_centroid: FloatArray  # (k,) m
    sigma_direction: FloatArray  # (k,) rad
    range: FloatArray  # (k,) m, distance of the centroid from the scanner
    origin: FloatArray  # (3,) the scanner's position, world frame
    n_points: NDArray[np.int64] | None = None  # (k,) the segments' point counts (weights of the parallel choice)

    @property
    def n(self) -> int:
        return int(self.centroid.shape[0])


@dataclass(frozen=True)
class Gates:
    """Uncertainties added to every test, and the extent margin (``slam.params.gates``)."""

    sigma_pose: float  # m, current pose estimate at the segment
    sigma_rotation: float  # rad, in the angle test
    sigma_lever: float  # rad, rotation error times range in the distance test
    drift_rate: float  # m of offset uncertainty per m walked since the plane was seen
    drift_rate_vertical: float  # the same for floors and ceilings
    extent_margin_cells: int
    max_extra_cells: int  # cap of the drift-grown extent margin
    max_drift_sigma: float  # m, cap of the drift-grown offset uncertainty
    chi2: float  # gate of the combined test (CHI2_2DOF_99: 99 % of a chi-square with 2 dof)
    max_endpoint_distance: float  # m, hard cap on either endpoint's distance
    # planes tied parallel to a host wall (doors, boards: ``associate``'s ``children``): their
    # extent margin (cells, not grown with the drift; -1: as every plane's), and whether their
    # distance is taken to the plane through their extent's centre with the host's normal
    child_margin_cells: int
    child_host_normal: bool
    # the choice between parallel planes from the segments' own lines (``parallel_choice``); None:
    # the nearest candidate under the gates, as before
    choice: ChoiceParams | None

    def loosened(self, factor: float) -> Gates:
        # the choice's prior on the scan's offset loosens with the pose (its lever does not: loosened,
        # it let the demo's higher room's ceiling segments onto the corridor's ceiling in tracking)
        choice = None if self.choice is None else replace(self.choice, sigma_pose=self.choice.sigma_pose * factor)
        return Gates(
            self.sigma_pose * factor,
            self.sigma_rotation * factor,
            self.sigma_lever * factor,
            self.drift_rate,
            self.drift_rate_vertical,
            self.extent_margin_cells,
            self.max_extra_cells,
            self.max_drift_sigma,
            self.chi2,
            self.max_endpoint_distance * factor,
            self.child_margin_cells,
            self.child_host_normal,
            choice,
        )


def world_segments(virtual_world: FloatArray, endpoints_world: FloatArray, virtual_sigma: FloatArray,
                   point_sigma: float, n_points: NDArray[np.int64], origin_world: FloatArray) -> WorldSegments:
    """Summaries from the virtual points (k, 2, 3) and endpoints (k, 2, 3) already placed in the
    world; ``origin_world`` (3,) is the scanner's position (for the rotation's lever arm)."""
    # one compiled pass (slam.kernels.segment_summaries): the numpy formulation's
    # numbers to rounding
    c, u, sig_c, sig_dir, rng = fk.segment_summaries(
        np.ascontiguousarray(virtual_world, dtype=np.float64), np.ascontiguousarray(endpoints_world, dtype=np.float64),
        np.ascontiguousarray(virtual_sigma, dtype=np.float64), float(point_sigma),
        np.ascontiguousarray(n_points, dtype=np.int64), np.ascontiguousarray(origin_world, dtype=np.float64),
    )
    return WorldSegments(c, u, endpoints_world, sig_c, sig_dir, rng, origin_world, np.asarray(n_points, dtype=np.int64))


def associate(segs: WorldSegments, pmap: PlaneMap, odometer: float, gates: Gates,
              children: dict[int, int] | None = None) -> NDArray[np.int64]:
    """Plane id per segment, or -1 (no candidate, or ambiguous); see :func:`associate_scan`."""
    return associate_scan(segs, pmap, odometer, gates, children).ids


@dataclass(frozen=True)
class Association:
    """Per segment of a scan: its plane id, ``NONE`` (-1: left to the pool) or ``HELD`` (-2:
    ambiguous between parallel planes, neither associated nor pooled); and whether it may grow
    its plane's extent (an unambiguous choice)."""

    ids: NDArray[np.int64]
    grows: NDArray[np.bool_]


def associate_scan(segs: WorldSegments, pmap: PlaneMap, odometer: float, gates: Gates,
                   children: dict[int, int] | None = None) -> Association:
    """The segments of one scan (world frame) against the map: :class:`Association`.

    ``children`` maps the planes tied parallel to a host wall (a door set 1-2 cm into it, a board
    1-2 cm proud of it) to their host. A door's segment and the wall's next to it differ by those
    1-2 cm only, well inside the distance gate, so the nearer plane takes each; a child fitted a
    little tilted is then nearer the wall's (or a neighbouring board's) segments at one end of its
    extent, takes them, and tilts further. With ``gates.child_host_normal`` a child's distance is
    taken to the plane with its host's normal through the centre of its extent (the tie's model,
    which the child's own tilt cannot move), and with ``gates.child_margin_cells`` >= 0 its
    extent is dilated by that many cells only (a door's extent does not reach the next board).

    After the map's side in Python (:func:`_map_inputs`), one compiled call
    (``slam.frontend.assoc_scan_kernels.associate_summarised``): the per-pair gates (angle and
    distance, end points, facing side) and the extent cells of the pairs under them
    (``assoc_kernels.scan_pairs``), each such pair's extent test against the plane map's extent
    index (``extent_kernels.pairs_near``), then the choice and the nearest candidate
    (``assoc_kernels.decide``).
    """
    empty = Association(np.full(segs.n, NONE, dtype=np.int64), np.zeros(segs.n, dtype=bool))
    if segs.n == 0:
        return empty
    m = _map_inputs(pmap, gates, children)
    if m is None:
        return empty
    g = _gate_scalars(gates)
    choice = gates.choice
    weight_n = (np.ones(segs.n, dtype=np.int64) if segs.n_points is None else segs.n_points)
    out, grows = ask.associate_summarised(
        segs.centroid, segs.direction, segs.endpoints, segs.sigma_centroid, segs.sigma_direction, segs.range,
        segs.origin, weight_n, m.rows, m.horizontal, m.ids, m.child_rows, m.is_child, float(odometer),
        float(pmap.cell_size), g[0], g[1], pmap.extents.keys, pmap.extents.count, pmap.extents.box, choice is not None,
        choice is not None and choice.veto, choice is not None and choice.hold_past_child, m.hosts,
        m.hosts is not _NO_HOSTS, _SAME_NORMAL, g[2], m.walls, local_scalars(choice))
    return Association(out, grows)


@dataclass(frozen=True)
class _MapInputs:
    """The active planes as the association kernels take them (world frame): ``rows`` (P, 12)
    (``PlaneMap.active_rows``; a child's with its host's normal under ``child_host_normal``),
    ``horizontal`` (P,), ``ids`` (P,), the children's rows ``child_rows`` and ``is_child`` (P,), and
    the walls of the host test ``hosts`` (P,; ``_NO_HOSTS`` without it) and the walls that are no
    door or board ``walls`` (P,; the local step test's)."""

    rows: FloatArray
    horizontal: NDArray[np.bool_]
    ids: NDArray[np.int64]
    child_rows: NDArray[np.int64]
    is_child: NDArray[np.bool_]
    hosts: NDArray[np.bool_]
    walls: NDArray[np.bool_]


def _map_inputs(pmap: PlaneMap, gates: Gates, children: dict[int, int] | None) -> _MapInputs | None:
    """The map's side of :func:`associate_scan` (None without an active plane)."""
    active = pmap.active_planes()
    if not active:
        return None
    # the active planes' arrays (world frame): normal, offset, offset sigma, odometer when last
    # seen, in-plane axes u and v
    ids, id_arr, pos, is_wall = _active_index(active)
    rows, horizontal = pmap.active_rows()
    child_rows: list[int] = []
    if children:
        child_rows = [pos[c] for c in children if c in pos]
        if gates.child_host_normal:
            for j in child_rows:
                host = pmap.planes[children[ids[j]]]
                centre = pmap.cell_centres(ids[j])
                if not host.active or centre.shape[0] == 0:
                    continue
                n = host.normal if float(host.normal @ rows[j, 0:3]) >= 0.0 else -host.normal
                c = centre.mean(axis=0)
                c = c - (float(rows[j, 0:3] @ c) + rows[j, 3]) * rows[j, 0:3]  # onto the child's plane
                rows[j, 0:3] = n
                rows[j, 3] = -float(n @ c)
    is_child = np.zeros(rows.shape[0], dtype=np.bool_)
    is_child[child_rows] = True
    walls = is_wall.copy()
    walls[child_rows] = False
    hosts = _NO_HOSTS
    choice = gates.choice
    # the walls that may carry a door or board (not the children themselves, nor floors and
    # ceilings); not in the tracking's veto, whose poses are still the prediction's
    if choice is not None and choice.host_test and not choice.veto:
        hosts = walls
    return _MapInputs(rows, horizontal, id_arr, np.array(child_rows, dtype=np.int64), is_child, hosts, walls)


_SAME_NORMAL = float(np.cos(np.radians(2.0)))  # normals of one surface seen twice
_NO_HOSTS = np.zeros(0, dtype=bool)
# the index of the last active-plane list seen (``PlaneMap.active_planes`` keeps one list until a
# plane is added or merged): the list, its ids, as an array, row by id, and which are walls
_active_cache: list[tuple[list[Plane], list[int], NDArray[np.int64], dict[int, int], NDArray[np.bool_]]] = []


def _active_index(active: list[Plane]) -> tuple[list[int], NDArray[np.int64], dict[int, int], NDArray[np.bool_]]:
    """The active planes' ids (a list and an array), row by id and whether each is a wall."""
    if not _active_cache or _active_cache[0][0] is not active:
        ids = [p.id for p in active]
        _active_cache[:] = [(active, ids, np.asarray(ids, dtype=np.int64), {pid: j for j, pid in enumerate(ids)},
                             np.array([p.kind == KIND_WALL for p in active], dtype=bool))]
    return _active_cache[0][1:]


@lru_cache(maxsize=16)
def _gate_scalars(gates: Gates) -> tuple[tuple[float, float, float, int, int, int], tuple[float, float, float, float, float],
                                          ChoiceScalars]:
    """The gates' numbers as ``scan_pairs`` and ``decide`` take them (the choice's squares as
    ``parallel_choice.choose`` computed them)."""
    drift = (float(gates.drift_rate), float(gates.drift_rate_vertical), float(gates.max_drift_sigma),
             int(gates.extent_margin_cells), int(gates.max_extra_cells), int(gates.child_margin_cells))
    tests = (float(gates.sigma_pose), float(gates.sigma_rotation), float(gates.sigma_lever),
             float(gates.max_endpoint_distance), float(gates.chi2))
    return drift, tests, choice_scalars(gates.choice)


# the map's side of an association: the children asked (None: not asked) and the active planes' arrays
# (None: no active plane)
MapSide = tuple[dict[int, int] | None, _MapInputs | None]

# per scan, placed in the world: virtual points (k, 2, 3), end points (k, 2, 3), the scanner's
# position at the scan's stamp (4,, homogeneous)
ScanSummary = tuple[FloatArray, FloatArray, FloatArray]


class ScanAssociator:
    """Association of whole scans with the map (``pmap``), placed with the current knots
    (``knots``; ``T_body_scanner`` (4, 4) per scanner). ``point_sigma`` (m) is one point's
    range noise, segments of fewer than ``min_segment_points`` points stay unassociated;
    ``children`` gives the planes tied to a host wall (``associate``), asked only when the
    gates treat them apart. A segment's direction is its end points' (``line_direction`` off,
    the gates were tuned with it at the reference noise), else its fitted line's, through its
    two virtual points: a noisier scanner's end points turn a short segment by degrees (10 mm
    on 0.3 m: 2.7 deg, against the line's 1.2 deg), and the angle test then refuses most of
    them (demo, 10 mm: 80 % of the segments left unassociated failed it, and made duplicate
    planes that merged again)."""

    def __init__(self, pmap: PlaneMap, knots: KnotMirror, T_body_scanner: list[FloatArray], point_sigma: float,
                 min_segment_points: int, children: Callable[[], dict[int, int]], line_direction: bool = False) -> None:
        self._line_direction = line_direction
        self._pmap = pmap
        self._knots = knots
        self._T_body_scanner = T_body_scanner
        self._point_sigma = point_sigma
        self._min_segment_points = min_segment_points
        self._children = children
        self._gathered: dict[int, tuple[FloatArray, FloatArray, ScanSegments]] = {}

    def summaries(self, ps: list[PendingScan]) -> list[ScanSummary]:
        """Per scan, with the current knots (world frame): its segments' virtual points (k, 2, 3),
        their end points (k, 2, 3) and the scanner's position at the scan's stamp (4,,
        homogeneous). One ``place`` for all the scans: per point the same numbers as one call per
        scan (``place``'s arithmetic is element by element for two points or more, and a scan has
        four at least). The stamps' poses stay one ``pose_at`` each: for a single pose numpy
        takes another (matrix-vector) route through ``exp_coefficients``, with other last bits."""
        if not ps:
            return []
        # per scan its virtual points and end points (body frame) with their times, gathered once
        # (the tracking's pre-association and the observation place the same scans)
        gathered = []
        for p in ps:
            hit = self._gathered.get(p.serial)
            if hit is None or hit[2] is not p.segs:
                hit = self._gathered[p.serial] = self._gather(p)
            gathered.append(hit)
        if len(self._gathered) > 256:  # the scans of the last few knots are enough
            self._gathered = dict(list(self._gathered.items())[-128:])
        w = self._knots.place(np.concatenate([g[0] for g in gathered]), np.concatenate([g[1] for g in gathered]))
        out: list[ScanSummary] = []
        o = 0
        for p in ps:
            m = 2 * p.segs.n_segments
            out.append((w[o : o + m].reshape(-1, 2, 3), w[o + m : o + 2 * m].reshape(-1, 2, 3),
                        self._knots.pose_at(p.segs.stamp) @ self._T_body_scanner[p.segs.scanner][:, 3]))
            o += 2 * m
        return out

    @staticmethod
    def _gather(p: PendingScan) -> tuple[FloatArray, FloatArray, ScanSegments]:
        """The scan's virtual points (2k, 3) then end points (2k, 3), body frame, and their times
        (4k,)."""
        segs = p.segs
        ends_idx = np.stack((segs.offsets[:-1], segs.offsets[1:] - 1), axis=1).ravel()
        return (np.concatenate((segs.virtual_body.reshape(-1, 3), segs.points_body[ends_idx])),
                np.concatenate((segs.virtual_times.ravel(), segs.times[ends_idx])), segs)

    def map_side(self, gates: Gates) -> MapSide:
        """The map's side of :meth:`associate` under ``gates`` (the children asked, the active
        planes' arrays): computed once for scans associated while the map does not change (the
        tracking's pre-association), else per scan."""
        children = (self._children() if (gates.child_margin_cells >= 0 or gates.child_host_normal or gates.choice is not None)
                    else None)
        return children, _map_inputs(self._pmap, gates, children)

    def associate(self, p: PendingScan, gates: Gates, summary: ScanSummary, side: MapSide | None = None) -> Association:
        """The scan's :class:`Association` under ``gates``, from its ``summary``, with the map's
        side ``side`` (:meth:`map_side` of the same gates and an unchanged map; None: asked now)."""
        v_world, e_world, origin = summary
        children, m = self.map_side(gates) if side is None else side
        if self._line_direction:  # the segments' summaries in Python, their directions the lines'
            ws = world_segments(v_world, e_world, p.segs.virtual_sigma, self._point_sigma, p.segs.n_points, origin[:3])
            d = v_world[:, 1] - v_world[:, 0]
            d /= np.maximum(np.linalg.norm(d, axis=1), 1e-12)[:, None]
            a = associate_scan(replace(ws, direction=d), self._pmap, self._knots.odometer, gates, children)
            short = p.segs.n_points < self._min_segment_points
            a.ids[short] = NONE
            a.grows[short] = False
            return a
        # one compiled call: the summaries, the gates, the extents and the choice
        segs = p.segs
        if m is None or not segs.n_segments:
            return Association(np.full(segs.n_segments, NONE, dtype=np.int64), np.zeros(segs.n_segments, dtype=bool))
        g = _gate_scalars(gates)
        choice = gates.choice
        ext = self._pmap.extents
        ids, grows = ask.associate_segments(
            np.ascontiguousarray(v_world, dtype=np.float64), np.ascontiguousarray(e_world, dtype=np.float64),
            np.ascontiguousarray(segs.virtual_sigma, dtype=np.float64), float(self._point_sigma),
            np.ascontiguousarray(segs.n_points, dtype=np.int64), np.ascontiguousarray(origin[:3], dtype=np.float64),
            int(self._min_segment_points), m.rows, m.horizontal, m.ids, m.child_rows, m.is_child,
            float(self._knots.odometer), float(self._pmap.cell_size), g[0], g[1], ext.keys, ext.count, ext.box,
            choice is not None, choice is not None and choice.veto, choice is not None and choice.hold_past_child,
            m.hosts, m.hosts is not _NO_HOSTS, _SAME_NORMAL, g[2], m.walls, local_scalars(choice))
        return Association(ids, grows)
