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
from slam.backend.factors import (
    NO_KERNEL,
    PlaneTable,
    RobustKernel,
    check_block,
    point_planes_factor,
)
from slam.motion import MotionPriorConfig, constant_velocity_factor, constant_velocity_terms


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
    for fid in store.factor_ids().tolist():
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
        for fid in b.blocks.by_knot.get(k).tolist():
            if b.blocks.cols.has(fid) and not b.blocks.cols.held[fid]:
                b.blocks._summarize(fid)
    assert np.array_equal(a.blocks.cols.held, b.blocks.cols.held)
    sa, sb = a.blocks.cols.summarized(), b.blocks.cols.summarized()
    assert sa.keys() == sb.keys() and all(np.array_equal(sa[k], sb[k]) for k in sa)
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


def test_block_checks_fast_path_agrees_with_the_checks() -> None:
    """A two-pose block's compiled check accepts what the per-check path accepts, returns the same
    arrays, and anything it rejects gets the per-check path's message."""
    rng = np.random.default_rng(9)
    n = 6
    pts, al, sg = rng.normal(size=(n, 3)), rng.uniform(0, 1, n), rng.uniform(0.01, 0.02, n)
    p, a, s = check_block(pts, al, sg, True, "points_body")
    p2, a2, s2 = check_block(pts.tolist(), al.tolist(), sg.tolist(), True, "points_body")  # per-check path
    assert np.array_equal(p, p2) and a is not None and a2 is not None and np.array_equal(a, a2)
    assert np.array_equal(s, s2) and s is sg
    edges = [(0.0, 1.0), (1.0, 0.0)]
    for a0, a1 in edges:  # alphas at the bounds are fine
        al2 = al.copy()
        al2[0], al2[-1] = a0, a1
        check_block(pts, al2, sg, True, "points_body")
    bad = [
        ("points_body: contains NaN", lambda P, A, S: P.__setitem__((2, 1), np.nan)),
        ("points_body: contains NaN", lambda P, A, S: P.__setitem__((0, 0), np.inf)),
        ("sigmas: expected", lambda P, A, S: S.__setitem__(3, 0.0)),
        ("sigmas: expected", lambda P, A, S: S.__setitem__(1, np.nan)),
        ("alphas: expected", lambda P, A, S: A.__setitem__(4, 1.0 + 1e-12)),
        ("alphas: expected", lambda P, A, S: A.__setitem__(0, np.nan)),
    ]
    for msg, spoil in bad:
        P_, A_, S_ = pts.copy(), al.copy(), sg.copy()
        spoil(P_, A_, S_)
        with pytest.raises(ValueError, match=msg.replace("(", r"\(")):
            check_block(P_, A_, S_, True, "points_body")
    with pytest.raises(ValueError, match="alphas: expected"):
        check_block(pts, al[:-1], sg, True, "points_body")


def test_constant_velocity_factor_is_its_terms() -> None:
    """The factor's residual and Jacobians (from gtsam's derivative outputs) are
    :func:`constant_velocity_terms` bit for bit, from standing still to fast turns."""
    rng = np.random.default_rng(11)
    cfg = MotionPriorConfig(0.7, 0.2)
    for scale in (0.0, 1e-9, 1e-4, 0.02, 0.4, 2.5):
        v = gtsam.Values()
        T = _random_pose(rng)
        for i in range(3):
            v.insert(X(i), T)
            T = T.compose(gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * scale), rng.normal(size=3) * scale))
        dt1, dt2 = 0.05, float(rng.uniform(0.02, 0.08))
        f = constant_velocity_factor(X(0), X(1), X(2), dt1, dt2, cfg)
        r = constant_velocity_terms(v.atPose3(X(0)), v.atPose3(X(1)), v.atPose3(X(2)), dt1, dt2)[0]
        assert np.array_equal(f.unwhitenedError(v), r)
        g = gtsam.NonlinearFactorGraph()
        g.add(f)
        ref = gtsam.NonlinearFactorGraph()
        ref.add(gtsam.CustomFactor(f.noiseModel(), [X(0), X(1), X(2)],
                                   lambda this, vv, H, a=dt1, b=dt2: _terms_into(vv, H, a, b)))
        A, b = g.linearize(v).jacobian()
        A_ref, b_ref = ref.linearize(v).jacobian()
        assert np.array_equal(A, A_ref) and np.array_equal(b, b_ref)
        assert g.error(v) == ref.error(v)


