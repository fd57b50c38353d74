"""Creation of new planes from unassociated segments of recent scans (world frame).

A plane needs two segments that are coplanar and not collinear: either their
directions differ (segments of different scanners, or of the tilted scanners
crossing a wall), or they are parallel but apart within the plane (parallel
segments of consecutive scans once the rig has moved across them). The seed
pair's plane gathers every pooled segment that lies on it (angle and point
distances within tolerance, close to the seed in space); the plane enters the
map only with ``min_support`` segments from at least two scans and when the
gathered points span two dimensions (their second principal spread above
``min_spread``). It is then refitted by total least squares on those points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam.frontend import batch_kernels as bk

FloatArray = NDArray[np.float64]


@dataclass
class PooledSegment:
    """An unassociated segment waiting for a plane; ``ref`` lets the caller find its observation."""

    ref: tuple[int, int]  # (scan serial, segment index in that scan)
    time: float
    scan_serial: int
    centroid: FloatArray
    direction: FloatArray
    endpoints: FloatArray  # (2, 3)
    samples: FloatArray  # (m, 3) points, world frame
    line: FloatArray  # (2, 3) the fitted line's two virtual points, world frame
    scan_normal: FloatArray  # (3,) normal of the scanner's scan plane, world frame
    origin: FloatArray  # (3,) the scanner's position when it saw the segment, world frame


@dataclass(frozen=True)
class PlaneInitParams:
    """Plane creation from the pool (``slam.params.plane_init_params``; angles in radians)."""

    min_support: int
    min_scans: int
    coplanar_distance: float  # m, a member's fitted line (both virtual points) within this of the plane
    sample_distance: float  # m, and every one of its raw samples within this
    coplanar_angle: float
    min_spread: float  # m, second principal standard deviation of the members' points
    min_angle_between: float  # non-parallel seed pair
    min_parallel_separation: float  # m, parallel seed pair
    neighbourhood: float  # m, members within this of the seed
    min_scan_plane_angle: float  # a plane this close to a member's scan plane is that scan plane
    window: float  # s, pooled segments older than this are dropped
    max_partners: int  # seed pairs tried per seed segment (nearest in distance first)
    vertical_walls: bool  # allow walls from horizontal segments alone (kept vertical by a prior)
    horizontal_tolerance: float  # a segment this close to horizontal counts as horizontal
    # the wall hypothesis takes segments of level scan planes only: a tilted scanner's level line
    # lies as well on a floor or table top as on the vertical plane through it, while a level
    # scanner cannot see a horizontal surface
    max_level_scan_tilt: float


@dataclass
class NewPlane:
    normal: FloatArray
    d: float
    members: list[PooledSegment]
    rms: float
    vertical_hypothesis: bool = False  # defined by horizontal segments + verticality


@dataclass
class SegmentPool:
    """Recent unassociated segments, oldest first."""

    params: PlaneInitParams
    items: list[PooledSegment] = field(default_factory=list)
    dropped: int = 0
    _tried: set[int] = field(default_factory=set)
    _cache: tuple[list[PooledSegment], int, FloatArray, FloatArray, NDArray[np.int64]] | None = None

    def add(self, seg: PooledSegment) -> None:
        self.items.append(seg)

    def expire(self, now: float) -> list[PooledSegment]:
        """Drop and return segments older than the window."""
        keep: list[PooledSegment] = []
        gone: list[PooledSegment] = []
        for s in self.items:
            (keep if now - s.time <= self.params.window else gone).append(s)
        self.items = keep
        self.dropped += len(gone)
        for g in gone:
            self._tried.discard(id(g))
        return gone

    def remove(self, members: list[PooledSegment]) -> None:
        ids = {id(m) for m in members}
        self.items = [s for s in self.items if id(s) not in ids]
        self._tried -= ids

    def create_planes(self) -> list[NewPlane]:
        """Find and remove groups of pooled segments that define new planes, newest seeds first."""
        out: list[NewPlane] = []
        while True:
            found = self._one_plane()
            if found is None:
                return out
            out.append(found)
            self.remove(found.members)

    def _one_plane(self) -> NewPlane | None:
        p = self.params
        items = self.items
        if len(items) < p.min_support:
            return None
        C = np.array([s.centroid for s in items])
        U = np.array([s.direction for s in items])
        serial = np.array([s.scan_serial for s in items])
        SN = np.array([s.scan_normal for s in items])
        # a segment already tried as a seed is still found as a partner of newer seeds
        for a in range(len(items) - 1, -1, -1):
            if id(items[a]) in self._tried:
                continue
            self._tried.add(id(items[a]))
            ca, ua = C[a], U[a]
            near = np.linalg.norm(C - ca, axis=1) < p.neighbourhood
            other = near & (serial != serial[a])
            other[a] = False
            if not other.any():
                continue
            cross = bk.cross_rows(ua, U)
            sin_ab = np.linalg.norm(cross, axis=1)
            sep = C - ca
            sep_perp = sep - (sep @ ua)[:, None] * ua
            sep_norm = np.linalg.norm(sep_perp, axis=1)
            normals = np.where(
                (sin_ab > np.sin(p.min_angle_between))[:, None],
                cross / np.maximum(sin_ab, 1e-12)[:, None],
                bk.cross_rows(ua, sep_perp) / np.maximum(sep_norm, 1e-12)[:, None],
            )
            usable = other & ((sin_ab > np.sin(p.min_angle_between)) | (sep_norm > p.min_parallel_separation))
            # coplanarity of b with the plane through a: b's centroid and direction
            dist_b = np.abs(np.einsum("ij,ij->i", normals, C - ca))
            ang_b = np.abs(np.einsum("ij,ij->i", normals, U))
            # every segment lies in its scanner's scan plane: segments of one scanner at nearly
            # one pose are "coplanar" in that plane, which is no surface
            not_scan = (np.abs(np.einsum("ij,ij->i", normals, SN)) < np.cos(p.min_scan_plane_angle)) & (
                np.abs(normals @ items[a].scan_normal) < np.cos(p.min_scan_plane_angle)
            )
            cand = np.flatnonzero(
                usable & not_scan & (dist_b < p.coplanar_distance) & (ang_b < np.sin(p.coplanar_angle))
            )
            for b in cand[np.argsort(dist_b[cand])][: p.max_partners]:
                plane = self._grow(a, int(b), normals[b], near, U, SN)
                if plane is not None:
                    return _facing(plane, items[a].origin)
            if (p.vertical_walls and abs(float(ua[2])) < np.sin(p.horizontal_tolerance)
                    and _level_scan(items[a], p)):
                plane = self._vertical(a, near)
                if plane is not None:
                    return _facing(plane, items[a].origin)
        return None

    def _vertical(self, a: int, near: NDArray[np.bool_]) -> NewPlane | None:
        """A wall from horizontal segments of level scan planes alone (the horizontal scanner's
        lines on a wall it faces, where bob gives no 2D spread): the vertical plane through the seed's line. The
        caller must keep such a plane vertical (a prior), as its tilt about the line is unseen."""
        p = self.params
        items = self.items
        ua = items[a].direction
        n = np.cross(ua, np.array([0.0, 0.0, 1.0]))
        n /= np.linalg.norm(n)
        d = -float(n @ items[a].centroid)
        members = []
        for i in np.flatnonzero(near):
            s = items[i]
            if abs(float(s.direction[2])) > np.sin(p.horizontal_tolerance) or abs(float(s.direction @ n)) > np.sin(p.coplanar_angle):
                continue
            if not on_plane(s, n, d, p):
                continue
            if abs(float(s.scan_normal @ n)) > np.cos(p.min_scan_plane_angle) or not _level_scan(s, p):
                continue
            members.append(s)
        if len(members) < p.min_support + 1 or len({s.scan_serial for s in members}) < p.min_scans + 1:
            return None
        pts = np.vstack([s.samples for s in members])
        # refit the offset and the heading, keeping the normal horizontal
        c = pts.mean(axis=0)
        q = (pts - c)[:, :2]
        _, _, vt = np.linalg.svd(q, full_matrices=False)
        n2 = np.array([vt[1, 0], vt[1, 1], 0.0])
        if n2 @ n < 0:
            n2 = -n2
        d2 = -float(n2 @ c)
        res = pts @ n2 + d2
        if not _consistent(members, n2, d2, p):
            return None
        return NewPlane(n2, d2, members, float(np.sqrt(np.mean(res**2))), vertical_hypothesis=True)

    def _arrays(self) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
        """The pooled segments' fitted lines (k, 2, 3) and samples (all of them, world frame) with
        each one's first row (k + 1,) in them; kept while the pool is unchanged (``add`` only
        appends to the list, the others replace it)."""
        hit = self._cache
        if hit is None or hit[0] is not self.items or hit[1] != len(self.items):
            items = self.items
            lines = np.array([s.line for s in items], dtype=np.float64).reshape(-1, 2, 3)
            samples = np.concatenate([np.empty((0, 3)), *(s.samples for s in items)]).astype(np.float64, copy=False)
            start = np.zeros(len(items) + 1, dtype=np.int64)
            np.cumsum(np.array([s.samples.shape[0] for s in items], dtype=np.int64), out=start[1:])
            hit = (items, len(items), lines, samples, start)
            self._cache = hit
        return hit[2], hit[3], hit[4]

    def _grow(self, a: int, b: int, normal: FloatArray, near: NDArray[np.bool_], U_all: FloatArray,
              SN_all: FloatArray) -> NewPlane | None:
        """The plane of the seed pair ``a``, ``b`` (about ``normal``) with the pooled segments
        ``near`` the seed that lie on it (``U_all``, ``SN_all``: every pooled segment's direction
        and scan normal), or None."""
        p = self.params
        items = self.items
        n, d, _ = fit_plane(np.vstack((items[a].samples, items[b].samples)))
        if n @ normal < 0:
            n, d = -n, -d
        cand = np.flatnonzero(near)
        U = U_all[cand]
        SN = SN_all[cand]
        ok = (np.abs(U @ n) <= np.sin(p.coplanar_angle)) & (np.abs(SN @ n) <= np.cos(p.min_scan_plane_angle))
        lines, samples, sample_start = self._arrays()
        idx = cand[ok]
        lying = bk.on_plane_many(lines, samples, sample_start, idx, np.ascontiguousarray(n, dtype=np.float64),
                                 float(d), p.coplanar_distance, p.sample_distance)
        members = [items[i] for i in idx[lying].tolist()]
        if len(members) < p.min_support or len({s.scan_serial for s in members}) < p.min_scans:
            return None
        pts = np.vstack([s.samples for s in members])
        n2, d2, spreads = fit_plane(pts)
        if spreads[1] < p.min_spread:
            return None
        if any(abs(float(s.scan_normal @ n2)) > np.cos(p.min_scan_plane_angle) for s in members):
            return None
        res = pts @ n2 + d2
        if not _consistent(members, n2, d2, p):
            return None
        return NewPlane(n2, d2, members, float(np.sqrt(np.mean(res**2))))


def _level_scan(s: PooledSegment, p: PlaneInitParams) -> bool:
    """Whether the segment's scan plane is within ``max_level_scan_tilt`` of horizontal."""
    return abs(float(s.scan_normal[2])) >= np.cos(p.max_level_scan_tilt)


