"""The compiled world: a triangle mesh with a plane id and an object kind per triangle."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from simulation.world.clearance import PlanObstacles
from simulation.world.io import write_mesh, write_planes
from simulation.world.kinds import KINDS
from simulation.world.mesh import Plane
from simulation.world.spec import Walk, WorldSpec


@dataclass(frozen=True, eq=False)
class World:
    """A building in the world frame (metres, z up).

    ``planes[i].id == i``; ``tri_plane`` gives each triangle's plane id and ``tri_kind``
    its kind code (``KINDS``). ``bounds`` is (2, 3): the min and max corners of the mesh.
    """

    name: str
    vertices: NDArray[np.float64]
    triangles: NDArray[np.int32]
    tri_plane: NDArray[np.int32]
    tri_kind: NDArray[np.int8]
    planes: list[Plane]
    walk: Walk
    floor_z: float
    ceiling_z: float
    bounds: NDArray[np.float64]
    spec: WorldSpec | None = field(default=None, repr=False)
    obstacles: PlanObstacles | None = field(default=None, repr=False)

    @cached_property
    def plane_normals(self) -> NDArray[np.float64]:
        """(P, 3) unit normals, indexed by plane id."""
        return np.stack([p.normal for p in self.planes])

    @cached_property
    def plane_d(self) -> NDArray[np.float64]:
        """(P,) offsets ``d`` of ``n . x + d = 0``, indexed by plane id."""
        return np.array([p.d for p in self.planes], dtype=np.float64)

    @cached_property
    def plane_kind(self) -> NDArray[np.int8]:
        """(P,) kind codes, indexed by plane id."""
        return np.array([KINDS[p.kind] for p in self.planes], dtype=np.int8)

    def write_mesh(self, path: str | Path) -> None:
        """Write the mesh as PLY (atomic; plane ids in the vertex colours, see ``io``)."""
        write_mesh(path, self.vertices, self.triangles, self.tri_plane)

    def write_planes(self, path: str | Path) -> None:
        """Write the planes as JSON (atomic): id, kind, normal, d, polygon per plane."""
        write_planes(path, self.planes)
