"""Accumulate a triangle mesh whose triangles carry a plane id, and the plane records.

Frames: everything is in the world frame, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from simulation.world.kinds import kind_code


@dataclass(frozen=True)
class Plane:
    """A physical plane: unit ``normal`` and ``d`` with ``normal . x + d = 0`` (world frame).

    ``normal`` points into free space (towards a viewer). ``polygon`` (k, 3) is the outer
    boundary of the plane's surface, counter-clockwise seen from the normal side.
    """

    id: int
    normal: NDArray[np.float64]
    d: float
    kind: str
    polygon: NDArray[np.float64]

    def distance(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Signed distances of points (N, 3) to the plane (positive on the normal side)."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.d


def newell_normal(polygon: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit normal of a planar polygon (k, 3) by Newell's method (counter-clockwise = +)."""
    p = np.asarray(polygon, dtype=np.float64)
    q = np.roll(p, -1, axis=0)
    n = np.array(
        [
            np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
            np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
            np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
        ]
    )
    norm = np.linalg.norm(n)
    if norm == 0:
        raise ValueError("degenerate polygon")
    return n / norm


def _snap_axis(n: NDArray[np.float64]) -> NDArray[np.float64]:
    """Make near-axis-aligned normals exactly axis-aligned (removes 1e-17 rounding)."""
    out = np.where(np.abs(n) < 1e-15, 0.0, n)
    return out / np.linalg.norm(out)


@dataclass
class MeshBuilder:
    """Collects vertices, triangles (with plane ids) and planes."""

    vertices: list[NDArray[np.float64]] = field(default_factory=list)
    triangles: list[NDArray[np.int64]] = field(default_factory=list)
    tri_plane: list[NDArray[np.int32]] = field(default_factory=list)
    planes: list[Plane] = field(default_factory=list)
    _n_vertices: int = 0

    def add_plane(
        self,
        normal: NDArray[np.float64],
        point: NDArray[np.float64],
        kind: str,
        polygon: NDArray[np.float64],
    ) -> int:
        """Register a plane through ``point`` with unit ``normal``; returns its id."""
        kind_code(kind)  # validates the name
        n = _snap_axis(np.asarray(normal, dtype=np.float64))
        pid = len(self.planes)
        d = -float(n @ np.asarray(point, dtype=np.float64))
        self.planes.append(
            Plane(id=pid, normal=n, d=d, kind=kind, polygon=np.asarray(polygon, dtype=np.float64))
        )
        return pid

    def add_triangles(
        self, vertices: NDArray[np.float64], triangles: NDArray[np.int64], plane_id: int
    ) -> None:
        """Add triangles (indices into ``vertices``) on plane ``plane_id``."""
        v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        self.vertices.append(v)
        self.triangles.append(t + self._n_vertices)
        self.tri_plane.append(np.full(len(t), plane_id, dtype=np.int32))
        self._n_vertices += len(v)

    def add_polygon(
        self,
        polygon: NDArray[np.float64],
        kind: str,
        toward: NDArray[np.float64],
        plane_id: int | None = None,
    ) -> int:
        """Add a convex planar polygon (k, 3), fan-triangulated, facing ``toward``.

        A new plane is created unless ``plane_id`` is given; returns the plane id.
        """
        p = np.asarray(polygon, dtype=np.float64)
        n = newell_normal(p)
        if n @ np.asarray(toward, dtype=np.float64) < 0:
            p, n = p[::-1], -n
        if plane_id is None:
            plane_id = self.add_plane(n, p[0], kind, p)
        k = len(p)
        fan = np.stack([np.zeros(k - 2, np.int64), np.arange(1, k - 1), np.arange(2, k)], axis=1)
        self.add_triangles(p, fan, plane_id)
        return plane_id

    def build(self) -> tuple[NDArray[np.float64], NDArray[np.int32], NDArray[np.int32]]:
        """Vertices (V, 3) with exact duplicates merged, triangles (T, 3), plane id per triangle."""
        v = np.concatenate(self.vertices, axis=0)
        t = np.concatenate(self.triangles, axis=0)
        uniq, inverse = np.unique(v, axis=0, return_inverse=True)
        tris = inverse.reshape(-1)[t].astype(np.int32)
        return uniq, tris, np.concatenate(self.tri_plane).astype(np.int32)
