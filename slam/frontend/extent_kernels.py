"""Compiled (numba) kernels of the planes' extent index (``slam.frontend.extent_index``): every
plane's extent cells in one open-addressing hash table, grown in place, and the dilated-extent
test of the association's candidate pairs in one call per scan.

A cell is the key ``(plane id, cu, cv)`` (integer cells of the plane's (u, v) frame,
``PlaneMap.cells_of``); the table ``keys`` (cap, 3) has a power-of-two capacity and ``EMPTY`` in
column 0 of a free slot (linear probing). Per plane, ``count`` holds its number of cells and
``box`` (P, 4) their bounds (least and most cu, least and most cv). The tests answer booleans
only: they are those of the set and array code they replaced (``tests/test_extent_kernels.py``).
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from slam.frontend.batch_kernels import grow_extremes, segment_cells

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

EMPTY = np.iinfo(np.int64).min  # column 0 of a free slot (no plane id is negative)


@nb.njit(cache=True, inline="always")
def _slot(keys: IntArray, pid: int, cu: int, cv: int) -> int:
    """The slot of ``(pid, cu, cv)`` in ``keys``: where it is, else the free slot it would take."""
    mask = keys.shape[0] - 1
    h = pid * 0x9E3779B1 + cu * 0x85EBCA77 + cv * 0xC2B2AE3D
    h ^= h >> 29
    h *= 0x5851F42D4C957F2D
    h ^= h >> 32
    i = h & mask
    while True:
        k0 = keys[i, 0]
        if k0 == EMPTY or (k0 == pid and keys[i, 1] == cu and keys[i, 2] == cv):
            return i
        i = (i + 1) & mask


@nb.njit(cache=True, inline="always")
def _has(keys: IntArray, pid: int, cu: int, cv: int) -> bool:
    return keys[_slot(keys, pid, cu, cv), 0] != EMPTY


@nb.njit(cache=True)
def insert_cells(keys: IntArray, count: IntArray, box: IntArray, seg_pid: IntArray, start: IntArray,
                 cells: IntArray) -> int:
    """Add the cells ``cells[start[s]:start[s + 1]]`` (c, 2) to plane ``seg_pid[s]``'s extent, for
    every ``s`` (``start`` (S + 1,)); cells already there are left. The table must have room for
    all of them. Returns the number of cells added."""
    added = 0
    for s in range(seg_pid.shape[0]):
        pid = seg_pid[s]
        for r in range(start[s], start[s + 1]):
            cu, cv = cells[r, 0], cells[r, 1]
            i = _slot(keys, pid, cu, cv)
            if keys[i, 0] != EMPTY:
                continue
            keys[i, 0], keys[i, 1], keys[i, 2] = pid, cu, cv
            added += 1
            if count[pid] == 0:
                box[pid, 0] = box[pid, 1] = cu
                box[pid, 2] = box[pid, 3] = cv
            else:
                box[pid, 0] = min(box[pid, 0], cu)
                box[pid, 1] = max(box[pid, 1], cu)
                box[pid, 2] = min(box[pid, 2], cv)
                box[pid, 3] = max(box[pid, 3], cv)
            count[pid] += 1
    return added


@nb.njit(cache=True)
def rehash(keys: IntArray, capacity: int) -> IntArray:
    """The table's keys in a new table of ``capacity`` slots (a power of two)."""
    out = np.empty((capacity, 3), dtype=np.int64)
    out[:, 0] = EMPTY
    for i in range(keys.shape[0]):
        if keys[i, 0] != EMPTY:
            j = _slot(out, keys[i, 0], keys[i, 1], keys[i, 2])
            out[j, 0], out[j, 1], out[j, 2] = keys[i, 0], keys[i, 1], keys[i, 2]
    return out


@nb.njit(cache=True)
def _dilated_hit(keys: IntArray, box: IntArray, pid: int, cu: int, cv: int, dilate: int) -> bool:
    """Whether a cell of plane ``pid``'s extent lies within ``dilate`` cells (Chebyshev distance,
    both axes) of ``(cu, cv)``: the cells of that square inside the extent's bounds looked up."""
    u0, u1 = max(cu - dilate, box[pid, 0]), min(cu + dilate, box[pid, 1])
    v0, v1 = max(cv - dilate, box[pid, 2]), min(cv + dilate, box[pid, 3])
    for u in range(u0, u1 + 1):
        for v in range(v0, v1 + 1):
            if _has(keys, pid, u, v):
                return True
    return False


@nb.njit(cache=True)
def cells_near(keys: IntArray, count: IntArray, box: IntArray, pid: int, cells: IntArray, dilate: int) -> bool:
    """``PlaneMap.overlaps_cells``: whether any of ``cells`` (q, 2) is within ``dilate`` cells of
    plane ``pid``'s extent (in it, or with ``dilate`` > 0 within that Chebyshev distance of one
    of its cells); False for an empty extent."""
    if count[pid] == 0:
        return False
    for q in range(cells.shape[0]):
        if _has(keys, pid, cells[q, 0], cells[q, 1]):
            return True
    if dilate <= 0:
        return False
    for q in range(cells.shape[0]):
        if _dilated_hit(keys, box, pid, cells[q, 0], cells[q, 1], dilate):
            return True
    return False


@nb.njit(cache=True)
def pairs_near(keys: IntArray, count: IntArray, box: IntArray, pair_id: IntArray, cells: IntArray,
               dilate: IntArray, whole: BoolArray) -> tuple[BoolArray, BoolArray]:
    """The association's extent tests of one scan's candidate pairs (``assoc_kernels.scan_pairs``:
    pair ``i`` of plane ``pair_id[i]``, its three cells ``cells[i]`` (3, 2), margin ``dilate[i]``):
    ``near`` (n,), any of the three cells over the dilated extent (:func:`cells_near`), and
    ``each`` (n,), where ``whole[i]`` and ``near[i]``: every one of the three on its own (else
    ``near[i]``)."""
    n = pair_id.shape[0]
    near = np.empty(n, dtype=np.bool_)
    each = np.empty(n, dtype=np.bool_)
    for i in range(n):
        near[i] = cells_near(keys, count, box, pair_id[i], cells[i], dilate[i])
        each[i] = near[i]
        if near[i] and whole[i]:
            for q in range(cells.shape[1]):
                if not cells_near(keys, count, box, pair_id[i], cells[i, q:q + 1], dilate[i]):
                    each[i] = False
                    break
    return near, each


@nb.njit(cache=True)
def observe_cells(points_world: FloatArray, bounds: IntArray, seg_plane: IntArray, seg_pid: IntArray,
                  grows: BoolArray, extremes: FloatArray, has: BoolArray, us: FloatArray, vs: FloatArray,
                  cell_size: float, keys: IntArray, count: IntArray, box: IntArray) -> tuple[IntArray, IntArray, int]:
    """``PlaneMap.observe_segments``' compiled part in one call: the growing segments' new cells
    (``batch_kernels.segment_cells``: (c, 2) and each segment's start (S + 1,)), their planes'
    extreme points grown in place (``batch_kernels.grow_extremes``), and the cells added to
    plane ``seg_pid[s]``'s extent in the index (:func:`insert_cells`; the table must have room for
    every row of ``points_world``). Returns the cells, the starts and the number of cells added."""
    cells, start = segment_cells(points_world, bounds, seg_plane, grows, us, vs, cell_size)
    grow_extremes(points_world, bounds, seg_plane, grows, extremes, has, us, vs)
    added = insert_cells(keys, count, box, seg_pid, start, cells)
    return cells, start, added
