"""The back end's batched paths against the per-factor / per-block code they replace: the
interval factors served from the solve's table, the summaries of the blocks leaving the window,
the whole graph's factor order and the constant-velocity kernel, all equal bit for bit."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from backend_defaults import backend_defaults
from gtsam.symbol_shorthand import P, X

from slam.backend import Backend
from slam.backend.blocks import BlockStore
from slam.backend.factors import NO_KERNEL, PlaneTable, RobustKernel, point_planes_factor


def _random_pose(rng: np.random.Generator, scale: float = 1.0) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * scale), rng.normal(size=3) * 5.0)


def _backend(seed: int, knots: int = 12, planes: int = 5, blocks: int = 60, single: bool = True) -> Backend:
    """A back end with random knots, planes and blocks (some single-pose, some of one point)."""
    rng = np.random.default_rng(seed)
    be = Backend(backend_defaults())
    T = np.eye(4)
    for i in range(knots):
        step = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.05), rng.normal(size=3) * 0.05).matrix()
        T = T @ step
        be.add_pose(0.05 * i, T)
    for j in range(planes):
        n = rng.normal(size=3)
        be.add_plane(j, n / np.linalg.norm(n), rng.normal() * 3.0, anchor=rng.normal(size=3) * 4.0)
    for _ in range(blocks):
        m = int(rng.integers(1, 12))
        alphas = None if single and rng.uniform() < 0.2 else rng.uniform(0.0, 1.0, m)
        be.add_observations(int(rng.integers(0, knots - 1)), int(rng.integers(0, planes)), rng.normal(size=(m, 3)) * 3,
                            alphas, rng.uniform(0.005, 0.03, m))
    return be


def _old_whole_graph(store: BlockStore) -> list[tuple[int, ...]]:
    """The keys of the whole graph's factors in the order of the former per-record loop."""
    groups: dict[int, list[int]] = {}
    out: list[tuple[int, ...]] = []
    cols = store.cols
    for fid in sorted(store.graph.records):
        if cols.has(fid) and cols.two[fid]:
            groups.setdefault(int(cols.knot[fid]), []).append(fid)
        else:
            out.append(tuple(int(k) for k in store.factor(fid).keys()))
    for knot, bids in groups.items():
        out.append(tuple(int(k) for k in store.group_factor(knot, bids).keys()))
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_whole_graph_keeps_the_factor_order(seed: int) -> None:
    be = _backend(seed)
    # replaced blocks get new ids for old intervals: the groups' order is that of their first block
    for bid in list(be.blocks.blocks)[::7]:
        blk = be.block(bid)
        be.blocks.replace(bid, blk.points, blk.alphas, blk.sigmas)
    graph = be.blocks.whole_graph()
    got = [tuple(int(k) for k in graph.at(i).keys()) for i in range(graph.size())]
    assert got == _old_whole_graph(be.blocks)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_summaries_of_many_blocks_are_the_single_ones(seed: int) -> None:
    """``hold_before`` (batched) gives every block's scatter and the planes' sums bit for bit as
    one ``_summarize`` per block in the same order."""
    a, b = _backend(seed), _backend(seed)
    first = 8
    a.blocks.hold_before(first)
    for k in range(b.blocks.summarized_upto, first):  # the former loop
        for fid in b.graph.by_knot.get(k, ()):
            if b.blocks.cols.has(fid) and not b.blocks.cols.held[fid]:
                b.blocks._summarize(fid)
    assert np.array_equal(a.blocks.cols.held, b.blocks.cols.held)
    assert np.array_equal(a.blocks.cols.scatter, b.blocks.cols.scatter)
    assert a.blocks.summary.keys() == b.blocks.summary.keys()
    for j in a.blocks.summary:
        assert np.array_equal(a.blocks.summary[j], b.blocks.summary[j])
    assert a.blocks._open == b.blocks._open


def test_summaries_of_nothing_and_single_pose_blocks_only() -> None:
    be = _backend(4, blocks=0)
    be.blocks.hold_before(5)
    assert be.blocks.summary == {} and be.blocks.summarized_upto == 5
    be = _backend(5, blocks=0)
    be.add_observations(1, 0, np.ones((3, 3)), None, np.full(3, 0.01))
    ref = _backend(5, blocks=0)
    ref.add_observations(1, 0, np.ones((3, 3)), None, np.full(3, 0.01))
    be.blocks.hold_before(5)
    ref.blocks._summarize(next(iter(ref.blocks.blocks)))
    assert np.array_equal(be.blocks.summary[0], ref.blocks.summary[0])


def _jacobian_rows(lin: gtsam.GaussianFactorGraph) -> list[np.ndarray]:
    return [lin.at(i).jacobian()[0] for i in range(lin.size())] + [lin.at(i).jacobian()[1] for i in range(lin.size())]


@pytest.mark.parametrize("kernel", [NO_KERNEL, RobustKernel("cauchy", 2.5), RobustKernel("huber", 1.5)],
                         ids=lambda k: k.name)
def test_interval_factors_from_the_table_are_the_read_ones(kernel: RobustKernel) -> None:
    """Served by a :class:`PlaneTable` (poses and planes by slot) or reading the values: the same
    rows and Jacobians, bit for bit; one point, one plane, many planes."""
    rng = np.random.default_rng(7)
    v = gtsam.Values()
    for i in range(4):
        v.insert(X(i), _random_pose(rng))
    J = 5
    for j in range(J):
        v.insert(P(j), gtsam.OrientedPlane3(gtsam.Unit3(rng.normal(size=3)), rng.normal()))
    table = PlaneTable()
    served, plain = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
    for i, (n, planes) in enumerate([(1, [3]), (7, [0]), (40, [4, 1, 2, 0])]):
        idx = np.concatenate((np.arange(len(planes)), rng.integers(0, len(planes), n - len(planes))))
        args = ([P(j) for j in planes], idx, rng.normal(size=(n, 3)) * 3, rng.uniform(0, 1, n),
                rng.uniform(0.01, 0.05, n), kernel, rng.normal(size=(len(planes), 3)))
        served.add(point_planes_factor(X(i), X(i + 1), *args, table=table))
        plain.add(point_planes_factor(X(i), X(i + 1), *args))
    table.at(v)
    lin_s, err_s = served.linearize(v), served.error(v)
    table.at(None)
    lin_p, err_p = plain.linearize(v), plain.error(v)
    assert err_s == err_p
    for a, b in zip(_jacobian_rows(lin_s), _jacobian_rows(lin_p), strict=True):
        assert np.array_equal(a, b)
    # not served: the factor reads the values itself (the same numbers again)
    lin_u = served.linearize(v)
    for a, b in zip(_jacobian_rows(lin_u), _jacobian_rows(lin_p), strict=True):
        assert np.array_equal(a, b)


def test_plane_table_slots_survive_growth() -> None:
    table = PlaneTable()
    first = table.slots_of([P(3), P(1)]).tolist()
    many = table.slots_of([P(j) for j in range(200)])
    assert first == [0, 1] and many[3] == 0 and many[1] == 1 and len(set(many.tolist())) == 200
    v = gtsam.Values()
    v.insert(P(150), gtsam.OrientedPlane3(gtsam.Unit3(np.array([0.0, 0.6, 0.8])), 2.0))
    v.insert(X(3000), gtsam.Pose3(gtsam.Rot3.Rz(0.3), np.array([1.0, 2.0, 3.0])))
    table.at(v)
    n, d, _ = table.get(P(150))
    assert np.allclose(n, [0.0, 0.6, 0.8]) and d == 2.0
    assert np.array_equal(table.t[3000], [1.0, 2.0, 3.0])
