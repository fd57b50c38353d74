"""Boundary of a union of axis-aligned free boxes, on a coordinate-compressed grid.

The free space (rooms, corridors, openings) is a union of boxes. Every box face lies on
a grid line of the compressed grid built from all box coordinates, so the boundary of the
union is exactly the set of grid cell faces between a free and a solid cell. Faces on the
same axis-aligned plane, facing the same way and connected through shared cell edges form
one physical plane (e.g. a wall with a door hole, or the floor of rooms joined by
openings). Vertices are shared between all faces through one global grid indexing, so the
mesh has no T-junctions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

#: Coordinates are rounded to this many decimals (1e-9 m) before compression.
DECIMALS = 9

#: (u, v) in-plane axes of a face normal to axis a, cyclic so that (e_u x e_v) = +e_a.
UV_AXES = {0: (1, 2), 1: (2, 0), 2: (0, 1)}


@dataclass(frozen=True)
class FreeGrid:
    """A coordinate-compressed grid over the free space (world frame, metres)."""

    coords: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]
    free: NDArray[np.bool_]  # (nx-1, ny-1, nz-1): cell is free space

    def index(self, axis: int, value: float) -> int:
        """Index of a grid coordinate; a ValueError when ``value`` is not a grid line."""
        c = self.coords[axis]
        i = int(np.searchsorted(c, round(value, DECIMALS)))
        if i >= len(c) or abs(c[i] - value) > 1e-8:
            raise ValueError(f"{value} is not a grid coordinate on axis {axis}")
        return i

    def cell_range(self, axis: int, lo: float, hi: float) -> tuple[int, int]:
        """Cell index range [i0, i1) covering [lo, hi] (both must be grid coordinates)."""
        return self.index(axis, lo), self.index(axis, hi)

    def is_free(self, points: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether points (N, 3) lie in free cells (points on grid lines: the upper cell)."""
        idx = []
        for a in range(3):
            c = self.coords[a]
            i = np.searchsorted(c, points[:, a], side="right") - 1
            idx.append(i)
        inside = np.ones(len(points), dtype=bool)
        for a in range(3):
            inside &= (idx[a] >= 0) & (idx[a] < len(self.coords[a]) - 1)
        out = np.zeros(len(points), dtype=bool)
        ii = [i[inside] for i in idx]
        out[inside] = self.free[ii[0], ii[1], ii[2]]
        return out


def build_grid(
    boxes: NDArray[np.float64], extra: tuple[list[float], list[float], list[float]]
) -> FreeGrid:
    """Grid of the union of free ``boxes`` (B, 6) as [x0, y0, z0, x1, y1, z1].

    ``extra`` holds further grid coordinates per axis (e.g. the edges of door holes)
    so that later cuts fall on grid lines.
    """
    b = np.round(np.asarray(boxes, dtype=np.float64), DECIMALS)
    coords = tuple(
        np.unique(np.concatenate([b[:, a], b[:, a + 3], np.round(extra[a], DECIMALS)]))
        for a in range(3)
    )
    free = np.zeros(tuple(len(c) - 1 for c in coords), dtype=bool)
    for box in b:
        sl = tuple(
            slice(
                int(np.searchsorted(coords[a], box[a])), int(np.searchsorted(coords[a], box[a + 3]))
            )
            for a in range(3)
        )
        free[sl] = True
    return FreeGrid(coords=(coords[0], coords[1], coords[2]), free=free)


@dataclass(frozen=True)
class FaceSlice:
    """The boundary faces on one axis-aligned plane, facing one way.

    ``mask[i, j]`` marks the face over cell (i, j) of the in-plane (u, v) grid, with
    u, v = UV_AXES[axis]. The face normal is ``sign * e_axis`` and points into free space.
    """

    axis: int
    index: int  # grid index of the plane's coordinate along ``axis``
    coord: float
    sign: int
    mask: NDArray[np.bool_]


def boundary_slices(grid: FreeGrid) -> list[FaceSlice]:
    """All non-empty boundary face slices of the free space."""
    padded = np.pad(grid.free, 1, constant_values=False)
    out: list[FaceSlice] = []
    for axis in range(3):
        lo = np.take(padded, np.arange(0, padded.shape[axis] - 1), axis=axis)
        hi = np.take(padded, np.arange(1, padded.shape[axis]), axis=axis)
        # interior of the other two axes (drop the padding)
        sl: list[slice] = [slice(1, -1)] * 3
        sl[axis] = slice(None)
        lo, hi = lo[tuple(sl)], hi[tuple(sl)]
        u, v = UV_AXES[axis]
        for sign, faces in ((+1, hi & ~lo), (-1, lo & ~hi)):
            # move the axis first, then (u, v)
            faces_uv = np.transpose(faces, (axis, u, v))
            for k in np.flatnonzero(faces_uv.any(axis=(1, 2))):
                out.append(
                    FaceSlice(
                        axis=axis,
                        index=int(k),
                        coord=float(grid.coords[axis][k]),
                        sign=sign,
                        mask=faces_uv[k].copy(),
                    )
                )
    return out


