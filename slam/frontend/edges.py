"""Door and board edges: where a scanline steps from a wall onto a door set into it (or a board on
it), the break between the two segments lies on the door's edge.

Along a corridor whose end walls are out of range every plane in view is parallel to the walking
direction, so the line-to-plane model leaves that direction to the IMU. The vertical edges of
doors and boards observe it. Each edge is modelled as a plane: vertical, perpendicular to the
host wall, through the edge (an *edge plane*, in the back end an ``OrientedPlane3`` tied
perpendicular to its wall). A break point observes it with the point-to-plane residual, which is
the break's offset along the wall from the edge.

A break is where a scanline steps between a wall and a surface parallel to it, a ``min_step`` to
``max_step`` step in front of or behind it (a door set in, a board standing proud): neighbouring
segments in beam order (one short segment between them, a door's sloped frame, may be skipped),
one associated with the wall, the other, associated or not, parallel to it at that step (measured
between the two segments, so a pose error does not change it), their boundary points within
``max_gap``. The edge lies where the surface nearer the scanner ends (beyond the edge the lower
surface is shadowed or seen on the step's face, by an amount that depends on the view, while the
higher one ends at the edge from every side): between the crossings of that surface's fitted
line by its last beam and by the next beam, which misses it. The midpoint of the two crossings
(``point = "bracket"``) should be unbiased, uniform within half the beam spacing there, but on the
office walk it biased the walking direction (with a perfect IMU, 25-45 mm lost along a door-poor
stretch; none with ``"midpoint"``, the midpoint of the gap between the two segments' boundary
points, the pipeline's default). The surface's last sample itself (``"higher"``) lies short of
the edge by half a spacing on average and carries the range noise along the wall at
1 / tan(incidence). The beam must meet the wall at least
``min_incidence_deg`` from grazing. The point's sigma along the wall is the local beam spacing's
uniform spread (``spacing / sqrt(12)``) plus ``sigma``. The door's own plane is not needed, so a
door yields edges from the first time it is passed.

Edges are keyed by (wall, step sign, side): the step sign tells a recessed door from a board
standing proud, ``side`` on which side of the edge (along the wall direction ``n_e``) the step
lies, so a door has one edge per side. A new edge is made from pending breaks of one key whose
offsets along the wall agree within ``cluster_width`` and that span ``min_height_span`` in height
or all come from nearly horizontal scanlines: vertical edges. Breaks on a door's top edge or a
board's bottom edge lie at one height; they spread along the wall, but a scanline nearly parallel
to such an edge can put a few of them close together.
"""

from __future__ import annotations

import itertools
import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam.frontend.observations import ScanSegments

FloatArray = NDArray[np.float64]
EDGE_ID_BASE = 1_000_000  # back-end plane ids of edge planes start here; map planes stay below


@dataclass(frozen=True)
class EdgeParams:
    """Break detection, clustering, association and ties of door/board edges (metres, seconds;
    ``slam.params.edge_params``, see ``slam.config.EdgeSection``)."""

    max_gap: float
    min_incidence_deg: float
    sigma: float
    cluster_width: float
    min_points: int
    min_scans: int
    gate: float
    tracking_gate: float  # the gate of the tracker's pre-association
    window: float
    merge_distance: float
    link_sigma: float  # m and rad, the tie between merged edges
    min_step: float
    max_step: float
    step_tolerance: float
    max_skipped_points: int
    min_height_span: float
    point: str
    height_margin: float
    flat_slope: float
    perpendicular_sigma: float  # rad, the edge plane's tie across its wall
    inline: bool  # also steps inside wall segments
    inline_window: int
    inline_z: float
    min_segment_points: int  # a wall segment shorter than this yields no break (the front end's limit)


