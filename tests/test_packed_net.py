"""The packed Bayes net (slam.backend.packed_net) solves as gtsam's, in memory and from disk."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import P, V, X

from slam.backend.packed_net import pack, solve


def _section(rng: np.random.Generator, n_knots: int, n_planes: int, damped: bool = True
             ) -> tuple[gtsam.GaussianFactorGraph, list[int], dict[int, int]]:
    """A random linear graph shaped like a section: poses (6) and velocities (3) along a chain,
    planes (3) seen from several knots; the interior is the knots but the last."""
    graph = gtsam.GaussianFactorGraph()
    dims: dict[int, int] = {}
    for i in range(n_knots):
        dims[X(i)], dims[V(i)] = 6, 3
    for j in range(n_planes):
        dims[P(j)] = 3

    def add(keys: list[int], rows: int) -> None:
        args: list[object] = []
        for k in keys:
            args += [k, rng.normal(size=(rows, dims[k]))]
        graph.add(gtsam.JacobianFactor(*args, rng.normal(size=rows), gtsam.noiseModel.Unit.Create(rows)))

    for i in range(n_knots - 1):
        add([X(i), V(i), X(i + 1)], 9)
        add([V(i), X(i + 1), V(i + 1)], 3)
        for j in rng.choice(n_planes, size=3, replace=False).tolist():
            add([X(i), X(i + 1), P(j)], 4)
    for j in range(n_planes):
        add([P(j)], 3)
    if damped:  # damping rows on every variable, as the batch's
        for k, d in dims.items():
            graph.add(gtsam.JacobianFactor(k, 1e-3 * np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d)))
    interior = [k for i in range(n_knots - 1) for k in (X(i), V(i))]
    return graph, interior, dims


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_packed_solve_matches_gtsam(tmp_path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    graph, interior, dims = _section(rng, 40, 7)
    bn, rest = graph.eliminatePartialSequential(interior)
    sep = rest.optimize()
    want = bn.optimize(sep)
    net = pack(bn, dims.__getitem__)
    assert net.nbytes == 8 * sum(int(bn.at(i).rows()) * int(bn.at(i).cols()) for i in range(bn.size()))
    got = dict(solve(net, sep))
    assert sorted(got) == sorted(interior)
    for k in interior:
        np.testing.assert_allclose(got[k], want.at(k), rtol=1e-11, atol=1e-12)
    parents, held = net.parent_keys().copy(), net.index_bytes
    net.spill(tmp_path)
    assert net.data is None and net.parents is None and net.path is not None and net.path.exists()
    assert net.path.stat().st_size == net.nbytes + parents.nbytes  # the parents' keys on disk too
    assert net.index_bytes == held - parents.nbytes
    assert np.array_equal(net.parent_keys(), parents)
    again = dict(solve(net, sep))
    for k in interior:
        assert np.array_equal(again[k], got[k])  # the same numbers from disk
    del net  # the file goes with the net
    assert not list(tmp_path.iterdir())


def test_packed_solve_names_a_missing_parent() -> None:
    rng = np.random.default_rng(3)
    graph, interior, dims = _section(rng, 6, 3)
    bn, _ = graph.eliminatePartialSequential(interior)
    with pytest.raises(ValueError, match="no value given for parent"):
        solve(pack(bn, dims.__getitem__), gtsam.VectorValues())


def test_packed_solve_singular_is_a_runtime_error() -> None:
    """A zero on R's diagonal is gtsam's indeterminate system, a RuntimeError naming the variable."""
    R = np.eye(3)
    R[1, 1] = 0.0
    bn = gtsam.GaussianBayesNet()
    bn.push_back(gtsam.GaussianConditional(X(0), np.ones(3), R, P(0), np.ones((3, 3)), gtsam.noiseModel.Unit.Create(3)))
    given = gtsam.VectorValues()
    given.insert(P(0), np.zeros(3))
    with pytest.raises(RuntimeError):
        bn.optimize(given)
    with pytest.raises(RuntimeError, match="indeterminate system at conditional 0 \\(x0\\)"):
        solve(pack(bn, {X(0): 3, P(0): 3}.__getitem__), given)
