"""Planes' extents from the final map: where the plane's own segments, placed with the final
trajectory, lie on it.

The front end grows a plane's extent while it walks (``slam.frontend.planemap``): in the world
frame of the poses of that moment, and by every segment it gave the plane, so that one wall
segment given to a door stretches the door's outline along its wall. The exported outline is
instead taken from the final map: each associated segment's end points in the world frame (the
cloud pass places them with the final trajectory), projected on the plane's final estimate. A
segment counts where both its ends lie within ``gate`` of the plane and its points' RMS distance
to it (the pass measures it) is within ``rms``: a segment run across a door's edge onto its wall,
or across a floor's corner, does not. Its path is rasterised into
``cell`` squares of the plane's (u, v) frame (``slam.frontend.planemap.plane_basis``: u
horizontal on walls); a cell is part of the extent when at least ``min_segments`` segments cross
it, so that a stray segment or two (a mixed one, a person) do not stretch it; the outline is the
bounding rectangle of those cells, at the precision of the segments' points within them, and its
regions the rectangles of the groups of those cells that lie within ``gap`` of one another (a
plane can hold separate surfaces: a wall's pieces between doorways, two doors at one depth).

Frames: end points, planes and outlines in the world frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from slam.frontend.planemap import plane_basis

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_SAMPLES_PER_CELL = 4  # samples along a segment per cell length: a cell crossed at a corner is rarely missed
_CHUNK_SEGMENTS = 20_000  # segments rasterised at a time (a few million runs at most)
_OFFSET = 1 << 30  # cell indices offset into 31 bits each of one non-negative key (cells of 5 cm: +-50,000 km)
_MERGE_ROWS = 4_000_000  # the chunks' cell tables are joined when they hold more rows than this
_GRID_CELLS = 1_000_000  # a plane's cells counted in a grid up to this many (2,500 m2 at 5 cm; 40 MB)


@dataclass(frozen=True)
class ExtentRule:
    """``cell`` (m) the raster's square, ``min_segments`` the segments that must cross a cell for
    it to count, ``gate`` (m) how far a segment's ends may lie off the plane, ``rms`` (m; None:
    not tested) the largest RMS distance of a segment's points to the plane, ``gap`` (m) the
    widest empty space within one region of the outline."""

    cell: float
    min_segments: int
    gate: float
    rms: float | None = None
    gap: float = 0.25

    def __post_init__(self) -> None:
        if not (self.cell > 0 and self.min_segments >= 1 and self.gate > 0 and (self.rms is None or self.rms > 0)
                and self.gap >= 0):
            raise ValueError(f"extent rule: expected cell > 0, min_segments >= 1, gate > 0, rms None or > 0, gap >= 0; "
                             f"got {self}")


@nb.njit(cache=True)
def segment_runs(a_uv: FloatArray, b_uv: FloatArray, cell: float) -> tuple[IntArray, IntArray, FloatArray]:  # pragma: no cover
    """The cells each segment ``a_uv[k] -> b_uv[k]`` ((k, 2) in-plane coordinates, m) crosses, one
    run per (segment, cell): its cell (r, 2) (``floor(uv / cell)``), its segment (r,) and the
    least and most u and v of the segment's samples in it (r, 4: u_lo, u_hi, v_lo, v_hi; the end
    points are samples)."""
    k_n = a_uv.shape[0]
    total = 0
    for k in range(k_n):
        length = math.hypot(b_uv[k, 0] - a_uv[k, 0], b_uv[k, 1] - a_uv[k, 1])
        total += math.ceil(length * _SAMPLES_PER_CELL / cell) + 1
    cells = np.empty((total, 2), dtype=np.int64)
    seg = np.empty(total, dtype=np.int64)
    box = np.empty((total, 4))
    r = -1
    for k in range(k_n):
        du, dv = b_uv[k, 0] - a_uv[k, 0], b_uv[k, 1] - a_uv[k, 1]
        n = math.ceil(math.hypot(du, dv) * _SAMPLES_PER_CELL / cell) + 1
        first = True
        for i in range(n):
            t = i / (n - 1) if n > 1 else 0.0
            u = a_uv[k, 0] + t * du
            v = a_uv[k, 1] + t * dv
            cu, cv = math.floor(u / cell), math.floor(v / cell)
            # a straight line's cells come in order and never again: a new cell is a new run
            if first or cells[r, 0] != cu or cells[r, 1] != cv:
                r += 1
                cells[r, 0], cells[r, 1] = cu, cv
                seg[r] = k
                box[r, 0], box[r, 1], box[r, 2], box[r, 3] = u, u, v, v
                first = False
            else:
                box[r, 0], box[r, 1] = min(box[r, 0], u), max(box[r, 1], u)
                box[r, 2], box[r, 3] = min(box[r, 2], v), max(box[r, 3], v)
    return cells[: r + 1], seg[: r + 1], box[: r + 1]


def union_box(boxes: Sequence[FloatArray]) -> FloatArray:
    """The box (2, 2: lo, hi of u and v) around ``boxes`` (2, 2 each; at least one)."""
    return np.array([np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)])


def rectangle(normal: FloatArray, d: float, box: FloatArray) -> FloatArray:
    """The closed (5, 3) outline (world frame) of the in-plane box (2, 2: lo, hi of u and v) on
    the plane ``normal . x + d = 0`` (its axes from ``plane_basis``)."""
    u, v = plane_basis(np.asarray(normal, dtype=np.float64))
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    (u0, v0), (u1, v1) = box
    corners = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1], [u0, v0]])
    return corners[:, :1] * u + corners[:, 1:] * v - d * n


@dataclass(frozen=True)
class Outline:
    """A plane's outline from the final map (world frame): ``polygon`` (5, 3) the bounding rectangle
    of all its counted cells, ``regions`` one such rectangle per group of them (cells within
    ``ExtentRule.gap`` of each other), the one of most cells first: the separate surfaces the plane
    holds (the pieces of a wall between its doorways, two doors at one depth)."""

    polygon: FloatArray
    regions: tuple[FloatArray, ...]


@nb.njit(cache=True)
def _grid_runs(a_uv: FloatArray, b_uv: FloatArray, cell: float, lo_u: int, lo_v: int, count: IntArray,
               box: FloatArray) -> None:  # pragma: no cover
    """:func:`segment_runs` accumulated into a grid whose cell (0, 0) is ``(lo_u, lo_v)``: per
    cell the segments that cross it (``count`` (H, W)) and their samples' least and most u and v
    (``box`` (H, W, 4), to be started at +inf, -inf, +inf, -inf)."""
    for k in range(a_uv.shape[0]):
        du, dv = b_uv[k, 0] - a_uv[k, 0], b_uv[k, 1] - a_uv[k, 1]
        n = math.ceil(math.hypot(du, dv) * _SAMPLES_PER_CELL / cell) + 1
        pu, pv = -1, -1
        for i in range(n):
            t = i / (n - 1) if n > 1 else 0.0
            u = a_uv[k, 0] + t * du
            v = a_uv[k, 1] + t * dv
            cu, cv = math.floor(u / cell) - lo_u, math.floor(v / cell) - lo_v
            if cu != pu or cv != pv:  # a new cell of this segment (a line meets each cell once)
                count[cu, cv] += 1
                pu, pv = cu, cv
            box[cu, cv, 0] = min(box[cu, cv, 0], u)
            box[cu, cv, 1] = max(box[cu, cv, 1], u)
            box[cu, cv, 2] = min(box[cu, cv, 2], v)
            box[cu, cv, 3] = max(box[cu, cv, 3], v)


def cell_table(a_uv: FloatArray, b_uv: FloatArray, cell: float,
               chunk: int = _CHUNK_SEGMENTS) -> tuple[IntArray, IntArray, FloatArray]:
    """Per cell that the segments ``a_uv -> b_uv`` ((k, 2) each) cross: the cell (c, 2), how many
    segments cross it (c,) and the least and most u and v of their samples in it (c, 4: u_lo,
    u_hi, v_lo, v_hi); cells in lexicographic order. Within a grid of at most ``_GRID_CELLS``
    cells around the segments they are counted in place; else rasterised ``chunk`` at a time and
    their runs reduced per cell, so that memory follows the cells, not the samples."""
    a = np.ascontiguousarray(a_uv, dtype=np.float64)
    b = np.ascontiguousarray(b_uv, dtype=np.float64)
    if a.shape[0]:
        lo = np.floor(np.minimum(a.min(axis=0), b.min(axis=0)) / cell).astype(np.int64) - 1
        hi = np.floor(np.maximum(a.max(axis=0), b.max(axis=0)) / cell).astype(np.int64) + 1
        shape = hi - lo + 1
        if int(shape[0]) * int(shape[1]) <= _GRID_CELLS:
            count = np.zeros((int(shape[0]), int(shape[1])), dtype=np.int64)
            box = np.empty((int(shape[0]), int(shape[1]), 4))
            box[..., 0::2], box[..., 1::2] = np.inf, -np.inf
            _grid_runs(a, b, float(cell), int(lo[0]), int(lo[1]), count, box)
            hit = np.argwhere(count > 0)  # row-major: lexicographic
            return hit + lo, count[hit[:, 0], hit[:, 1]], box[hit[:, 0], hit[:, 1]]
    parts: list[tuple[IntArray, IntArray, FloatArray]] = []
    rows = 0
    for lo in range(0, a.shape[0], chunk):
        cells, _, runs = segment_runs(a[lo:lo + chunk], b[lo:lo + chunk], float(cell))
        parts.append(_reduce(_keys(cells), np.ones(cells.shape[0], dtype=np.int64), runs))
        rows += parts[-1][0].shape[0]
        if rows > _MERGE_ROWS and len(parts) > 1:  # joined now and then: the parts' cells repeat
            parts = [_reduce(*(np.concatenate(c) for c in zip(*parts, strict=True)))]
            rows = parts[0][0].shape[0]
    if not parts:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 4))
    key, count, box = _reduce(*(np.concatenate(c) for c in zip(*parts, strict=True))) if len(parts) > 1 else parts[0]
    return np.column_stack(((key >> 32) - _OFFSET, (key & 0xFFFFFFFF) - _OFFSET)), count, box


def _keys(cells: IntArray) -> IntArray:
    """Each cell (r, 2) as one non-negative int64 key that sorts as the cells do."""
    return ((cells[:, 0] + _OFFSET) << 32) | (cells[:, 1] + _OFFSET)


def _reduce(key: IntArray, count: IntArray, box: FloatArray) -> tuple[IntArray, IntArray, FloatArray]:
    """Rows of one cell (``key``) joined, in key order: counts added, boxes (u_lo, u_hi, v_lo,
    v_hi) widened."""
    order = np.argsort(key)  # (any order within a cell: min, max and sum do not care)
    k = key[order]
    starts = np.flatnonzero(np.concatenate(([True], k[1:] != k[:-1])))
    b = box[order]
    out = np.column_stack((np.minimum.reduceat(b[:, 0], starts), np.maximum.reduceat(b[:, 1], starts),
                           np.minimum.reduceat(b[:, 2], starts), np.maximum.reduceat(b[:, 3], starts)))
    return k[starts], np.add.reduceat(count[order], starts), out


def region_boxes(a_uv: FloatArray, b_uv: FloatArray, cell: float, min_segments: int, gap: float) -> list[FloatArray]:
    """The boxes (2, 2 each: lo, hi of u and v, m, at the samples' precision) of the groups of cells that at least
    ``min_segments`` of the segments ``a_uv -> b_uv`` cross, a group being the cells within
    ``gap`` (m) of one another (by way of others); the group of most cells first."""
    if a_uv.shape[0] < min_segments:
        return []
    cells, counts, box = cell_table(a_uv, b_uv, cell)
    keep = counts >= min_segments
    if not keep.any():
        return []
    dense, box = cells[keep], box[keep]
    lo = dense.min(axis=0)
    grid = np.zeros(dense.max(axis=0) - lo + 1, dtype=bool)
    grid[tuple((dense - lo).T)] = True
    reach = max(0, math.ceil(gap / cell))
    joined = ndimage.binary_dilation(grid, structure=np.ones((3, 3), dtype=bool), iterations=reach) if reach else grid
    labels, n = ndimage.label(joined, structure=np.ones((3, 3), dtype=bool))
    label = labels[tuple((dense - lo).T)]
    sizes = np.bincount(label, minlength=n + 1)
    out = []
    for g in sorted(range(1, n + 1), key=lambda i: -sizes[i]):
        b = box[label == g]
        if b.shape[0]:
            out.append(np.array([[b[:, 0].min(), b[:, 2].min()], [b[:, 1].max(), b[:, 3].max()]]))
    return out


def final_extents(endpoints_world: FloatArray, seg_pid: NDArray[np.integer], planes: Sequence[tuple[int, FloatArray, float]],
                  rule: ExtentRule, seg_rms: NDArray[np.floating] | None = None) -> dict[int, Outline]:
    """Each plane's :class:`Outline` (world frame) from its segments' end points
    (``endpoints_world`` (m, 2, 3), world frame; ``seg_pid`` (m,) their planes) and its final
    estimate (``planes``: id, unit normal, offset) and, with ``rule.rms``, their points' RMS
    distances to their plane (``seg_rms`` (m,)), by ``rule`` (module doc). Planes without a cell
    crossed by ``rule.min_segments`` segments on them are left out."""
    ends = np.asarray(endpoints_world, dtype=np.float64).reshape(-1, 2, 3)
    pid = np.asarray(seg_pid, dtype=np.int64)
    order = np.argsort(pid, kind="stable")
    ids, first = np.unique(pid[order], return_index=True)
    bounds = dict(zip(ids.tolist(), zip(first.tolist(), [*first[1:].tolist(), order.size], strict=True), strict=True))
    out: dict[int, Outline] = {}
    for plane_id, normal, d in planes:
        span = bounds.get(int(plane_id))
        if span is None:
            continue
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        sel = order[span[0]:span[1]]
        e = ends[sel]
        on = (np.abs(e @ n + d) <= rule.gate).all(axis=1)
        if seg_rms is not None and rule.rms is not None:
            on &= np.asarray(seg_rms)[sel] <= rule.rms
        if not on.any():
            continue
        u, v = plane_basis(n)
        B = np.stack((u, v), axis=1)
        boxes = region_boxes(e[on, 0] @ B, e[on, 1] @ B, rule.cell, rule.min_segments, rule.gap)
        if boxes:
            whole = union_box(boxes)
            out[int(plane_id)] = Outline(rectangle(n, float(d), whole),
                                         tuple(rectangle(n, float(d), b) for b in boxes))
    return out
