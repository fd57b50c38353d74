"""Plan view (x, y, world frame) of a world's obstacles: is a point free, how far from walls.

Used to validate the walk (clearance from walls and objects) and to place clutter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from common.config import ConfigError
from simulation.world.grid import FreeGrid
from simulation.world.spec import Walk

#: Height above the floor at which the plan is cut (m): the operator's body.
CUT_HEIGHT = 1.0
#: Spacing of the samples along the walk checked for clearance (m).
PATH_STEP = 0.05


def _wall_segments(
    xs: NDArray[np.float64], ys: NDArray[np.float64], free: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """Boundary segments (S, 2, 2) between free and solid cells of a 2D grid."""
    p = np.pad(free, 1)
    segs = []
    dx = p[1:, 1:-1] != p[:-1, 1:-1]  # faces at x = xs[i], cell row j
    i, j = np.nonzero(dx)
    segs.append(np.stack([np.stack([xs[i], ys[j]], 1), np.stack([xs[i], ys[j + 1]], 1)], 1))
    dy = p[1:-1, 1:] != p[1:-1, :-1]  # faces at y = ys[j], cell column i
    i, j = np.nonzero(dy)
    segs.append(np.stack([np.stack([xs[i], ys[j]], 1), np.stack([xs[i + 1], ys[j]], 1)], 1))
    return np.concatenate(segs, axis=0)


def point_segment_distance(
    points: NDArray[np.float64], segs: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Distance (N,) from each point (N, 2) to the nearest segment (S, 2, 2)."""
    out = np.full(len(points), np.inf)
    if len(segs) == 0:
        return out
    a, b = segs[:, 0], segs[:, 1]
    ab = b - a
    len2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
    chunk = max(1, 4_000_000 // len(segs))
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk, None, :]
        t = np.clip(np.einsum("nsk,sk->ns", p - a, ab) / len2, 0.0, 1.0)
        d = p - (a + t[..., None] * ab)
        out[s : s + chunk] = np.sqrt(np.min(np.einsum("nsk,nsk->ns", d, d), axis=1))
    return out


