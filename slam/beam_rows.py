"""Rows of the ground truth's per-beam arrays (``beams.npz``: ``<scanner>_plane_id``, (n_scans,
n_beams)) read a block of scans at a time, so that evaluating an hour's walk (1.9 GB of plane ids)
holds one block in memory, not the whole array.

``NpzRows`` streams one member of an ``.npz`` (stored or deflated) in increasing row order;
``ArrayRows`` gives the same interface over an array already in memory.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import IO, Any, Protocol

import numpy as np
from numpy.typing import NDArray


class BeamRows(Protocol):
    """A 2-D array read by row ranges."""

    @property
    def shape(self) -> tuple[int, int]: ...

    def rows(self, lo: int, hi: int) -> NDArray[Any]:
        """Rows ``lo`` to ``hi - 1`` (a copy or a view; callers do not write to it)."""
        ...


class ArrayRows:
    """``BeamRows`` over an array in memory."""

    def __init__(self, array: NDArray[Any]) -> None:
        if array.ndim != 2:
            raise ValueError(f"beam array of shape {array.shape}: expected (n_scans, n_beams)")
        self.array = array

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.array.shape[0]), int(self.array.shape[1]))

    def rows(self, lo: int, hi: int) -> NDArray[Any]:
        return self.array[lo:hi]


class NpzRows:
    """``BeamRows`` over the member ``name`` of the .npz at ``path``, read from the file in
    increasing row order (a read before the current position opens the member again).

    Raises ``ValueError`` for a member that is not a C-ordered 2-D array and ``KeyError`` for a
    missing one."""

    def __init__(self, path: str | Path, name: str) -> None:
        self.path = Path(path)
        self.name = name
        self._zip: zipfile.ZipFile | None = None
        self._f: IO[bytes] | None = None
        self._pos = 0
        self._open()
        if len(self._shape) != 2 or self._fortran:
            self.close()
            raise ValueError(f"{self.path}: '{name}' is not a C-ordered (n_scans, n_beams) array")

    def _open(self) -> None:
        self.close()
        self._zip = zipfile.ZipFile(self.path)
        self._f = self._zip.open(self.name)
        version = np.lib.format.read_magic(self._f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(self._f)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(self._f)
        else:
            raise ValueError(f"{self.path}: '{self.name}' has .npy format {version}, expected 1.0 or 2.0")
        self._shape: tuple[int, ...] = tuple(int(s) for s in shape)
        self._fortran = bool(fortran)
        self.dtype = np.dtype(dtype)
        self._pos = 0

    @property
    def shape(self) -> tuple[int, int]:
        return (self._shape[0], self._shape[1])

    def rows(self, lo: int, hi: int) -> NDArray[Any]:
        lo, hi = max(0, lo), min(hi, self._shape[0])
        if hi <= lo:
            return np.empty((0, self._shape[1]), dtype=self.dtype)
        if lo < self._pos or self._f is None:
            self._open()
        row_bytes = self._shape[1] * self.dtype.itemsize
        assert self._f is not None
        skip = (lo - self._pos) * row_bytes
        while skip > 0:  # a deflated member cannot seek: read past the rows not asked for
            chunk = self._f.read(min(skip, 1 << 24))
            if not chunk:
                raise ValueError(f"{self.path}: '{self.name}' ends before row {lo}")
            skip -= len(chunk)
        want = (hi - lo) * row_bytes
        data = self._f.read(want)
        if len(data) != want:
            raise ValueError(f"{self.path}: '{self.name}' ends before row {hi}")
        self._pos = hi
        return np.frombuffer(data, dtype=self.dtype).reshape(hi - lo, self._shape[1])

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None
        if self._zip is not None:
            self._zip.close()
            self._zip = None

    def __enter__(self) -> NpzRows:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def as_rows(source: NDArray[Any] | BeamRows) -> BeamRows:
    """``source`` as ``BeamRows`` (an array is wrapped)."""
    return ArrayRows(source) if isinstance(source, np.ndarray) else source
