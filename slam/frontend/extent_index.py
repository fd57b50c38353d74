"""The planes' extents as one compiled index (``slam.frontend.extent_kernels``): every plane's
extent cells (integer cells of its own (u, v) frame, ``PlaneMap.cells_of``) in one hash table
grown in place, so that the association tests all candidate pairs of a scan against their planes'
dilated extents in one call, without rebuilding per-plane arrays or keys per scan.

The index mirrors the planes' cell sets (``Plane.cells``, which the plane map keeps for the
outlines, merges and exports): ``PlaneMap`` adds to both in the same calls.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from slam.frontend import extent_kernels as xk

IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


class ExtentIndex:
    """All planes' extent cells (``(plane id, cu, cv)``), the count and bounds of each plane's."""

    def __init__(self, capacity: int = 1 << 12) -> None:
        self.size = 0  # cells held
        self.keys = np.empty((capacity, 3), dtype=np.int64)
        self.keys[:, 0] = xk.EMPTY
        self.count = np.zeros(64, dtype=np.int64)  # per plane id
        self.box = np.zeros((64, 4), dtype=np.int64)  # per plane id: least, most cu; least, most cv

    def add_plane(self, pid: int) -> None:
        """Room for plane ``pid`` (no cells yet)."""
        if pid >= self.count.shape[0]:
            n = max(2 * self.count.shape[0], pid + 1)
            self.count = np.concatenate((self.count, np.zeros(n - self.count.shape[0], dtype=np.int64)))
            self.box = np.concatenate((self.box, np.zeros((n - self.box.shape[0], 4), dtype=np.int64)))

    def reserve(self, n: int) -> None:
        """Room for ``n`` more cells (the table kept at most half full)."""
        need = self.size + n
        if 2 * need > self.keys.shape[0]:
            cap = self.keys.shape[0]
            while 2 * need > cap:
                cap *= 2
            self.keys = xk.rehash(self.keys, cap)

    def insert(self, seg_pid: IntArray, start: IntArray, cells: IntArray) -> None:
        """Add ``cells[start[s]:start[s + 1]]`` (c, 2) to plane ``seg_pid[s]``'s extent, every ``s``."""
        self.reserve(cells.shape[0])
        self.size += xk.insert_cells(self.keys, self.count, self.box, seg_pid, start, cells)

    def insert_one(self, pid: int, cells: IntArray) -> None:
        """Add ``cells`` (c, 2) to plane ``pid``'s extent."""
        self.insert(np.array([pid], dtype=np.int64), np.array([0, cells.shape[0]], dtype=np.int64),
                    np.ascontiguousarray(cells, dtype=np.int64).reshape(-1, 2))

    def near(self, pid: int, cells: IntArray, dilate: int) -> bool:
        """Whether any of ``cells`` (q, 2) is within ``dilate`` cells of plane ``pid``'s extent."""
        return bool(xk.cells_near(self.keys, self.count, self.box, int(pid), cells, int(dilate)))

    def pairs_near(self, pair_id: IntArray, cells: IntArray, dilate: IntArray,
                   whole: BoolArray) -> tuple[BoolArray, BoolArray]:
        """``extent_kernels.pairs_near`` of candidate pairs (plane ``pair_id`` (n,), three cells each
        ``cells`` (n, 3, 2), margins ``dilate`` (n,)): any cell near, and (where ``whole``) each."""
        return xk.pairs_near(self.keys, self.count, self.box, pair_id, cells, dilate, whole)

    def cells_of_plane(self, pid: int) -> set[tuple[int, int]]:
        """The cells held for plane ``pid`` (a check against ``Plane.cells``; a pass over the table)."""
        k = self.keys[self.keys[:, 0] == pid]
        return set(zip(k[:, 1].tolist(), k[:, 2].tolist(), strict=True))