def _terms_into(v: gtsam.Values, H: list | None, dt1: float, dt2: float) -> np.ndarray:
    r, H0, H1, H2 = constant_velocity_terms(v.atPose3(X(0)), v.atPose3(X(1)), v.atPose3(X(2)), dt1, dt2)
    if H is not None:
        H[0], H[1], H[2] = H0, H1, H2
    return r


def _old_trim(be: Backend, max_whitened: float, min_distance: float) -> tuple[int, int]:
    """The former block-by-block trim (reference)."""
    n_points = n_blocks = 0
    for bid, e in be.blocks.all_whitened_residuals():
        blk = be.blocks.blocks[bid]
        out = (np.abs(e) > max_whitened) & (np.abs(e) * blk.sigmas > min_distance)
        if not out.any():
            continue
        n_points += int(out.sum())
        n_blocks += 1
        keep = ~out
        if not keep.any():
            be.blocks.remove(bid)
        else:
            be.blocks.replace(bid, blk.points[keep], None if blk.alphas is None else blk.alphas[keep],
                              blk.sigmas[keep])
    return n_points, n_blocks


@pytest.mark.parametrize(("seed", "max_whitened", "min_distance"), [(0, 30.0, 0.01), (1, 100.0, 0.0),
                                                                     (2, 1e9, 0.0), (3, 1e-3, 0.0)])
def test_trim_in_one_pass_is_the_block_by_block_trim(seed: int, max_whitened: float, min_distance: float) -> None:
    a, b = _backend(seed, blocks=80), _backend(seed, blocks=80)
    got = a.trim_observations(max_whitened, min_distance)
    assert got == _old_trim(b, max_whitened, min_distance)
    assert list(a.blocks.blocks) == list(b.blocks.blocks)
    for bid in a.blocks.blocks:
        x, y = a.block(bid), b.block(bid)
        assert np.array_equal(x.points, y.points) and np.array_equal(x.sigmas, y.sigmas)


def test_trim_of_no_blocks() -> None:
    assert _backend(6, blocks=0).trim_observations(3.0, 0.01) == (0, 0)


@pytest.mark.parametrize("extra_pose", [False, True])
def test_plane_table_serves_every_knot(extra_pose: bool) -> None:
    """The table's rotations and positions are each knot's ``atPose3(X(i)).matrix()`` bit for bit,
    read in one call (or one by one when other Pose3 variables are present)."""
    rng = np.random.default_rng(21)
    v = gtsam.Values()
    knots = [17, 2, 400, 3, 0, 58]
    for i in knots:
        v.insert(X(i), _random_pose(rng))
    if extra_pose:
        v.insert(gtsam.symbol("e", 1), _random_pose(rng))
    v.insert(P(4), gtsam.OrientedPlane3(gtsam.Unit3(rng.normal(size=3)), 0.5))
    table = PlaneTable()
    table.at(v)
    for i in knots:
        M = v.atPose3(X(i)).matrix()
        assert np.array_equal(table.R[i], M[:3, :3]) and np.array_equal(table.t[i], M[:3, 3])


def _old_perpendicular_error(this: gtsam.CustomFactor, v: gtsam.Values, H: list | None) -> np.ndarray:
    ua = v.atOrientedPlane3(this.keys()[0]).normal()
    ub = v.atOrientedPlane3(this.keys()[1]).normal()
    na, nb = ua.point3(), ub.point3()
    if H is not None:
        H[0] = np.array([[*(nb @ ua.basis()), 0.0]])
        H[1] = np.array([[*(na @ ub.basis()), 0.0]])
    return np.array([float(na @ nb)])


def test_perpendicular_tie_rows() -> None:
    """The perpendicular tie's linearisation and error: the former function's bit for bit."""
    from slam.backend.ties import perpendicular_error
    rng = np.random.default_rng(23)
    for _ in range(50):
        v = gtsam.Values()
        v.insert(P(0), gtsam.OrientedPlane3(gtsam.Unit3(rng.normal(size=3)), rng.normal()))
        v.insert(P(1), gtsam.OrientedPlane3(gtsam.Unit3(rng.normal(size=3)), rng.normal()))
        out = []
        for fn in (perpendicular_error, _old_perpendicular_error):
            g = gtsam.NonlinearFactorGraph()
            g.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, 0.01), [P(0), P(1)], fn))
            out.append((*g.linearize(v).jacobian(), g.error(v)))
        (A, b, e), (A0, b0, e0) = out
        assert np.array_equal(A, A0) and np.array_equal(b, b0) and e == e0
