"""Compiled (numba) loops of the cloud's export: a cloud.ply's rows packed from the point
columns, and the plane id of every point from its scan's associated segments.

The cloud pass handles ~10^8 points; numpy's per-field copies into the PLY's packed rows (six
strided passes over each chunk) and the per-segment Python loop of every scan were most of its
time. These loops compute nothing new: the rows are the same bytes, the plane ids the same
integers.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@nb.njit(cache=True)
def pack_rows(rows: NDArray[np.void], points_world: FloatArray, scanner: NDArray[np.integer], time: FloatArray,
              plane_id: NDArray[np.integer], start: int) -> None:  # pragma: no cover
    """Rows ``0 .. len(rows)`` of a cloud.ply without intensities (``slam.export``'s vertex
    layout) from points ``start ..`` of the columns."""
    for i in range(rows.shape[0]):
        k = start + i
        r = rows[i]
        r.x = points_world[k, 0]
        r.y = points_world[k, 1]
        r.z = points_world[k, 2]
        r.scanner = scanner[k]
        r.time = time[k]
        r.plane_id = plane_id[k]


@nb.njit(cache=True)
def pack_rows_intensity(rows: NDArray[np.void], points_world: FloatArray, scanner: NDArray[np.integer],
                        time: FloatArray, plane_id: NDArray[np.integer], intensity: NDArray[np.float32],
                        start: int) -> None:  # pragma: no cover
    """:func:`pack_rows` for a cloud.ply with the ``intensity`` property."""
    pack_rows(rows, points_world, scanner, time, plane_id, start)
    for i in range(rows.shape[0]):
        rows[i].intensity = intensity[start + i]


@nb.njit(cache=True)
def segment_planes(beams: IntArray, scan_start: IntArray, row_lo: IntArray, row_hi: IntArray, rows: IntArray,
                   first_beam: IntArray, last_beam: IntArray, row_plane: IntArray,
                   transient: int) -> tuple[NDArray[np.int32], IntArray, IntArray, IntArray]:  # pragma: no cover
    """The plane id of every point of a batch of scans from the scans' segment rows.

    Scan ``j`` holds points ``scan_start[j] .. scan_start[j + 1]`` (their beam indices ``beams``,
    increasing within the scan) and the segment rows ``rows[row_lo[j] .. row_hi[j]]`` (indices
    into ``first_beam``/``last_beam``/``row_plane``), taken in that order: a row marks the points
    of its beams with its plane (a later row over an earlier one), ``transient`` rows without
    counting as a segment, rows with a negative plane not at all. Returns the points' plane ids
    (-1: none), and per associated segment that covers a point: its scan ``j``, its plane and
    its first and last point (batch indices, two per segment)."""
    n = beams.shape[0]
    plane = np.full(n, -1, dtype=np.int32)
    m = 0
    for j in range(row_lo.shape[0]):
        m += row_hi[j] - row_lo[j]
    seg_scan = np.empty(m, dtype=np.int64)
    seg_plane = np.empty(m, dtype=np.int64)
    ends = np.empty(2 * m, dtype=np.int64)
    k = 0
    for j in range(row_lo.shape[0]):
        a, b = scan_start[j], scan_start[j + 1]
        if a == b:
            continue
        for q in range(row_lo[j], row_hi[j]):
            r = rows[q]
            pid = row_plane[r]
            if pid != transient and pid < 0:
                continue
            lo = a + np.searchsorted(beams[a:b], first_beam[r], side="left")
            hi = a + np.searchsorted(beams[a:b], last_beam[r], side="right")
            if hi <= lo:
                continue
            for i in range(lo, hi):
                plane[i] = pid
            if pid != transient:
                seg_scan[k] = j
                seg_plane[k] = pid
                ends[2 * k] = lo
                ends[2 * k + 1] = hi - 1
                k += 1
    return plane, seg_scan[:k], seg_plane[:k], ends[: 2 * k]

