"""A section's eliminated interior packed into flat arrays, kept in memory or on disk, and
back-substituted by one compiled pass (issue 27): what :mod:`slam.backend.sections` keeps of a
section between its reduction and its back-substitution instead of gtsam's Bayes net.

A Gaussian Bayes net from sequential elimination is a list of conditionals ``R x_f = d - S x_p``
(``x_f`` the frontal variables, ``R`` upper triangular; ``x_p`` the parents: variables
eliminated later and the separator's). Packed, each conditional is its augmented matrix
``[R S d]`` (row-major, float64, in one flat array) and the keys of its frontals and parents.
The data array can be written to a file and read back for the solve, so that the sections'
eliminations need not stay on the heap nor be eliminated again when they do not fit the batch's
budget. The solve is the same arithmetic as gtsam's ``GaussianConditional::solve`` (``rhs = d -
S x_p``, then back substitution through ``R``) in another summation order, so the step agrees
with ``GaussianBayesNet.optimize`` to rounding (about 1e-15 relative).

Keys are gtsam keys; the values are steps (tangent vectors) in the variables' own coordinates.
"""

from __future__ import annotations

import os
import tempfile
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numba as nb
import numpy as np
from numpy.typing import NDArray

from slam.backend.graph import key_dim

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class PackedNet:
    """The conditionals of a Bayes net (see the module doc), in elimination order.

    ``frontals[fptr[j]:fptr[j + 1]]`` are conditional ``j``'s frontal keys, ``parents[pptr[j]:
    pptr[j + 1]]`` its parents; ``dims`` maps every key that occurs to its dimension (``keys``
    sorted, ``key_dims`` alongside); conditional ``j``'s ``[R S d]`` is ``data[mptr[j]:mptr[j + 1]]``
    (rows = its frontals' dimension, row-major). ``data`` and ``parents`` are None while they lie
    in ``path`` (the matrices, then the parents' keys): the parents are a section's largest index
    array, one key per parent per conditional, and what a spilled net keeps in memory should not
    grow with the walk."""

    frontals: IntArray
    fptr: IntArray
    parents: IntArray | None
    pptr: IntArray
    keys: IntArray
    key_dims: IntArray
    mptr: IntArray
    data: FloatArray | None
    path: Path | None = None

    @property
    def nbytes(self) -> int:
        """Bytes of the matrices (in memory or on disk)."""
        return 8 * int(self.mptr[-1])

    @property
    def index_bytes(self) -> int:
        """Bytes of the index arrays in memory (the parents' keys while they are not on disk)."""
        held = [self.frontals, self.fptr, self.pptr, self.keys, self.key_dims, self.mptr]
        if self.parents is not None:
            held.append(self.parents)
        return sum(int(a.nbytes) for a in held)

    @property
    def held_bytes(self) -> int:
        """Bytes this net holds in memory: its index, and its matrices unless they are on disk."""
        return self.index_bytes + (0 if self.data is None else self.nbytes)

    def spill(self, folder: Path) -> None:
        """Move the matrices and the parents' keys to a new file in ``folder`` (removed when this
        object is collected)."""
        if self.data is None:
            return
        assert self.parents is not None
        fd, name = tempfile.mkstemp(prefix="net_", suffix=".f64", dir=folder)
        with os.fdopen(fd, "wb") as f:
            f.write(np.ascontiguousarray(self.data).tobytes())
            f.write(np.ascontiguousarray(self.parents, dtype=np.int64).tobytes())
        self.path, self.data, self.parents = Path(name), None, None
        weakref.finalize(self, Path(name).unlink, True)  # kept alive by weakref's registry

    def matrices(self) -> FloatArray:
        """The matrices, from memory or read from the file (a copy that the caller lets go)."""
        if self.data is not None:
            return self.data
        assert self.path is not None
        return np.fromfile(self.path, dtype=np.float64, count=int(self.mptr[-1]))

    def parent_keys(self) -> IntArray:
        """The parents' keys (``pptr`` indexes them), from memory or read from the file (a copy
        that the caller lets go)."""
        if self.parents is not None:
            return self.parents
        assert self.path is not None
        return np.fromfile(self.path, dtype=np.int64, count=int(self.pptr[-1]), offset=self.nbytes)