@dataclass(frozen=True)
class Break:
    """One break point: ``point_body`` (3,) in the body frame at ``time``, its offset ``u`` along the
    wall (world, ``n_e . x``), sigma along the wall, the (raw) wall id, the step's sign (+1: in
    front of the wall along its normal) and side (+1: the step lies along ``+n_e``). ``flat``: the
    scanline runs nearly horizontally across the wall there, so it can only cross a vertical edge.
    A record, never changed (:meth:`EdgeMap.cluster` remembers breaks that made no edge)."""

    host: int
    step: int
    side: int
    u: float
    point_body: FloatArray
    point_world: FloatArray
    time: float
    sigma: float
    serial: int
    flat: bool = False


@dataclass
class Edge:
    """An edge plane: ``normal . x + d = 0`` (world), ``normal`` along the wall (``n_e``)."""

    id: int
    host: int
    step: int
    side: int
    normal: FloatArray
    d: float
    n_obs: int = 0
    last_seen_time: float = 0.0
    merged_into: int | None = None
    z_range: tuple[float, float] = (-np.inf, np.inf)

    @property
    def u(self) -> float:
        return -self.d


def along_wall(normal_wall: FloatArray) -> FloatArray:
    """The horizontal unit direction in a (vertical) wall: ``up x n_wall`` normalised (world)."""
    x, y = float(normal_wall[0]), float(normal_wall[1])  # up x n = (-n_y, n_x, 0)
    return np.array([-y, x, 0.0]) / max(math.hypot(x, y), 1e-12)


def break_pairs(
    first_beam: NDArray[np.int64], n_points: NDArray[np.int64], plane_ids: NDArray[np.int64],
    is_wall: Callable[[int], bool], max_skipped_points: int,
) -> list[tuple[int, int]]:
    """Neighbouring segments of one scan in beam order, ``(j_wall, j_other)``, where ``j_wall`` is
    associated with a wall; one segment of at most ``max_skipped_points`` points between them may
    be skipped. Two neighbours on the same wall give both orders: a door set 1 cm in can pass the
    wall's association gates, and only the step between the two segments tells it (the caller
    keeps the order whose ``j_wall`` lies nearer the plane). Geometry is checked by the caller."""
    order = np.argsort(first_beam, kind="stable").tolist()
    n_pts, pids = np.asarray(n_points).tolist(), np.asarray(plane_ids).tolist()
    wall = {pid: is_wall(pid) for pid in set(pids) if pid >= 0}
    out = []
    for i, a in enumerate(order):
        for b in order[i + 1 : i + 3]:
            if b != order[i + 1] and n_pts[order[i + 1]] > max_skipped_points:
                break
            pa, pb = pids[a], pids[b]
            if pa >= 0 and wall[pa]:
                out.append((a, b))
            if pb >= 0 and wall[pb]:
                out.append((b, a))
    return out


def step_of(normal_wall: FloatArray, wall_world: FloatArray, other_world: FloatArray) -> tuple[float, float]:
    """Step (m) of the other segment's two virtual points (2, 3) from the wall segment's (2, 3),
    along the wall normal (world): the difference cancels a pose offset common to both."""
    base = float(np.mean(wall_world @ normal_wall))
    s = other_world @ normal_wall - base
    return float(s[0]), float(s[1])


def ray_on_line(angle: float, centroid: FloatArray, direction: FloatArray) -> FloatArray | None:
    """Where the beam at ``angle`` (scanner frame, from the origin) meets the line through
    ``centroid`` along ``direction`` (2D, scanner frame); None when it runs (nearly) parallel
    to the line or meets it behind the scanner."""
    r = np.array([np.cos(angle), np.sin(angle)])
    det = float(direction[0] * r[1] - direction[1] * r[0])
    if abs(det) < 1e-6:
        return None
    lam = float(direction[0] * centroid[1] - direction[1] * centroid[0]) / det
    return None if lam <= 0.0 else lam * r