def _consistent(members: list[PooledSegment], n: FloatArray, d: float, p: PlaneInitParams) -> bool:
    """Whether the refitted plane explains its members as noise: every fitted line within
    ``coplanar_distance`` and their RMS within a third of it. A plane tilted through a door and
    a bit of its wall (a 1-2 cm step) fits each line to a few millimetres, not to one."""
    if not all(on_plane(s, n, d, p) for s in members):
        return False
    r = np.concatenate([s.line @ n + d for s in members])
    return bool(np.sqrt(np.mean(r**2)) <= p.coplanar_distance / 3.0)


def on_plane(s: PooledSegment, n: FloatArray, d: float, p: PlaneInitParams) -> bool:
    """Whether a segment lies on the plane: its fitted line within ``coplanar_distance`` (tight:
    the line's offset is known to a fraction of a millimetre, so that a door recessed 1-2 cm or a
    board 1-2 cm proud does not join its wall) and each raw sample within ``sample_distance``."""
    if np.max(np.abs(s.line @ n + d)) > p.coplanar_distance:
        return False
    return bool(np.max(np.abs(s.samples @ n + d)) <= p.sample_distance)


def _facing(plane: NewPlane, origin: FloatArray) -> NewPlane:
    """Orient the plane's normal towards the side it was seen from."""
    if float(plane.normal @ origin) + plane.d < 0.0:
        plane.normal, plane.d = -plane.normal, -plane.d
    return plane


