"""Ray casting against a :class:`~simulation.world.World` with open3d's RaycastingScene.

Precision: open3d (Embree) works in float32, so the mesh, the ray origins and the
directions are rounded to ~1e-7 relative (about 1-3 um at 10-30 m from the origin) and
the returned hit distance carries that error. Embree is only used to find *which*
triangle a ray hits; the range is then recomputed in float64 from the hit triangle's
exact plane: ``t = -(n . o + d) / (n . u)`` with the float64 origin ``o`` and
direction ``u``. That is exact to float64 rounding for any ray that hits the interior
of a triangle. Near a triangle's edge float32 may pick the neighbouring triangle; across
a shared edge of two planes the two ranges agree there to float32 precision anyway.
At grazing incidence (``|n . u| < GRAZING_COS``) the float32 distance is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from simulation.world.kinds import NO_HIT
from simulation.world.model import World

#: Below this |cos(incidence)| the plane refinement is ill-conditioned; keep Embree's t.
GRAZING_COS = 1e-6


@numba.njit(cache=True, nogil=True)
def _refine(
    o: NDArray[np.float64],
    u: NDArray[np.float64],
    t32: NDArray[np.float32],
    prim: NDArray[np.uint32],
    tri_plane: NDArray[np.int32],
    normals: NDArray[np.float64],
    d: NDArray[np.float64],
    plane_kind: NDArray[np.int8],
    out_range: NDArray[np.float64],
    out_plane: NDArray[np.int32],
    out_kind: NDArray[np.int8],
    out_cos: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled
    """Exact float64 range on the hit triangle's plane; fills the output arrays."""
    for i in range(len(t32)):
        t = t32[i]
        if not np.isfinite(t):
            out_range[i] = np.inf
            out_plane[i] = NO_HIT
            out_kind[i] = NO_HIT
            out_cos[i] = 0.0
            continue
        pid = tri_plane[prim[i]]
        nx, ny, nz = normals[pid, 0], normals[pid, 1], normals[pid, 2]
        nu = nx * u[i, 0] + ny * u[i, 1] + nz * u[i, 2]
        if abs(nu) >= GRAZING_COS:
            out_range[i] = -(nx * o[i, 0] + ny * o[i, 1] + nz * o[i, 2] + d[pid]) / nu
        else:
            out_range[i] = t
        out_plane[i] = pid
        out_kind[i] = plane_kind[pid]
        out_cos[i] = abs(nu)


@dataclass(frozen=True)
class RayHits:
    """Per-ray results; misses have ``range`` inf, ``plane_id`` -1, ``kind`` -1, ``cos`` 0.

    ``cos_incidence`` is ``|n . u|`` for the hit plane's normal n and the ray direction u.
    """

    range: NDArray[np.float64]
    plane_id: NDArray[np.int32]
    kind: NDArray[np.int8]
    cos_incidence: NDArray[np.float64]

    @property
    def hit(self) -> NDArray[np.bool_]:
        return self.plane_id >= 0


class Raycaster:
    """Casts batches of rays in the world frame against a world's mesh."""

    def __init__(self, world: World, nthreads: int = 0) -> None:
        import open3d as o3d  # heavy; kept out of module import time

        self._o3d = o3d
        self.world = world
        self.nthreads = nthreads
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(world.vertices, dtype=np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(world.triangles, dtype=np.uint32)),
        )
        self._tri_plane = np.asarray(world.tri_plane, dtype=np.int32)
        self._normals = np.asarray(world.plane_normals, dtype=np.float64)
        self._d = np.asarray(world.plane_d, dtype=np.float64)
        self._plane_kind = np.asarray(world.plane_kind, dtype=np.int8)

    def cast(
        self, origins_world: NDArray[np.floating], directions_world: NDArray[np.floating]
    ) -> RayHits:
        """Cast rays from ``origins_world`` (N, 3) along unit ``directions_world`` (N, 3)."""
        o = np.asarray(origins_world, dtype=np.float64).reshape(-1, 3)
        u = np.asarray(directions_world, dtype=np.float64).reshape(-1, 3)
        if o.shape != u.shape:
            raise ValueError(f"origins {o.shape} and directions {u.shape} differ in shape")
        rays = np.empty((len(o), 6), dtype=np.float32)
        rays[:, :3] = o
        rays[:, 3:] = u
        res = self._scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays), nthreads=self.nthreads)
        t32 = res["t_hit"].numpy()
        prim = res["primitive_ids"].numpy()
        n = len(o)
        rng = np.empty(n)
        plane = np.empty(n, dtype=np.int32)
        kind = np.empty(n, dtype=np.int8)
        cos = np.empty(n)
        _refine(
            o,
            u,
            t32,
            prim,
            self._tri_plane,
            self._normals,
            self._d,
            self._plane_kind,
            rng,
            plane,
            kind,
            cos,
        )
        return RayHits(range=rng, plane_id=plane, kind=kind, cos_incidence=cos)