def surface_end(k_end: int, step: int, angles: FloatArray, ranges: FloatArray, valid: NDArray[np.bool_],
                centroid: FloatArray, direction: FloatArray, tolerance: float, max_beams: int = 8) -> int:
    """The last beam, from ``k_end`` on in direction ``step`` (+1 / -1), whose return still lies
    on the surface's fitted 2D line (scanner frame) within ``tolerance`` (m): a segmenter may stop
    a few beams short of the surface's edge (its windows, a mixed pixel), and a beam that still
    hits the surface must not be taken for the first one past the edge. At most ``max_beams``."""
    normal = np.array([-direction[1], direction[0]])
    k = k_end
    for _ in range(max_beams):
        j = k + step
        if not 0 <= j < angles.shape[0] or not valid[j]:
            break
        p = ranges[j] * np.array([np.cos(angles[j]), np.sin(angles[j])])
        if abs(float(normal @ (p - centroid))) > tolerance:
            break
        k = j
    return k


def recess_beyond(k_end: int, step: int, angles: FloatArray, ranges: FloatArray, valid: NDArray[np.bool_],
                  centroid: FloatArray, direction: FloatArray, min_step: float, max_step: float,
                  max_gap: float, n_beams: int = 8, min_returns: int = 3) -> tuple[int, int, float] | None:
    """Whether the returns just past a wall segment's end (beam ``k_end``, walking ``step``) lie a
    door's recess behind the wall's fitted 2D line (scanner frame): a door seen obliquely is
    often left unsegmented, so there is no segment to pair the wall with, yet the wall still ends
    at the door's edge. Of the next ``n_beams`` beams, at least ``min_returns`` valid returns must
    lie ``min_step``-``max_step`` behind the line (away from the scanner; their median too), the
    first within ``max_gap`` of the wall's last return. Returns (the first valid beam past the
    end, the last beam inside the recess, the median depth in m), or None."""
    nx, ny = -float(direction[1]), float(direction[0])  # the line's normal
    cx, cy = float(centroid[0]), float(centroid[1])
    away = 1.0 if nx * cx + ny * cy > 0.0 else -1.0
    r_end, a_end = float(ranges[k_end]), float(angles[k_end])
    lx, ly = r_end * math.cos(a_end), r_end * math.sin(a_end)
    depths: list[float] = []
    beams: list[int] = []
    first = None
    for i in range(1, n_beams + 1):
        j = k_end + i * step
        if not 0 <= j < angles.shape[0]:
            break
        if not valid[j]:
            continue
        r_j, a_j = float(ranges[j]), float(angles[j])
        qx, qy = r_j * math.cos(a_j), r_j * math.sin(a_j)
        if first is None:
            if math.hypot(qx - lx, qy - ly) > max_gap:
                return None
            first = j
        depths.append(away * (nx * (qx - cx) + ny * (qy - cy)))
        beams.append(j)
    if first is None or len(depths) < min_returns:
        return None
    inside = [i for i, d in enumerate(depths) if min_step <= d <= max_step]
    median = statistics.median(depths)
    if len(inside) < min_returns or not min_step <= median <= max_step:
        return None
    return first, beams[inside[-1]], median


def segment_owner(segs: ScanSegments) -> NDArray[np.int64]:
    """Per beam of the scan, the segment whose beam range holds it (-1: none)."""
    owner = np.full(segs.beam_angles.shape[0], -1, dtype=np.int64)
    for j in range(segs.n_segments):
        owner[segs.first_beam[j] : segs.last_beam[j] + 1] = j
    return owner


def segment_end(segs: ScanSegments, j: int, direction: int) -> int:
    """The beam at segment ``j``'s end in ``direction`` (+1: its last beam, -1: its first)."""
    return int(segs.last_beam[j]) if direction == 1 else int(segs.first_beam[j])


def next_to_segment(owner: NDArray[np.int64], k_end: int, direction: int) -> bool:
    """Whether another segment starts within three beams past beam ``k_end`` in ``direction``
    (then the segment pairs, not the recess test, handle that end)."""
    near = owner[max(0, min(k_end + direction, k_end + 3 * direction)): max(k_end + direction, k_end + 3 * direction) + 1]
    return bool(np.any(near >= 0))


