"""Marginal covariances of many variables of a graph from one elimination.

``gtsam.Marginals`` eliminates the graph in its own (COLAMD) order and then answers each
variable's marginal from the Bayes tree, walking from its clique to the root; for the ~150 planes
of a 10-minute walk, among ~36,000 variables, the walks cost as much as the elimination. With the
wanted variables ordered last they end in the root clique, whose conditional ``R`` has no
parents: their joint marginal information is ``R^T R``, and every marginal covariance is a block
of ``R^-1 R^-T`` (one dense inverse of the root).
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from slam.backend.factors import PlaneTable

FloatArray = NDArray[np.float64]


def root_marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, keys: Sequence[int],
                   table: PlaneTable | None = None) -> dict[int, FloatArray] | None:
    """Marginal covariances (in each variable's tangent coordinates) of ``keys`` at ``values``,
    from one elimination of ``graph`` with them ordered last (``table``: the plane table its
    interval factors read while it is linearised). None when that cannot give them all: the
    system is singular (an indeterminate variable), or the wanted variables do not all end in
    one root clique (they lie in pieces of the graph that share no variable); the caller then
    asks ``gtsam.Marginals``."""
    wanted = [int(k) for k in keys]
    if not wanted:
        return {}
    lin = _linearize(graph, values, table)
    order = gtsam.Ordering.ColamdConstrainedLastGaussianFactorGraph(lin, gtsam.KeyVector(wanted))
    try:
        tree = lin.eliminateMultifrontal(order)
    except RuntimeError:  # indeterminate
        return None
    cond = next((c for c in (r.conditional() for r in tree.roots()) if set(wanted) <= {int(k) for k in c.keys()}),
                None)
    if cond is None or cond.get_model() is not None:
        return None
    root_keys = [int(k) for k in cond.keys()]
    R = np.asarray(cond.R())
    try:
        R_inv = scipy.linalg.solve_triangular(R, np.eye(R.shape[0]), lower=False, check_finite=True)
    except (np.linalg.LinAlgError, ValueError):
        return None
    dims = values.dims()
    start = np.cumsum([0] + [int(dims[k]) for k in root_keys])
    where = {k: (int(start[i]), int(start[i + 1])) for i, k in enumerate(root_keys)}
    out: dict[int, FloatArray] = {}
    for k in wanted:
        a, b = where[k]
        rows = R_inv[a:b]
        out[k] = rows @ rows.T
    return out


def dense_marginals(info: FloatArray, spans: Sequence[tuple[int, int]],
                    null_tolerance: float = 1e-11) -> list[FloatArray | None]:
    """Marginal covariances of the coordinate ranges ``spans`` (``[a, b)`` each) of a dense
    information matrix ``info`` (n, n; not changed): blocks of its inverse, by Cholesky. When
    ``info`` is singular (a variable the system leaves indeterminate: a plane whose points were
    all detached, a direction nothing observes), the blocks of its pseudo-inverse instead, and None
    for a span that the null space reaches (an eigenvalue at most ``null_tolerance`` times the
    largest, a component over 1e-6 in the span): only its direction within the null space is
    undetermined, so no covariance is given for it. The others' covariances are exact: a span
    orthogonal to the null space has the same marginal in every completion of the system."""
    n = info.shape[0]
    if n == 0 or not spans:
        return [None] * len(spans)
    if not np.isfinite(info).all():  # LAPACK's behaviour on a non-finite matrix is undefined
        return [None] * len(spans)
    try:
        factor = scipy.linalg.cho_factor(info, lower=True, overwrite_a=False, check_finite=False)
    except np.linalg.LinAlgError:
        factor = None
    out: list[FloatArray | None] = []
    if factor is not None:
        for lo in range(0, len(spans), _CHUNK):  # a chunk of spans' columns of the inverse at a time
            chunk = spans[lo:lo + _CHUNK]
            cols = np.concatenate([np.arange(a, b) for a, b in chunk])
            unit = np.zeros((n, cols.shape[0]))
            unit[cols, np.arange(cols.shape[0])] = 1.0
            inv = scipy.linalg.cho_solve(factor, unit, check_finite=False)[cols]
            at = 0
            for a, b in chunk:
                block = inv[at:at + b - a, at:at + b - a]
                out.append(0.5 * (block + block.T))
                at += b - a
        return out
    w, V = scipy.linalg.eigh(info, check_finite=False)
    null = w <= null_tolerance * max(float(w[-1]), 0.0)
    reach = np.linalg.norm(V[:, null], axis=1) if null.any() else np.zeros(n)
    Vr, wr = V[:, ~null], w[~null]
    for a, b in spans:
        if reach[a:b].max() > 1e-6:
            out.append(None)
            continue
        rows = Vr[a:b] / np.sqrt(wr)
        block = rows @ rows.T
        out.append(0.5 * (block + block.T))
    return out


_CHUNK = 256  # spans whose columns of the inverse are solved at once


def eliminated_marginals(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, keys: Sequence[int],
                         table: PlaneTable | None = None) -> dict[int, FloatArray] | None:
    """Marginal covariances of ``keys`` at ``values`` where :func:`root_marginals` cannot give
    them (a singular system, a graph in pieces): every other variable eliminated onto them, their
    dense information matrix then inverted by :func:`dense_marginals` (a key the system leaves
    indeterminate left out). None when the other variables cannot be eliminated (one of them is
    indeterminate)."""
    wanted = [int(k) for k in keys]
    lin = _linearize(graph, values, table)
    present = {int(k) for k in lin.keyVector()}
    kept = [k for k in wanted if k in present]
    others = sorted(present.difference(kept))
    try:
        rest = lin.eliminatePartialMultifrontal(gtsam.KeyVector(others))[1] if others else lin
    except RuntimeError:
        return None
    dims = values.dims()
    start = np.cumsum([0] + [int(dims[k]) for k in kept])
    info, _ = rest.hessian(gtsam.Ordering(kept))
    covs = dense_marginals(info, [(int(start[i]), int(start[i + 1])) for i in range(len(kept))])
    return {k: c for k, c in zip(kept, covs, strict=True) if c is not None}


def _linearize(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
               table: PlaneTable | None) -> gtsam.GaussianFactorGraph:
    """``graph`` linearised at ``values``, the plane table (if any) serving them meanwhile."""
    if table is not None:
        table.at(values)
    try:
        return graph.linearize(values)
    finally:
        if table is not None:
            table.at(None)