def pack(bn: gtsam.GaussianBayesNet, dim: Callable[[int], int] = key_dim) -> PackedNet:
    """The conditionals of ``bn`` packed (see :class:`PackedNet`); ``dim`` a variable's dimension
    by key (every key of ``bn``)."""
    n = bn.size()
    conds = [bn.at(j) for j in range(n)]
    sizes = np.array([int(c.rows()) * int(c.cols()) for c in conds], dtype=np.int64)
    mptr = np.concatenate(([0], np.cumsum(sizes))).astype(np.int64)
    data = np.empty(int(mptr[-1]))  # filled in place: no second copy of the matrices
    frontals: list[IntArray] = []
    parents: list[IntArray] = []  # numpy rows, not Python ints: a section's parents run to millions
    fptr, pptr = np.zeros(n + 1, dtype=np.int64), np.zeros(n + 1, dtype=np.int64)
    for j, c in enumerate(conds):
        ks = np.array(c.keys(), dtype=np.int64)
        R = np.asarray(c.R())
        rows, nf, acc = R.shape[0], 0, 0
        while acc < rows:  # the leading keys whose dimensions make up R's rows are the frontals
            acc += dim(int(ks[nf]))
            nf += 1
        if acc != rows:
            raise ValueError(f"pack: conditional {j}'s R has {rows} rows, its frontals {acc} dimensions")
        frontals.append(ks[:nf])
        parents.append(ks[nf:])
        fptr[j + 1] = fptr[j] + nf
        pptr[j + 1] = pptr[j] + ks.shape[0] - nf
        aug = data[mptr[j]:mptr[j + 1]].reshape(rows, -1)
        aug[:, :rows] = R
        if ks.shape[0] > nf:
            aug[:, rows:-1] = c.S()
        aug[:, -1] = c.d()
    f_all = np.concatenate(frontals) if frontals else np.zeros(0, dtype=np.int64)
    p_all = np.concatenate(parents) if parents else np.zeros(0, dtype=np.int64)
    all_keys = np.unique(np.concatenate((f_all, p_all)))
    return PackedNet(f_all, fptr, p_all, pptr, all_keys,
                     np.array([dim(int(k)) for k in all_keys.tolist()], dtype=np.int64), mptr, data)


def solve(net: PackedNet, given: gtsam.VectorValues) -> list[tuple[int, FloatArray]]:
    """The frontal variables' values given the parents' that no conditional solves (``given``:
    the separator's step), by back substitution from the last conditional to the first. Returns
    ``(key, value)`` per frontal key in elimination order. A singular ``R`` (a zero on its
    diagonal) is a RuntimeError, as gtsam's indeterminate system."""
    offsets = np.concatenate(([0], np.cumsum(net.key_dims)))
    x = np.zeros(int(offsets[-1]))
    f_slot = np.searchsorted(net.keys, net.frontals)
    frontal = np.zeros(net.keys.shape[0], dtype=np.bool_)
    frontal[f_slot] = True
    for i in np.flatnonzero(~frontal).tolist():
        k = int(net.keys[i])
        if not given.exists(k):
            raise ValueError(f"packed net: no value given for parent {gtsam.DefaultKeyFormatter(k)}")
        x[offsets[i]:offsets[i + 1]] = given.at(k)
    p_slot = np.searchsorted(net.keys, net.parent_keys())
    ok = _back_substitute(net.fptr, net.pptr, f_slot, p_slot, offsets, net.key_dims, net.mptr, net.matrices(), x)
    if ok >= 0:
        raise RuntimeError(f"indeterminate system at conditional {ok} "
                           f"({gtsam.DefaultKeyFormatter(int(net.frontals[net.fptr[ok]]))})")
    return [(int(k), x[offsets[s]:offsets[s + 1]].copy()) for k, s in zip(net.frontals.tolist(), f_slot.tolist(),
                                                                            strict=True)]


@nb.njit(cache=True)
def _back_substitute(fptr: IntArray, pptr: IntArray, f_slot: IntArray, p_slot: IntArray, offsets: IntArray,
                     key_dims: IntArray, mptr: IntArray, data: FloatArray, x: FloatArray) -> int:
    """Solve every conditional in reverse elimination order into ``x`` (indexed by ``offsets``
    of the keys' slots). Returns -1, or the index of a conditional with a singular ``R``."""
    n = fptr.shape[0] - 1
    for j in range(n - 1, -1, -1):
        rows = 0
        for s in f_slot[fptr[j]:fptr[j + 1]]:
            rows += key_dims[s]
        cols = int((mptr[j + 1] - mptr[j]) // rows)
        m = data[mptr[j]:mptr[j + 1]].reshape(rows, cols)
        rhs = m[:, cols - 1].copy()
        c = rows
        for s in p_slot[pptr[j]:pptr[j + 1]]:
            o = offsets[s]
            for q in range(key_dims[s]):
                v = x[o + q]
                for r in range(rows):
                    rhs[r] -= m[r, c] * v
                c += 1
        sol = np.zeros(rows)
        for r in range(rows - 1, -1, -1):
            acc = rhs[r]
            for q in range(r + 1, rows):
                acc -= m[r, q] * sol[q]
            if m[r, r] == 0.0 or not np.isfinite(acc):
                return j
            sol[r] = acc / m[r, r]
        c = 0
        for s in f_slot[fptr[j]:fptr[j + 1]]:
            o = offsets[s]
            for q in range(key_dims[s]):
                x[o + q] = sol[c]
                c += 1
    return -1
