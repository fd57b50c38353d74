"""The map of planes seen by the front end, in the world frame.

A plane is ``n . x + d = 0`` (unit normal ``n``). Its *extent* is the set of
cells (``cell_size`` squares) of its own 2D coordinate frame ``(u, v)`` that
observed points have fallen into; association requires a segment to overlap
the (dilated) extent, so that coplanar walls of different rooms are not
confused. The back end owns the estimates; the front end copies them in after
each update (``set_estimates``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam.frontend import extent_kernels as xk
from slam.frontend import kernels as fk
from slam.frontend.extent_index import ExtentIndex

FloatArray = NDArray[np.float64]

KIND_OTHER, KIND_WALL, KIND_FLOOR, KIND_CEILING = 0, 1, 2, 3
HORIZONTAL_KINDS = (KIND_FLOOR, KIND_CEILING)
KIND_NAMES = {KIND_OTHER: "other", KIND_WALL: "wall", KIND_FLOOR: "floor", KIND_CEILING: "ceiling"}


def plane_basis(normal: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors spanning the plane: ``u`` horizontal where possible, ``v = n x u``."""
    n = normal / np.linalg.norm(normal)
    ref = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(ref, n)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    return u, v


def merge_tolerance(merge_distance: float, drift_rate: float, walked: float, coobserved: bool,
                    coobserved_max: float) -> float:
    """Largest offset difference (m) at which two parallel, touching planes merge: ``merge_distance``
    plus the drift possible over ``walked`` m, but at most ``coobserved_max`` when the two were seen
    together (a cabinet's front seen with the wall behind it is another surface, however far the
    walk has gone since)."""
    tol = merge_distance + drift_rate * walked
    return min(tol, max(coobserved_max, merge_distance)) if coobserved else tol


def is_other_face(wall_normal: FloatArray, wall_d: float, normal: FloatArray, points_world: FloatArray,
                  cos_min: float, thickness: tuple[float, float]) -> bool:
    """Whether a plane (unit ``normal``, its points (m, 3), world frame) is the other face of the
    wall ``wall_normal . x + wall_d = 0``: facing the opposite way (normals facing their
    observers, within ``acos(cos_min)``) and every point ``thickness`` (min, max, m) behind the
    wall's face."""
    if float(wall_normal @ normal) > -cos_min:
        return False
    behind = -(points_world @ wall_normal + wall_d)
    return bool(behind.min() >= thickness[0] and behind.max() <= thickness[1])


def classify(normal: FloatArray, d: float, body_z_world: float, vertical_tol: float) -> int:
    """Wall (normal within ``vertical_tol`` rad of horizontal), floor/ceiling (normal near vertical), else other."""
    nz = abs(float(normal[2]))
    if nz < np.sin(vertical_tol):
        return KIND_WALL
    if nz > np.cos(vertical_tol):
        z_plane = -d / normal[2]
        return KIND_FLOOR if z_plane < body_z_world else KIND_CEILING
    return KIND_OTHER


@dataclass
class Plane:
    """One map plane: estimate, extent, bookkeeping."""

    id: int
    normal: FloatArray
    d: float
    kind: int
    u: FloatArray
    v: FloatArray
    cells: set[tuple[int, int]] = field(default_factory=set)
    n_segments: int = 0
    last_seen_time: float = 0.0
    last_seen_odometer: float = 0.0
    first_seen_odometer: float = 0.0
    sigma_offset: float = 0.005
    active: bool = True
    merged_into: int = -1
    transient: bool = False  # taken out of the map as a thing that moved (``frontend.transients``)
    # while young (``PlaneMap.samples_until`` segments): the points its extent was grown by (world frame)
    samples: list[FloatArray] = field(default_factory=list)
    # time buckets (``PlaneMap.bucket`` s) in which the plane had a segment: two planes seen in one
    # bucket were measured from (nearly) one pose, without drift between them
    seen_buckets: set[int] = field(default_factory=set)
    # the extent's extreme points (world frame, up to 4: least and most u, least and most v),
    # for the exported outline at the points' precision rather than the cells'
    extremes: FloatArray | None = None