def inside_convex(points: NDArray[np.float64], polygon: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether points (N, 2) lie strictly inside a counter-clockwise convex polygon (k, 2)."""
    a, b = polygon, np.roll(polygon, -1, axis=0)
    e = b - a
    rel = points[:, None, :] - a[None]
    cross = e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0]
    return np.all(cross > 0, axis=1)


def polygon_segments(polygon: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.stack([polygon, np.roll(polygon, -1, axis=0)], axis=1)


@dataclass(frozen=True)
class PlanObstacles:
    """Walls (from the free-space grid cut at CUT_HEIGHT) and object footprints, in plan."""

    xs: NDArray[np.float64]
    ys: NDArray[np.float64]
    free: NDArray[np.bool_]  # (nx-1, ny-1) free cells at the cut height
    segments: NDArray[np.float64]  # (S, 2, 2) walls and object outlines
    footprints: tuple[NDArray[np.float64], ...]  # convex counter-clockwise (k, 2)

    @staticmethod
    def from_grid(grid: FreeGrid, floor_z: float) -> PlanObstacles:
        zs = grid.coords[2]
        k = int(np.searchsorted(zs, floor_z + CUT_HEIGHT, side="right")) - 1
        k = min(max(k, 0), grid.free.shape[2] - 1)
        free = grid.free[:, :, k].copy()
        xs, ys = grid.coords[0], grid.coords[1]
        return PlanObstacles(
            xs=xs, ys=ys, free=free, segments=_wall_segments(xs, ys, free), footprints=()
        )

    def with_footprints(self, footprints: list[NDArray[np.float64]]) -> PlanObstacles:
        if not footprints:
            return self
        segs = np.concatenate([self.segments, *[polygon_segments(f) for f in footprints]])
        return PlanObstacles(
            xs=self.xs,
            ys=self.ys,
            free=self.free,
            segments=segs,
            footprints=(*self.footprints, *footprints),
        )

    def is_free(self, points: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Points (N, 2) in free space and outside every object footprint."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        i = np.searchsorted(self.xs, pts[:, 0], side="right") - 1
        j = np.searchsorted(self.ys, pts[:, 1], side="right") - 1
        ok = (i >= 0) & (i < len(self.xs) - 1) & (j >= 0) & (j < len(self.ys) - 1)
        out = np.zeros(len(pts), dtype=bool)
        out[ok] = self.free[i[ok], j[ok]]
        for f in self.footprints:
            out &= ~inside_convex(pts, f)
        return out

    def clearance(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance (N,) to the nearest wall or object; -inf for points not in free space."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        d = point_segment_distance(pts, self.segments)
        return np.where(self.is_free(pts), d, -np.inf)


def walk_samples(walk: Walk) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Points (N, 2) every <= PATH_STEP along the walk, and the leg index of each."""
    wp = np.asarray(walk.waypoints, dtype=np.float64)
    if walk.closed:
        wp = np.concatenate([wp, wp[:1]])
    pts, legs = [], []
    for i in range(len(wp) - 1):
        n = max(1, int(np.ceil(np.linalg.norm(wp[i + 1] - wp[i]) / PATH_STEP)))
        t = np.linspace(0.0, 1.0, n + 1)[:, None]
        pts.append(wp[i] + t * (wp[i + 1] - wp[i]))
        legs.append(np.full(n + 1, i))
    return np.concatenate(pts), np.concatenate(legs)


def segment_segment_distance(
    legs: NDArray[np.float64], segs: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Distance (L,) from each segment in ``legs`` (L, 2, 2) to the nearest one in ``segs``."""
    out = np.full(len(legs), np.inf)
    if len(segs) == 0:
        return out
    for i, (p, q) in enumerate(legs):
        a, b = segs[:, 0], segs[:, 1]
        d = np.minimum(
            point_segment_distance(np.stack([p, q]), segs).min(),
            np.min(_endpoint_distances(a, b, p, q)),
        )
        if d > 0 and np.any(_crosses(a, b, p, q)):
            d = 0.0
        out[i] = d
    return out


def _endpoint_distances(
    a: NDArray[np.float64], b: NDArray[np.float64], p: NDArray[np.float64], q: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Distances of every segment endpoint in a, b (S, 2) to the segment p-q."""
    pq = q - p
    len2 = max(float(pq @ pq), 1e-300)
    pts = np.concatenate([a, b])
    t = np.clip((pts - p) @ pq / len2, 0.0, 1.0)
    return np.linalg.norm(pts - (p + t[:, None] * pq), axis=1)


def _crosses(
    a: NDArray[np.float64], b: NDArray[np.float64], p: NDArray[np.float64], q: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """Whether segment p-q properly crosses each segment a-b (S, 2)."""

    def orient(
        u: NDArray[np.float64], v: NDArray[np.float64], w: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        return (v[..., 0] - u[..., 0]) * (w[..., 1] - u[..., 1]) - (v[..., 1] - u[..., 1]) * (
            w[..., 0] - u[..., 0]
        )

    d1, d2 = orient(a, b, p), orient(a, b, q)
    d3, d4 = orient(p, q, a), orient(p, q, b)
    return (d1 * d2 < 0) & (d3 * d4 < 0)


def check_walk(walk: Walk, obstacles: PlanObstacles, source: str) -> None:
    """ConfigError naming the first waypoint or leg closer than ``walk.clearance`` to an obstacle.

    Waypoints are checked for being in free space; legs by their exact distance to every
    wall and object outline (a leg that crosses one has distance 0).
    """
    need = walk.clearance
    wp = np.asarray(walk.waypoints, dtype=np.float64)
    c = obstacles.clearance(wp)
    for i in np.flatnonzero(c < need):
        x, y = wp[i]
        what = (
            "is outside free space" if np.isinf(c[i]) else f"is {c[i]:.2f} m from a wall or object"
        )
        raise ConfigError(
            f"{source}: key 'walk.waypoints.{i}': waypoint ({x:.2f}, {y:.2f}) {what} "
            f"(needs >= {need} m clearance)"
        )
    ends = np.concatenate([wp, wp[:1]]) if walk.closed else wp
    legs = np.stack([ends[:-1], ends[1:]], axis=1)
    dist = segment_segment_distance(legs, obstacles.segments)
    for leg in np.flatnonzero(dist < need):
        p, q = legs[leg]
        n = max(1, int(np.ceil(np.linalg.norm(q - p) / PATH_STEP)))
        pts = p + np.linspace(0.0, 1.0, 4 * n + 1)[:, None] * (q - p)
        cl = obstacles.clearance(pts)
        blocked = np.flatnonzero(np.isinf(cl))
        k = int(blocked[0]) if len(blocked) else int(np.argmin(cl))
        nxt = (leg + 1) % len(wp)
        what = (
            "leaves free space"
            if np.isinf(cl[k])
            else f"passes {dist[leg]:.2f} m from a wall or object"
        )
        raise ConfigError(
            f"{source}: key 'walk.waypoints': the leg from waypoint {leg} to {nxt} {what} near "
            f"({pts[k, 0]:.2f}, {pts[k, 1]:.2f}) (needs >= {need} m clearance)"
        )