def fit_plane(points: FloatArray) -> tuple[FloatArray, float, FloatArray]:
    """TLS plane ``n . x + d = 0`` through (m, 3) points, and the principal standard deviations (descending)."""
    c = points.mean(axis=0)
    q = points - c
    _, s, vt = np.linalg.svd(q, full_matrices=False)
    n = vt[2]
    spreads = s / np.sqrt(max(points.shape[0], 1))
    return n, float(-n @ c), spreads


def tilt_sigma(points_world: FloatArray, sigmas: FloatArray, normal: FloatArray, about: FloatArray | None = None) -> float:
    """Standard deviation (rad) of a plane's worst-observed tilt from weighted points on it.

    A plane fitted to points (m, 3) with point-to-plane sigmas (m,) tilts about an in-plane
    axis ``e`` with information ``sum w_k s_k^2``, ``s_k`` the points' coordinates across ``e``
    from their weighted centroid. Returns the largest sigma over in-plane axes, or, with
    ``about`` (a unit in-plane axis, e.g. the vertical of a wall kept vertical by a prior),
    the sigma of the tilt about that axis only. Points in a thin strip far from the origin make
    the world-frame plane parameters (normal, offset) nearly singular for the solver.
    """
    w = 1.0 / np.maximum(sigmas, 1e-12) ** 2
    c = (w[:, None] * points_world).sum(axis=0) / w.sum()
    q = points_world - c
    if about is not None:
        across = np.cross(about, normal)
        s = q @ (across / max(float(np.linalg.norm(across)), 1e-12))
        info = float(w @ (s * s))
        return float(1.0 / np.sqrt(max(info, 1e-300)))
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    uv = q @ np.column_stack((u, v))
    S = (w[:, None, None] * uv[:, :, None] * uv[:, None, :]).sum(axis=0)
    return float(1.0 / np.sqrt(max(float(np.linalg.eigvalsh(S)[0]), 1e-300)))
