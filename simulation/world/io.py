"""Ground-truth exports of a world: the mesh (PLY) and the planes (JSON), and their readers.

Both are written atomically: to a temporary name in the target folder, then renamed.

Mesh PLY: open3d writes vertex positions (float64) and colours only, no per-face
properties, so every plane gets its own copy of its vertices and the vertex colour
(8-bit RGB) encodes the plane id: ``rgb = (id * PLANE_COLOR_MULT) mod 2**24``. The
multiplier scrambles neighbouring ids into distinct colours, so the PLY also views
well; ``read_mesh`` inverts it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from common.atomic import atomic_path
from simulation.world.kinds import KINDS
from simulation.world.mesh import Plane

PLANES_CONVENTION = "n . x + d = 0, world frame, metres"
PLANE_COLOR_MULT = 0x9E3779  # odd, hence invertible modulo 2**24
_MOD = 1 << 24


def plane_ids_to_rgb(ids: NDArray[np.integer]) -> NDArray[np.uint8]:
    """Plane ids (N,) -> 8-bit colours (N, 3)."""
    ids = np.asarray(ids, dtype=np.int64)
    if ids.size and (ids.min() < 0 or ids.max() >= _MOD):
        raise ValueError("plane ids must be in [0, 2**24) to be encoded as colours")
    code = (ids * PLANE_COLOR_MULT) % _MOD
    return np.stack([(code >> 16) & 255, (code >> 8) & 255, code & 255], axis=1).astype(np.uint8)


def rgb_to_plane_ids(rgb: NDArray[np.uint8]) -> NDArray[np.int32]:
    """Inverse of :func:`plane_ids_to_rgb`."""
    c = np.asarray(rgb, dtype=np.int64)
    code = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    inv = pow(PLANE_COLOR_MULT, -1, _MOD)
    return ((code * inv) % _MOD).astype(np.int32)


@dataclass(frozen=True)
class MeshData:
    """A mesh read back from PLY: vertices (V, 3) world frame, triangles (T, 3), plane ids (T,)."""

    vertices: NDArray[np.float64]
    triangles: NDArray[np.int32]
    tri_plane: NDArray[np.int32]


def write_mesh(
    path: str | Path,
    vertices: NDArray[np.float64],
    triangles: NDArray[np.int32],
    tri_plane: NDArray[np.int32],
) -> None:
    """Write the mesh as binary PLY (float64 positions, plane id in the vertex colours)."""
    import open3d as o3d  # heavy; only where needed

    # one vertex copy per (plane, vertex) so that a vertex colour names one plane
    keys = np.stack([np.repeat(tri_plane, 3), triangles.reshape(-1)], axis=1).astype(np.int64)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor.from_numpy(np.ascontiguousarray(vertices[uniq[:, 1]]))
    mesh.vertex.colors = o3d.core.Tensor.from_numpy(
        plane_ids_to_rgb(uniq[:, 0]).astype(np.float32) / 255.0
    )
    mesh.triangle.indices = o3d.core.Tensor.from_numpy(inverse.reshape(-1, 3).astype(np.int32))
    with atomic_path(path, make_parents=True) as tmp:
        if not o3d.t.io.write_triangle_mesh(tmp, mesh, write_ascii=False):
            raise OSError(f"{path}: open3d could not write the mesh")


def read_mesh(path: str | Path) -> MeshData:
    """Read a mesh written by :func:`write_mesh`."""
    import open3d as o3d

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such mesh file")
    mesh = o3d.io.read_triangle_mesh(p)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    triangles = np.asarray(mesh.triangles, dtype=np.int32)
    colors = np.asarray(mesh.vertex_colors)
    if len(triangles) == 0 or len(colors) != len(vertices):
        raise ValueError(f"{p}: not a world mesh (no triangles or no plane-id colours)")
    rgb = np.rint(colors * 255.0).astype(np.uint8)
    ids = rgb_to_plane_ids(rgb)
    return MeshData(vertices=vertices, triangles=triangles, tri_plane=ids[triangles[:, 0]])


def write_planes(path: str | Path, planes: list[Plane]) -> None:
    """Write planes as JSON: ``{"convention", "planes": [{id, kind, normal, d, polygon}]}``."""
    doc = {
        "convention": PLANES_CONVENTION,
        "planes": [
            {
                "id": int(p.id),
                "kind": p.kind,
                "normal": [float(x) for x in p.normal],
                "d": float(p.d),
                "polygon": [[float(x) for x in q] for q in p.polygon],
            }
            for p in planes
        ],
    }
    with atomic_path(path, make_parents=True) as tmp:
        tmp.write_text(json.dumps(doc, indent=1))


def read_planes(path: str | Path) -> list[Plane]:
    """Read planes written by :func:`write_planes`; a ValueError names the file and entry."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except OSError as e:
        raise FileNotFoundError(f"{p}: cannot read ({e.strerror or e})") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{p}: invalid JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(doc, dict) or doc.get("convention") != PLANES_CONVENTION:
        raise ValueError(f"{p}: not a planes file (convention must be {PLANES_CONVENTION!r})")
    out: list[Plane] = []
    for i, entry in enumerate(doc.get("planes", [])):
        try:
            normal = np.asarray(entry["normal"], dtype=np.float64).reshape(3)
            polygon = np.asarray(entry["polygon"], dtype=np.float64).reshape(-1, 3)
            kind = str(entry["kind"])
            if kind not in KINDS:
                raise ValueError(f"unknown kind {kind!r}")
            out.append(
                Plane(
                    id=int(entry["id"]),
                    normal=normal,
                    d=float(entry["d"]),
                    kind=kind,
                    polygon=polygon,
                )
            )
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{p}: planes[{i}]: {err}") from None
    return out
