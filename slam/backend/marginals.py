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
    if table is not None:
        table.at(values)
    try:
        lin = graph.linearize(values)
    finally:
        if table is not None:
            table.at(None)
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
