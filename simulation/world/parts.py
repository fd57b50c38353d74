"""Geometry of the parts placed in a world: doors, boards and boxes (world frame, metres).

Parts that meet the walls or the floor overlap them by ``OVERLAP`` behind the visible
surface instead of touching edge to edge, so that rays cannot slip through float32
cracks between separately built pieces; the overlap is hidden behind the surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from simulation.world.mesh import MeshBuilder

#: Hidden overlap between parts and the surfaces they meet (m).
OVERLAP = 1e-4


@dataclass(frozen=True)
class WallFrame:
    """A wall surface: ``axis`` (0: x = coord, 1: y = coord), facing ``sign * e_axis``.

    Local coordinates: ``h`` along the wall (the other horizontal axis), ``z`` world z,
    ``depth`` into the wall (0 on the surface, > 0 behind it, < 0 in front of it).
    """

    axis: int
    coord: float
    sign: int

    @property
    def h_axis(self) -> int:
        return 1 - self.axis

    @property
    def normal(self) -> NDArray[np.float64]:
        n = np.zeros(3)
        n[self.axis] = float(self.sign)
        return n

    def point(self, h: float, z: float, depth: float) -> NDArray[np.float64]:
        p = np.zeros(3)
        p[self.axis] = self.coord - self.sign * depth
        p[self.h_axis] = h
        p[2] = z
        return p

    def points(self, hzd: list[tuple[float, float, float]]) -> NDArray[np.float64]:
        return np.stack([self.point(*q) for q in hzd])


def add_door(
    mb: MeshBuilder,
    wall: WallFrame,
    at: float,
    width: float,
    height: float,
    recess: float,
    frame_width: float,
    floor_z: float,
    floor_plane: int,
) -> list[int]:
    """A closed door: leaf ``recess`` behind the wall, three sloped frame strips.

    The wall hole is ``width + 2 frame_width`` wide and ``height + frame_width`` high
    (minus OVERLAP); the frames slope from the hole's edge on the wall surface to the
    leaf's edge. The floor is continued into the recess on ``floor_plane``.
    Returns the new plane ids (leaf, left, right, top frames).
    """
    w2, w, r = width / 2.0, frame_width, recess
    z0, z1 = floor_z, floor_z + height
    a, b = at - w2, at + w2
    ao, bo = a - w, b + w
    f = wall.points
    toward = wall.normal
    leaf = mb.add_polygon(f([(a, z0, r), (b, z0, r), (b, z1, r), (a, z1, r)]), "door", toward)
    left = mb.add_polygon(
        f([(ao, z0, 0.0), (a, z0, r), (a, z1, r), (ao, z1 + w, 0.0)]), "door_frame", toward
    )
    right = mb.add_polygon(
        f([(b, z0, r), (bo, z0, 0.0), (bo, z1 + w, 0.0), (b, z1, r)]), "door_frame", toward
    )
    top = mb.add_polygon(
        f([(ao, z1 + w, 0.0), (a, z1, r), (b, z1, r), (bo, z1 + w, 0.0)]), "door_frame", toward
    )
    mb.add_polygon(
        f(
            [
                (ao, z0, -OVERLAP),
                (bo, z0, -OVERLAP),
                (bo, z0, 0.0),
                (b, z0, r),
                (a, z0, r),
                (ao, z0, 0.0),
            ]
        ),
        "floor",
        np.array([0.0, 0.0, 1.0]),
        plane_id=floor_plane,
    )
    return [leaf, left, right, top]


def add_board(
    mb: MeshBuilder,
    wall: WallFrame,
    at: float,
    z0: float,
    width: float,
    height: float,
    thickness: float,
) -> list[int]:
    """A board ``thickness`` proud of the wall with four steep (perpendicular) edges.

    Returns the plane ids (front, then the four edges).
    """
    a, b = at - width / 2.0, at + width / 2.0
    z1 = z0 + height
    t, o = -thickness, OVERLAP
    f = wall.points
    front = mb.add_polygon(
        f([(a, z0, t), (b, z0, t), (b, z1, t), (a, z1, t)]), "board", wall.normal
    )
    h = np.zeros(3)
    h[wall.h_axis] = 1.0
    ez = np.array([0.0, 0.0, 1.0])
    edges = [
        mb.add_polygon(f([(a, z0, o), (b, z0, o), (b, z0, t), (a, z0, t)]), "board_edge", -ez),
        mb.add_polygon(f([(a, z1, o), (b, z1, o), (b, z1, t), (a, z1, t)]), "board_edge", ez),
        mb.add_polygon(f([(a, z0, o), (a, z1, o), (a, z1, t), (a, z0, t)]), "board_edge", -h),
        mb.add_polygon(f([(b, z0, o), (b, z1, o), (b, z1, t), (b, z0, t)]), "board_edge", h),
    ]
    return [front, *edges]


def box_footprint(center: list[float], size_xy: list[float], yaw_deg: float) -> NDArray[np.float64]:
    """Corners (4, 2) of a yawed rectangle in plan, counter-clockwise."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    hx, hy = size_xy[0] / 2.0, size_xy[1] / 2.0
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + np.asarray(center, dtype=np.float64)


def add_box(
    mb: MeshBuilder,
    footprint: NDArray[np.float64],
    z0: float,
    z1: float,
    kind: str,
    bottom: bool = True,
    top: bool = True,
) -> list[int]:
    """A prism over a convex counter-clockwise ``footprint`` (4, 2) from z0 to z1.

    Every face is its own plane. Faces that would lie on the floor or ceiling are left
    out (``bottom``/``top`` False); the caller then extends z0/z1 by OVERLAP into them.
    """
    k = len(footprint)
    lo = np.column_stack([footprint, np.full(k, z0)])
    hi = np.column_stack([footprint, np.full(k, z1)])
    centroid = np.array([*footprint.mean(axis=0), 0.5 * (z0 + z1)])
    ids = []
    for i in range(k):
        j = (i + 1) % k
        quad = np.stack([lo[i], lo[j], hi[j], hi[i]])
        outward = quad.mean(axis=0) - centroid
        outward[2] = 0.0
        ids.append(mb.add_polygon(quad, kind, outward))
    if top:
        ids.append(mb.add_polygon(hi, kind, np.array([0.0, 0.0, 1.0])))
    if bottom:
        ids.append(mb.add_polygon(lo, kind, np.array([0.0, 0.0, -1.0])))
    return ids