class PlaneMap:
    """Planes with extents; ids are stable (a merged plane stays, inactive, pointing to its survivor)."""

    def __init__(self, cell_size: float = 0.25, bucket: float = 0.5, samples_until: int = 0) -> None:
        self.cell_size = cell_size
        self.bucket = bucket
        self.samples_until = samples_until  # planes with fewer segments keep their extent's points
        self.planes: list[Plane] = []
        self.merges = 0  # merges so far: what :meth:`resolve` gives changes only with it
        self._active: list[Plane] | None = None  # the active planes, kept until a plane is added or merged
        self._version = 0  # bumped by every change of a plane's estimate, a new plane and a merge
        self._rows: tuple[int, FloatArray, NDArray[np.bool_]] | None = None
        # per plane: its cell set, their count, its frame (u, v, normal, d), the cells' centres in
        # the plane's (u, v) frame (+0.5) and in the world
        self._centres: dict[int, tuple[set[tuple[int, int]], int, FloatArray, FloatArray, FloatArray]] = {}
        # every plane's extent cells in one compiled index (the dilated-extent tests), grown with
        # the planes' cell sets (``extend``, ``observe_segments``: the only places they grow)
        self.extents = ExtentIndex()
        self._hosts: set[int] = set()  # the planes another plane was merged into (``has_merged``)

    def __len__(self) -> int:
        return len(self.planes)

    def add(self, normal: FloatArray, d: float, kind: int, time: float, odometer: float) -> Plane:
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        u, v = plane_basis(n)
        p = Plane(len(self.planes), n, float(d), kind, u, v, last_seen_time=time, last_seen_odometer=odometer,
                  first_seen_odometer=odometer, seen_buckets={self._bucket_of(time)})
        self.planes.append(p)
        self.extents.add_plane(p.id)
        self._active = None
        self._version += 1
        return p

    def _bucket_of(self, time: float) -> int:
        return math.floor(time / self.bucket)

    def seen(self, pid: int, time: float, odometer: float) -> None:
        """Record a sighting of plane ``pid`` (a segment associated with it) at ``time`` (s)."""
        p = self.planes[pid]
        p.last_seen_time = time
        p.last_seen_odometer = odometer
        p.seen_buckets.add(self._bucket_of(time))

    def coobserved(self, a: int, b: int) -> bool:
        """Whether planes ``a`` and ``b`` were seen in one time bucket (so from nearly one pose:
        their relative offset then carries no drift)."""
        sa, sb = self.planes[a].seen_buckets, self.planes[b].seen_buckets
        return not (sa.isdisjoint(sb) if len(sa) <= len(sb) else sb.isdisjoint(sa))

    def resolve(self, pid: int) -> int:
        """Follow merges to the surviving plane id."""
        while self.planes[pid].merged_into >= 0:
            pid = self.planes[pid].merged_into
        return pid

    def active_planes(self) -> list[Plane]:
        """The planes not merged into another, by id (a shared list: do not modify)."""
        if self._active is None:
            self._active = [p for p in self.planes if p.active]
        return self._active

    def active_rows(self) -> tuple[FloatArray, NDArray[np.bool_]]:
        """One row per active plane (world frame): normal (3), offset, offset sigma, odometer when
        last seen, in-plane axes u (3) and v (3); and whether each is a floor or ceiling. The
        estimates' part is kept until an estimate changes; the odometers are read fresh."""
        active = self.active_planes()
        if self._rows is None or self._rows[0] != self._version:
            rows = np.array([[*p.normal.tolist(), p.d, p.sigma_offset, 0.0, *p.u.tolist(), *p.v.tolist()]
                             for p in active]).reshape(-1, 12)
            self._rows = (self._version, rows, np.array([p.kind in HORIZONTAL_KINDS for p in active], dtype=bool))
        rows = self._rows[1].copy()
        rows[:, 5] = [p.last_seen_odometer for p in active]
        return rows, self._rows[2]

    def active_ids(self) -> NDArray[np.int64]:
        return np.array([p.id for p in self.active_planes()], dtype=np.int64)

    def arrays(self, ids: NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
        """Normals (m, 3) and offsets (m,) of the given planes."""
        if ids.size == 0:
            return np.empty((0, 3)), np.empty(0)
        return (
            np.array([self.planes[i].normal for i in ids]),
            np.array([self.planes[i].d for i in ids]),
        )

    def cells_of(self, pid: int, points_world: FloatArray) -> NDArray[np.int64]:
        """Cell indices (m, 2) of points (m, 3), world frame, in the plane's (u, v) frame:
        ``floor((p . u, p . v) / cell_size)`` (compiled, slam.kernels.plane_cells)."""
        p = self.planes[pid]
        return fk.plane_cells(np.ascontiguousarray(points_world, dtype=np.float64), np.ascontiguousarray(p.u, dtype=np.float64),
                              np.ascontiguousarray(p.v, dtype=np.float64), float(self.cell_size))

    def extend(self, pid: int, points_world: FloatArray) -> None:
        """Add the cells of ``points_world`` (m, 3), world frame, to the plane's extent."""
        cells = self.cells_of(pid, points_world)
        # the set takes the duplicates (np.unique over rows costs ten times more)
        p = self.planes[pid]
        p.cells.update(zip(cells[:, 0].tolist(), cells[:, 1].tolist(), strict=True))
        self.extents.insert_one(pid, cells)
        if p.n_segments < self.samples_until:
            p.samples.append(np.array(points_world, dtype=np.float64))
        self._grow_extremes(p, np.asarray(points_world, dtype=np.float64))

    def observe_segments(self, pids: list[int], points_world: FloatArray, bounds: NDArray[np.int64],
                         grows: NDArray[np.bool_], time: float, odometer: float) -> None:
        """A scan's segments observe their planes ``pids`` in order: segment s (rows ``bounds[s]``
        to ``bounds[s + 1] - 1`` of ``points_world`` (n, 3), world frame) extends its plane where
        ``grows[s]`` (as :meth:`extend`), counts as one of its segments and sights it at ``time``
        (s) and ``odometer`` (m, as :meth:`seen`): the same planes as those calls one by one."""
        if not pids:
            return
        planes = self.planes
        local: dict[int, int] = {}
        for pid in pids:
            local.setdefault(pid, len(local))
        uniq = list(local)
        us = np.array([planes[pid].u for pid in uniq], dtype=np.float64).reshape(-1, 3)
        vs = np.array([planes[pid].v for pid in uniq], dtype=np.float64).reshape(-1, 3)
        extremes = np.zeros((len(uniq), 4, 3))
        has = np.zeros(len(uniq), dtype=np.bool_)
        for q, pid in enumerate(uniq):
            e = planes[pid].extremes
            if e is not None:
                extremes[q] = e
                has[q] = True
        seg_plane = np.array([local[pid] for pid in pids], dtype=np.int64)
        pts = np.ascontiguousarray(points_world, dtype=np.float64)
        grows = np.ascontiguousarray(grows, dtype=np.bool_)
        # the cells, the extreme points and the extent index in one compiled call
        ext = self.extents
        ext.reserve(pts.shape[0])
        cells, start, added = xk.observe_cells(pts, bounds, seg_plane, np.array(pids, dtype=np.int64), grows,
                                               extremes, has, us, vs, float(self.cell_size), ext.keys, ext.count,
                                               ext.box)
        ext.size += added
        cu, cv, cs, bs = cells[:, 0].tolist(), cells[:, 1].tolist(), start.tolist(), bounds.tolist()
        grown = grows.tolist()
        for s, pid in enumerate(pids):
            p = planes[pid]
            if grown[s]:
                if cs[s + 1] > cs[s]:
                    p.cells.update(zip(cu[cs[s]:cs[s + 1]], cv[cs[s]:cs[s + 1]], strict=True))
                if p.n_segments < self.samples_until:
                    p.samples.append(np.array(pts[bs[s]:bs[s + 1]]))
            p.n_segments += 1
        bucket = self._bucket_of(time)
        for q, pid in enumerate(uniq):
            p = planes[pid]
            if has[q]:
                p.extremes = extremes[q].copy()
            p.last_seen_time = time
            p.last_seen_odometer = odometer
            p.seen_buckets.add(bucket)

    @staticmethod
    def _grow_extremes(p: Plane, points_world: FloatArray) -> None:
        """Keep the points (world frame) of least and most ``u`` and ``v`` among the plane's
        extreme points and ``points_world`` (m, 3)."""
        if points_world.shape[0] == 0:
            return
        pts = points_world if p.extremes is None else np.concatenate((p.extremes, points_world))
        pu, pv = pts @ p.u, pts @ p.v
        p.extremes = pts[[int(pu.argmin()), int(pu.argmax()), int(pv.argmin()), int(pv.argmax())]]

    def overlaps(self, pid: int, points_world: FloatArray, dilate: int) -> bool:
        """Whether any of the points' (m, 3), world frame, cells is within ``dilate`` cells of the
        plane's extent."""
        if not self.planes[pid].cells:
            return False
        return self.extents.near(pid, self.cells_of(pid, points_world), dilate)

    def overlaps_cells(self, pid: int, cells: list[list[int]], dilate: int) -> bool:
        """Whether any of the cells ``[[cu, cv], ...]`` (the plane's (u, v) frame, as
        ``cells_of``) is within ``dilate`` cells (Chebyshev distance) of the plane's extent
        (compiled: ``extents``)."""
        return self.extents.near(pid, np.array(cells, dtype=np.int64).reshape(-1, 2), dilate)

    def extents_touch(self, a: int, b: int, dilate: int) -> bool:
        """Whether two planes' extents are within ``dilate`` cells (measured in plane ``a``'s frame)."""
        pa, pb = self.planes[a], self.planes[b]
        if not pa.cells or not pb.cells:
            return False
        # cell centres of b, lifted to 3D on b and re-expressed in a's cells
        return self.overlaps(a, self.cell_centres(b), dilate)

    def cell_centres(self, pid: int) -> FloatArray:
        """Centres (m, 3) of the plane's extent cells, lifted onto the plane (world frame; kept until
        the plane map or the extent changes: do not modify)."""
        p = self.planes[pid]
        if not p.cells:
            return np.empty((0, 3))
        # kept while the plane keeps its cells (they only grow: the same set and count) and its
        # frame, whatever else of the map changed
        frame = np.concatenate((p.u, p.v, p.normal, [p.d]))
        hit = self._centres.get(pid)
        if hit is not None and hit[0] is p.cells and hit[1] == len(p.cells):
            if np.array_equal(hit[2], frame):
                return hit[4]
            cells = hit[3]
        else:
            cells = np.array(list(p.cells), dtype=np.float64) + 0.5
        out = (cells[:, :1] * p.u + cells[:, 1:] * p.v) * self.cell_size - p.d * p.normal
        self._centres[pid] = (p.cells, len(p.cells), frame, cells, out)
        return out

    def extent_length(self, pid: int) -> float:
        """The longer side (m) of the bounding rectangle of the plane's extent cells (0 without cells)."""
        cells = self.planes[pid].cells
        if not cells:
            return 0.0
        c = np.array(list(cells), dtype=np.int64)
        return float((c.max(axis=0) - c.min(axis=0) + 1).max()) * self.cell_size

    def max_distance_over(self, src: int, dst: int) -> float:
        """Largest distance of plane ``dst`` from plane ``src`` over ``src``'s extent (m): the
        offset difference of two planes where one of them was seen, tilt included."""
        pts = self.cell_centres(src)
        if pts.shape[0] == 0:
            return float("inf")
        q = self.planes[dst]
        return float(np.max(np.abs(pts @ q.normal + q.d)))

    def polygon(self, pid: int) -> FloatArray:
        """The extent's bounding rectangle as a closed (5, 3) polygon on the plane (world frame):
        of its extreme points where known, else of its cells."""
        p = self.planes[pid]
        if not p.cells:
            return np.empty((0, 3))
        if p.extremes is not None:
            uv = np.column_stack((p.extremes @ p.u, p.extremes @ p.v))
            lo, hi = uv.min(axis=0), uv.max(axis=0)
        else:
            c = np.array(list(p.cells), dtype=np.float64)
            lo = c.min(axis=0) * self.cell_size
            hi = (c.max(axis=0) + 1.0) * self.cell_size
        corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]], [lo[0], lo[1]]])
        return corners[:, :1] * p.u + corners[:, 1:] * p.v - p.d * p.normal

    def unseen_between(self, a: int, b: int) -> float:
        """Distance walked (m) between the sightings of planes ``a`` and ``b``: 0 when their
        observation spans (by odometer) overlap, so that the two were measured against one
        another without drift in between (a door and its wall), else the gap between the spans
        (a plane seen again on a return to an old place)."""
        pa, pb = self.planes[a], self.planes[b]
        return max(0.0, max(pa.first_seen_odometer, pb.first_seen_odometer)
                   - min(pa.last_seen_odometer, pb.last_seen_odometer))

    def merge(self, keep: int, drop: int) -> None:
        """Fold plane ``drop`` into ``keep``: union of extents and counts; ``drop`` becomes inactive."""
        pk, pd = self.planes[keep], self.planes[drop]
        if pd.cells:
            own = pk.extremes
            self.extend(keep, self.cell_centres(drop))
            # the outline: the two planes' extreme points (the cell centres' only where one had none)
            if own is not None and pd.extremes is not None:
                pk.extremes = None
                self._grow_extremes(pk, np.vstack((own, pd.extremes)))
        pk.n_segments += pd.n_segments
        pk.last_seen_time = max(pk.last_seen_time, pd.last_seen_time)
        pk.last_seen_odometer = max(pk.last_seen_odometer, pd.last_seen_odometer)
        pk.first_seen_odometer = min(pk.first_seen_odometer, pd.first_seen_odometer)
        pk.seen_buckets |= pd.seen_buckets
        pd.active = False
        pd.merged_into = keep
        self._hosts.add(keep)
        self.merges += 1
        self._active = None
        self._version += 1

    def remove_transient(self, pid: int) -> None:
        """Take plane ``pid`` out of the map: a thing that moved (``frontend.transients``)."""
        p = self.planes[pid]
        p.active = False
        p.transient = True
        self._active = None
        self._version += 1

    def has_merged(self, pid: int) -> bool:
        """Whether another plane was merged into plane ``pid``."""
        return pid in self._hosts

    def merge_hosts(self) -> set[int]:
        """The planes another plane was merged into (a shared set: do not modify)."""
        return self._hosts

    def set_estimate(self, pid: int, normal: FloatArray, d: float, sigma_offset: float | None = None) -> None:
        """Copy a back-end estimate in, keeping the in-plane basis continuous."""
        p = self.planes[pid]
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        if float(n @ p.normal) < 0:  # keep the orientation the map started with
            n, d = -n, -d
        u = p.u - (p.u @ n) * n
        u /= np.linalg.norm(u)
        p.normal, p.d, p.u, p.v = n, float(d), u, np.cross(n, u)
        if sigma_offset is not None:
            p.sigma_offset = float(sigma_offset)
        self._version += 1
