"""Simulated buildings: world description (YAML), mesh compilation, ground-truth exports.

``load_world(name_or_path)`` gives a :class:`World`: a triangle mesh in the world frame
whose triangles carry a plane id and an object kind (``KINDS``), the list of
:class:`Plane` records (``n . x + d = 0``) and the operator's walk.
"""

from simulation.world.compile import compile_world
from simulation.world.io import MeshData, read_mesh, read_planes, write_mesh, write_planes
from simulation.world.kinds import KIND_NAMES, KINDS
from simulation.world.load import load_world, resolve_world, world_names
from simulation.world.mesh import Plane
from simulation.world.model import World
from simulation.world.spec import Walk, WorldSpec

__all__ = [
    "KINDS",
    "KIND_NAMES",
    "MeshData",
    "Plane",
    "Walk",
    "World",
    "WorldSpec",
    "compile_world",
    "load_world",
    "read_mesh",
    "read_planes",
    "resolve_world",
    "world_names",
    "write_mesh",
    "write_planes",
]