def label_components(mask: NDArray[np.bool_]) -> tuple[NDArray[np.int32], int]:
    """4-connected components of a face mask: labels 1..n, 0 where empty."""
    labels, n = ndimage.label(mask)
    return labels.astype(np.int32), int(n)


def vertex_index(
    grid: FreeGrid, i: NDArray[np.int64], j: NDArray[np.int64], k: NDArray[np.int64]
) -> NDArray[np.int64]:
    """Global index of grid point (i, j, k) along (x, y, z)."""
    ny, nz = len(grid.coords[1]), len(grid.coords[2])
    return (i * ny + j) * nz + k


def slice_quads(grid: FreeGrid, fs: FaceSlice, cells: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Triangles (2 per cell, (2C, 3) global grid vertex indices) of the selected cells.

    Wound counter-clockwise seen from the side the normal points to.
    """
    iu, iv = np.nonzero(cells)
    corners_uv = [(iu, iv), (iu + 1, iv), (iu + 1, iv + 1), (iu, iv + 1)]
    u_ax, v_ax = UV_AXES[fs.axis]
    quad = []
    for cu, cv in corners_uv:
        ijk: list[NDArray[np.int64]] = [np.empty(0, np.int64)] * 3
        ijk[fs.axis] = np.full(len(iu), fs.index, dtype=np.int64)
        ijk[u_ax] = cu.astype(np.int64)
        ijk[v_ax] = cv.astype(np.int64)
        quad.append(vertex_index(grid, ijk[0], ijk[1], ijk[2]))
    q = np.stack(quad, axis=1)
    if fs.sign < 0:
        q = q[:, ::-1]
    tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]], axis=0)
    return tris


def grid_points(grid: FreeGrid, ids: NDArray[np.int64]) -> NDArray[np.float64]:
    """World coordinates (N, 3) of global grid vertex indices."""
    ny, nz = len(grid.coords[1]), len(grid.coords[2])
    i, rest = np.divmod(ids, ny * nz)
    j, k = np.divmod(rest, nz)
    return np.stack([grid.coords[0][i], grid.coords[1][j], grid.coords[2][k]], axis=1)


def outer_loop(mask: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Outer boundary of a 4-connected cell region as grid points (k, 2), counter-clockwise.

    Collinear points are dropped. Holes are ignored (only the loop of largest area).
    """
    iu, iv = np.nonzero(mask)
    padded = np.pad(mask, 1)
    edges: dict[tuple[int, int], list[tuple[int, int]]] = {}

    def add(a: tuple[int, int], b: tuple[int, int]) -> None:
        edges.setdefault(a, []).append(b)

    for u, v in zip(iu.tolist(), iv.tolist(), strict=True):
        pu, pv = u + 1, v + 1
        # region on the left of each directed edge -> counter-clockwise outer loop
        if not padded[pu, pv - 1]:
            add((u, v), (u + 1, v))
        if not padded[pu + 1, pv]:
            add((u + 1, v), (u + 1, v + 1))
        if not padded[pu, pv + 1]:
            add((u + 1, v + 1), (u, v + 1))
        if not padded[pu - 1, pv]:
            add((u, v + 1), (u, v))
    loops: list[list[tuple[int, int]]] = []
    while edges:
        start = next(iter(edges))
        loop = [start]
        cur = start
        while True:
            nxt_list = edges[cur]
            nxt = nxt_list.pop()
            if not nxt_list:
                del edges[cur]
            if nxt == start:
                break
            loop.append(nxt)
            cur = nxt
        loops.append(loop)

    def area(lp: list[tuple[int, int]]) -> float:
        a = np.asarray(lp, dtype=np.float64)
        return 0.5 * float(np.sum(a[:, 0] * np.roll(a[:, 1], -1) - np.roll(a[:, 0], -1) * a[:, 1]))

    ring = np.asarray(max(loops, key=area), dtype=np.int64)
    prv, fwd = np.roll(ring, 1, axis=0), np.roll(ring, -1, axis=0)
    cross = (ring[:, 0] - prv[:, 0]) * (fwd[:, 1] - ring[:, 1]) - (ring[:, 1] - prv[:, 1]) * (
        fwd[:, 0] - ring[:, 0]
    )
    return ring[cross != 0]