def segment_returns(segs: ScanSegments, j: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Segment ``j``'s valid beams within its beam range and their returns (n, 2), scanner frame."""
    beams = np.flatnonzero(segs.beam_valid[segs.first_beam[j] : segs.last_beam[j] + 1]) + segs.first_beam[j]
    a, r = segs.beam_angles[beams], segs.beam_ranges[beams]
    return beams, np.column_stack((r * np.cos(a), r * np.sin(a)))


def steps_within(points_xy: FloatArray, centroid: FloatArray, direction: FloatArray, sigma: float,
                 window: int, min_step: float, max_step: float, min_z: float) -> list[tuple[int, float]]:
    """Steps inside one segment: where its points (n, 2, beam order, scanner frame) switch between
    two parallel lines ``min_step``-``max_step`` apart, as at the edge of a 5 mm poster that the
    segmenter left in its wall's segment. Their offsets from the fitted line (``centroid``,
    ``direction``) are compared over ``window`` points either side of every split; a split whose
    difference of means is at least ``min_z`` standard errors (point noise ``sigma``) and the
    largest within ``window`` points is a step. Returns (index of the last point before the step,
    the offset after minus before along the line's normal ``(-u_y, u_x)`` in m), by index."""
    n = points_xy.shape[0]
    if n < 2 * window:
        return []
    normal = np.array([-direction[1], direction[0]])
    r = (points_xy - centroid) @ normal
    c = np.concatenate(([0.0], np.cumsum(r)))
    k = np.arange(window - 1, n - window)  # last index of the left window
    before = (c[k + 1] - c[k + 1 - window]) / window
    after = (c[k + 1 + window] - c[k + 1]) / window
    depth = after - before
    z = np.abs(depth) / (sigma * np.sqrt(2.0 / window))
    ok = (np.abs(depth) >= min_step) & (np.abs(depth) <= max_step)
    out: list[tuple[int, float]] = []
    taken = np.zeros(k.shape[0], dtype=bool)
    for i in np.argsort(-z, kind="stable"):
        if z[i] < min_z:
            break
        if taken[i]:
            continue
        # the largest difference within the window decides: a step outside the bounds there is
        # not re-found as a smaller one beside it
        taken[max(0, i - window) : i + window + 1] = True
        if ok[i]:
            out.append(_refine_split(r, int(k[i]), window))
    return sorted(out)


def _refine_split(r: FloatArray, k0: int, window: int) -> tuple[int, float]:
    """The maximum-likelihood split of offsets ``r`` into two constant levels within ``window``
    points of ``k0`` (the difference of window means peaks broadly, a few points off at a 5 mm
    step in 3 mm noise): (last index before the split, offset after minus before)."""
    lo, hi = max(0, k0 + 1 - 2 * window), min(r.shape[0], k0 + 1 + 2 * window)
    seg = r[lo:hi]
    c = np.cumsum(seg)
    n = seg.shape[0]
    n_left = np.arange(1, n)
    mean_left = c[:-1] / n_left
    mean_right = (c[-1] - c[:-1]) / (n - n_left)
    gain = n_left * (n - n_left) / n * (mean_right - mean_left) ** 2
    split = lo + n_left - 1  # the last index before each candidate split
    # within the window of k0, with half a window of points on either side for the caller
    near = (np.abs(split - k0) <= window) & (split + 1 >= window // 2) & (r.shape[0] - split - 1 >= window // 2)
    i = int(np.argmax(np.where(near, gain, -1.0)))
    k = lo + i
    w_lo, w_hi = max(0, k + 1 - window), min(r.shape[0], k + 1 + window)
    return k, float(np.mean(r[k + 1 : w_hi]) - np.mean(r[w_lo : k + 1]))


def bracket_point(angle_end: float, angle_next: float, centroid: FloatArray,
                  direction: FloatArray) -> tuple[FloatArray, float] | None:
    """The edge of a surface (its fitted 2D line, scanner frame) whose last beam is ``angle_end``
    while the next beam ``angle_next`` misses it: the edge lies between the two beams' crossings
    of the line, so their midpoint is an unbiased estimate, uniform within +-spacing / 2.
    Returns (midpoint (2,), spacing) in the scanner frame, or None."""
    a = ray_on_line(angle_end, centroid, direction)
    b = ray_on_line(angle_next, centroid, direction)
    if a is None or b is None:
        return None
    return 0.5 * (a + b), float(np.linalg.norm(b - a))


def break_sigma(spacing: float, sigma: float) -> float:
    """Along-wall sigma of an edge point whose surface's points lie ``spacing`` apart there (m)."""
    return math.sqrt(sigma**2 + spacing**2 / 12.0)  # correctly rounded, as np.sqrt


def is_flat(direction_world: FloatArray, normal_wall: FloatArray, slope: float) -> bool:
    """Whether a scanline direction runs across the wall with a vertical slope below ``slope``."""
    along = abs(float(direction_world @ along_wall(normal_wall)))
    return abs(float(direction_world[2])) < slope * along


def steep_enough(origin_world: FloatArray, point_world: FloatArray, normal_wall: FloatArray, min_deg: float) -> bool:
    """Whether the beam from ``origin_world`` to ``point_world`` meets the wall at least ``min_deg``
    from grazing."""
    r = point_world - origin_world
    s = abs(float(r @ normal_wall)) / max(float(np.linalg.norm(r)), 1e-12)
    return s >= np.sin(np.radians(min_deg))


@dataclass
class EdgeMap:
    """Edges, pending breaks and their association; plane ids are resolved through ``resolve``
    (merged map planes) before comparing keys."""

    params: EdgeParams
    resolve: Callable[[int], int]
    edges: dict[int, Edge] = field(default_factory=dict)
    pending: list[Break] = field(default_factory=list)
    _next: int = EDGE_ID_BASE
    # what ``resolve`` gives changes only when this does (e.g. the plane map's merge count): with
    # it, :meth:`match` keeps an index of the edges by key instead of testing every edge
    generation: Callable[[], int] | None = None
    _index: tuple[tuple[int, int], dict[tuple[int, int, int], list[Edge]]] | None = None
    # per key, the pending breaks (in order) that made no edge at the last :meth:`cluster`
    _failed: dict[tuple[int, int, int], list[Break]] = field(default_factory=dict)

    def key(self, host: int, step: int, side: int) -> tuple[int, int, int]:
        return self.resolve(host), step, side

    def active(self) -> list[Edge]:
        return [e for e in self.edges.values() if e.merged_into is None]

    def root(self, edge_id: int) -> int:
        while self.edges[edge_id].merged_into is not None:
            nxt = self.edges[edge_id].merged_into
            assert nxt is not None
            edge_id = nxt
        return edge_id

    def match(self, b: Break, gate: float | None = None) -> Edge | None:
        """The active edge of ``b``'s key nearest along the wall, within ``gate`` (default: the
        parameters' gate) and, unless ``b`` is flat, within ``height_margin`` of the heights the
        edge was made from."""
        gate = self.params.gate if gate is None else gate
        key = self.key(b.host, b.step, b.side)
        z, margin = float(b.point_world[2]), self.params.height_margin
        best: tuple[float, Edge] | None = None
        # the index holds the edges by their current keys; without it every edge is a candidate
        indexed = self.generation is not None
        for e in self._candidates(key):
            if e.merged_into is not None or (not indexed and self.key(e.host, e.step, e.side) != key):
                continue
            # beyond the heights its breaks were seen at, a break may lie on the door's top edge,
            # anywhere along it; a flat scanline can only cross a vertical edge
            if not b.flat and not e.z_range[0] - margin <= z <= e.z_range[1] + margin:
                continue
            dist = abs(float(e.normal @ b.point_world) + e.d)
            if dist <= gate and (best is None or dist < best[0]):
                best = (dist, e)
        return None if best is None else best[1]

    def _candidates(self, key: tuple[int, int, int]) -> list[Edge]:
        """The edges that may have ``key`` (all of them without ``generation``)."""
        if self.generation is None:
            return list(self.edges.values())
        state = (self.generation(), len(self.edges))
        if self._index is not None and self._index[0][0] == state[0] and self._index[0][1] < state[1]:
            # only edges added since (the dict keeps their order): each to the end of its key's list
            index = self._index[1]
            for e in itertools.islice(self.edges.values(), self._index[0][1], None):
                index.setdefault(self.key(e.host, e.step, e.side), []).append(e)
            self._index = (state, index)
        elif self._index is None or self._index[0] != state:
            index = {}
            for e in self.edges.values():
                # a merged edge stays merged (match passes over it): an hour's walk merges half its edges
                if e.merged_into is None:
                    index.setdefault(self.key(e.host, e.step, e.side), []).append(e)
            self._index = (state, index)
        return self._index[1].get(key, [])

    def expire(self, now: float) -> None:
        self.pending = [b for b in self.pending if now - b.time <= self.params.window]

    def cluster(self) -> list[tuple[list[Break], float]]:
        """New edges from the pending breaks: groups of one key within ``cluster_width`` along the
        wall with ``min_points`` breaks from ``min_scans`` scans; returns (members, median u) and
        removes the members from the pending list."""
        p = self.params
        groups: dict[tuple[int, int, int], list[Break]] = {}
        resolved: dict[int, int] = {}
        for b in self.pending:
            host = resolved.get(b.host)
            if host is None:
                host = resolved[b.host] = self.resolve(b.host)
            groups.setdefault((host, b.step, b.side), []).append(b)
        found: list[tuple[list[Break], float]] = []
        taken: set[int] = set()
        failed: dict[tuple[int, int, int], list[Break]] = {}
        for key, members in groups.items():
            if len(members) < p.min_points:
                continue
            # a group of the very breaks that made no edge last time makes none now
            last = self._failed.get(key)
            if last is not None and len(last) == len(members) and all(a is b for a, b in zip(last, members, strict=True)):
                failed[key] = members
                continue
            failed[key] = members
            u = np.array([b.u for b in members])
            order = np.argsort(u)
            us = u[order]
            hi = np.searchsorted(us, us + p.cluster_width, side="right")
            counts = hi - np.arange(us.size)
            i = int(np.argmax(counts))
            if counts[i] < p.min_points:
                continue
            group = [members[int(k)] for k in order[i : hi[i]]]
            if len({b.serial for b in group}) < p.min_scans:
                continue
            z = [float(b.point_world[2]) for b in group]
            if max(z) - min(z) < p.min_height_span and not all(b.flat for b in group):
                continue
            found.append((group, float(np.median([b.u for b in group]))))
            taken.update(id(b) for b in group)
            del failed[key]
        self._failed = failed
        if taken:
            self.pending = [b for b in self.pending if id(b) not in taken]
        return found

    def add(self, host: int, step: int, side: int, normal: FloatArray, u: float, time: float,
            z_range: tuple[float, float] = (-np.inf, np.inf)) -> Edge:
        e = Edge(self._next, host, step, side, normal.copy(), -u, last_seen_time=time, z_range=z_range)
        self.edges[e.id] = e
        self._next += 1
        return e

    def duplicates(self) -> list[tuple[Edge, Edge]]:
        """Pairs (keep, drop) of active edges with the same resolved key within ``merge_distance``
        along the wall (the same edge created twice, e.g. before its walls merged, or again after a loop)."""
        by_key: dict[tuple[int, int, int], list[Edge]] = {}
        for e in self.active():
            by_key.setdefault(self.key(e.host, e.step, e.side), []).append(e)
        out = []
        for group in by_key.values():
            if len(group) < 2:
                continue
            group.sort(key=lambda e: (-e.n_obs, e.id))
            keep = group[0]
            for other in group[1:]:
                if abs(other.u - keep.u) <= self.params.merge_distance and float(other.normal @ keep.normal) > 0.99:
                    out.append((keep, other))
        return out
