"""Append-only float64 tables on disk: the rows of the observation blocks the window has left
(:mod:`slam.backend.blocks`), so that an hour's points do not stay on the heap.

Each table is one file of fixed-shape rows in a temporary folder made at the first append and
removed when the tables are collected, closed, or the interpreter exits. Rows are read back byte
for byte as written, by :meth:`SpillTables.read`: one read of the span they lie in when they are
close together (a knot interval's blocks, a section's), else through a memory map dropped after
the read, so that no mapping keeps the files' pages counted in the process's memory.
"""

from __future__ import annotations

import shutil
import tempfile
import weakref
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class SpillTables:
    """Tables ``name -> row shape`` of float64 rows on disk (see the module doc)."""

    def __init__(self, shapes: dict[str, tuple[int, ...]]) -> None:
        self._shapes = dict(shapes)
        self._rows = dict.fromkeys(shapes, 0)
        self._dir: Path | None = None
        self._cleanup: weakref.finalize | None = None

    def rows(self, name: str) -> int:
        """Rows written to table ``name``."""
        return self._rows[name]

    def append(self, name: str, rows: FloatArray) -> int:
        """Write ``rows`` (k, *shape) at the end of table ``name``; returns the first one's index."""
        if self._dir is None:
            self._dir = Path(tempfile.mkdtemp(prefix="backpack_slam_blocks_"))
            self._cleanup = weakref.finalize(self, shutil.rmtree, self._dir, True)
        arr = np.ascontiguousarray(rows, dtype=np.float64)
        assert arr.shape[1:] == self._shapes[name], (arr.shape, self._shapes[name])
        first = self._rows[name]
        with open(self._dir / name, "ab") as f:
            f.write(arr.tobytes())
        self._rows[name] += arr.shape[0]
        return first

    def table(self, name: str) -> FloatArray:
        """Table ``name`` (rows, *shape), read-only, mapped from its file (to inspect)."""
        if self._dir is None or self._rows[name] == 0:
            return np.zeros((0, *self._shapes[name]))
        return np.memmap(self._dir / name, dtype=np.float64, mode="r", shape=(self._rows[name], *self._shapes[name]))

    def read(self, name: str, rows: NDArray[np.int64]) -> FloatArray:
        """Rows ``rows`` (indices, any order) of table ``name``, (len(rows), *shape), a copy."""
        shape = self._shapes[name]
        if rows.shape[0] == 0:
            return np.zeros((0, *shape))
        assert self._dir is not None
        lo, hi = int(rows.min()), int(rows.max()) + 1
        width = int(np.prod(shape, dtype=np.int64))
        if hi - lo <= 4 * rows.shape[0] + 4096:  # close together: one read of their span
            span = np.fromfile(self._dir / name, dtype=np.float64, count=(hi - lo) * width, offset=8 * width * lo)
            return span.reshape(hi - lo, *shape)[rows - lo]
        table = self.table(name)
        out = np.asarray(table[rows])
        del table
        return out

    def clear(self, name: str) -> None:
        """Empty table ``name``."""
        self._rows[name] = 0
        if self._dir is not None:
            (self._dir / name).unlink(missing_ok=True)

    def close(self) -> None:
        """Remove the folder and every table."""
        if self._cleanup is not None:
            self._cleanup()
        self._dir, self._cleanup = None, None
        self._rows = dict.fromkeys(self._shapes, 0)

    @property
    def folder(self) -> Path | None:
        return self._dir
