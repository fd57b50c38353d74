"""The back end's factor index without per-block records: blocks by plane and by knot in compact
id lists (slam.backend.id_lists), the factors of a knot range, and a removed, replaced or merged
block gone from every lookup; iSAM2 keeps the blocks' indices in the columns."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from backend_defaults import backend_defaults
from box_scene import make_scene
from gtsam.symbol_shorthand import P

from slam.backend import Backend, StepReport
from slam.backend.graph import top_knot
from slam.backend.id_lists import IdLists
from slam.backend.incremental import Isam2Solver
from slam.backend.knots import is_imu_keys


def _random_backend(seed: int, knots: int = 12, planes: int = 5, blocks: int = 80, solver: str = "window") -> Backend:
    """Random knots, planes, blocks (some single-pose) and a few non-block factors on planes."""
    rng = np.random.default_rng(seed)
    be = Backend(replace(backend_defaults(), solver=solver))
    T = np.eye(4)
    for i in range(knots):
        T = T.copy()
        T[:3, 3] += rng.normal(size=3) * 0.05
        be.add_pose(0.05 * i, T)
    for j in range(planes):
        n = rng.normal(size=3)
        be.add_plane(j, n / np.linalg.norm(n), rng.normal() * 3.0, vertical=j % 2 == 0, anchor=rng.normal(size=3))
    be.add_parallel(0, 2, 0.01)
    for _ in range(blocks):
        m = int(rng.integers(1, 9))
        alphas = None if rng.uniform() < 0.2 else rng.uniform(0.0, 1.0, m)
        be.add_observations(int(rng.integers(0, knots - 1)), int(rng.integers(0, planes)), rng.normal(size=(m, 3)),
                            alphas, rng.uniform(0.005, 0.03, m))
    return be


def _brute_factors_of_knots(be: Backend, a: int, b: int) -> list[int]:
    """Every live factor id with its highest knot in [a, b], by that knot then id."""
    out = [(top_knot(be.blocks.factor_keys(f)), f) for f in be.blocks.factor_ids().tolist()]
    return [f for top, f in sorted((t, f) for t, f in out if t is not None and a <= t <= b)]


def test_id_lists_keep_order_and_drop_dead_ids_when_rewritten() -> None:
    live = np.ones(1000, dtype=bool)
    lists = IdLists(lambda ids: live[ids])
    lists.add_key(7)
    assert 7 in lists and lists.get(7).shape == (0,) and lists.live(7).shape == (0,)
    for i in range(100):
        lists.append(7 if i % 2 else 8, i)
    assert lists.get(7).tolist() == list(range(1, 100, 2)) and sorted(lists) == [7, 8]
    for i in range(1, 40, 2):  # 20 of 50 dead: not yet rewritten
        live[i] = False
        lists.note_dead(7)
    assert lists.get(7).shape == (50,) and lists.live(7).tolist() == list(range(41, 100, 2))
    for i in range(41, 53, 2):  # 26 of 50 dead: rewritten without them, in order
        live[i] = False
        lists.note_dead(7)
    assert lists.get(7).tolist() == list(range(53, 100, 2))
    lists.append(7, 500)
    assert lists.live(7).tolist() == [*range(53, 100, 2), 500]
    lists.pop(7)
    assert 7 not in lists and lists.get(7).shape == (0,) and len(lists) == 1


@pytest.mark.parametrize("seed", [0, 1])
def test_factors_of_knots_are_every_factor_by_highest_knot(seed: int) -> None:
    be = _random_backend(seed)
    for bid in list(be.blocks.blocks)[::5]:  # new ids for old intervals, dead ids in the lists
        blk = be.block(bid)
        be.blocks.replace(bid, blk.points, blk.alphas, blk.sigmas)
    n = be.num_knots
    for a, b in ((0, n - 1), (3, 7), (n - 1, n - 1), (5, 4)):
        ids, top, is_block = be.blocks.factors_of_knots(a, b)
        assert ids.tolist() == _brute_factors_of_knots(be, a, b)
        assert is_block.tolist() == [be.blocks.cols.has(f) for f in ids.tolist()]
        assert top.tolist() == [top_knot(be.blocks.factor_keys(f)) for f in ids.tolist()]


def test_a_removed_replaced_or_merged_block_leaves_every_lookup() -> None:
    be = _random_backend(2)
    n = be.num_knots
    bids = list(be.blocks.blocks)
    gone, old = bids[3], bids[4]
    knot = be.block(old).knot
    be.remove_observations(gone)
    blk = be.block(old)
    new = be.blocks.replace(old, blk.points[:1], None if blk.alphas is None else blk.alphas[:1], blk.sigmas[:1])
    every = set(be.blocks.factor_ids().tolist())
    all_of_planes = {b for j in be.plane_ids() for b in be.blocks_of_plane(j)}
    for dead in (gone, old):
        assert dead not in be.blocks.blocks and not be.blocks.cols.has(dead) and dead not in be.graph.records and dead not in every
        assert dead not in all_of_planes and dead not in be.blocks.factors_of_knots(0, n - 1)[0].tolist()
        with pytest.raises(ValueError, match="no observation block"):
            be.block(dead)
    assert new in every and new in all_of_planes and be.block(new).knot == knot
    assert all_of_planes == set(be.blocks.blocks) == every - set(be.graph.records)
    # a merge re-keys the dropped plane's blocks (same ids) and forgets the plane
    moved = be.blocks_of_plane(3)
    kept = be.blocks_of_plane(1)
    assert be.merge_planes(1, 3) == len(moved) > 0
    assert 3 not in be.plane_ids() and be.blocks_of_plane(1) == sorted(kept + moved)
    with pytest.raises(ValueError, match="no plane 3"):
        be.blocks_of_plane(3)
    for bid in moved:
        assert be.block(bid).plane_id == 1 and int(P(1)) in be.blocks.factor_keys(bid)
        assert int(P(3)) not in be.blocks.factor_keys(bid)
    graph = be.blocks.whole_graph()
    assert not any(int(P(3)) in graph.at(i).keys() for i in range(graph.size()))
    # a removed plane takes its blocks and ties with it
    on_zero = be.blocks_of_plane(0)
    be.remove_plane(0)
    left = set(be.blocks.factor_ids().tolist())
    assert not left & set(on_zero) and 0 not in be.plane_ids()
    assert not any(int(P(0)) in be.blocks.factor_keys(f) for f in left)
    assert set(be.blocks.blocks) == {b for j in be.plane_ids() for b in be.blocks_of_plane(j)}
    be.batch_optimize(2)  # the whole graph still solves


def test_held_blocks_keep_their_scatters_through_removal_merge_and_release() -> None:
    be = _random_backend(3)
    be.blocks.hold_before(8)
    held = be.blocks.cols.summarized()
    assert held and all(be.blocks.cols.held[b] for b in held)
    total = {j: np.zeros((4, 4)) for j in be.plane_ids()}
    for b, C in held.items():
        total[be.block(b).plane_id] += C
    for j, M in be.blocks.summary.items():
        np.testing.assert_allclose(M, total[j], atol=1e-9)
    b0 = next(iter(held))
    j0 = be.block(b0).plane_id
    be.remove_observations(b0)
    assert b0 not in be.blocks.cols.summarized()
    np.testing.assert_allclose(be.blocks.summary[j0], total[j0] - held[b0], atol=1e-9)
    be.blocks.drop_summaries()
    assert be.blocks.cols.summarized() == {} and be.blocks.cols.n_slots == 0 and not be.blocks.cols.held.any()


def test_isam2_keeps_block_indices_in_the_columns_and_follows_removals() -> None:
    scene = make_scene(duration=1.0, beams=61, sigma_range=0.003, seed=3)
    rng = np.random.default_rng(4)
    be = Backend(replace(backend_defaults(), solver="isam2"))
    for j, (n, d) in enumerate(zip(scene.planes[:, :3], scene.planes[:, 3], strict=True)):
        be.add_plane(j, n + rng.normal(0.0, 0.01, 3), d + rng.normal(0.0, 0.02))
    by_knot: dict[int, list[dict]] = {}
    for b in scene.blocks:
        by_knot.setdefault(b["knot"], []).append(b)
    removed = False
    for i, t in enumerate(scene.knot_times):
        be.add_pose(t, scene.knot_poses[0] if i == 0 else be.predict_pose(t))
        for b in by_knot.get(i - 1, []):
            be.add_observations(b["knot"], b["plane"], b["points_body"], b["alphas"], b["sigmas"])
        if i >= 8:
            assert be.step() == StepReport(True, 0, 0)
            cols = be.blocks.cols
            ids = cols.ids()
            assert (cols.isam[ids] >= 0).all() and be.graph.pending == []
            if not removed:  # a block in iSAM2 removed: its index goes to iSAM2's removals
                bid = int(ids[len(ids) // 2])
                index = int(cols.isam[bid])
                be.remove_observations(bid)
                assert be.graph.pending_removals == [index]
                removed = True
    assert isinstance(be.incremental, Isam2Solver)
    err = np.array([np.linalg.norm(be.pose(i)[:3, 3] - scene.knot_poses[i][:3, 3]) for i in range(be.num_knots)])
    assert err.max() < 0.01


def test_motion_factors_left_behind_are_released_and_rebuilt_the_same() -> None:
    be = _random_backend(4, knots=20)
    graph = be.blocks.whole_graph()
    values = be.graph.used_values(graph)
    be.blocks.planes.at(values)
    before = [graph.at(i).error(values) for i in range(graph.size())]
    be.blocks.planes.at(None)
    be.blocks.hold_before(12)
    released = [f for f, r in be.graph.records.items() if r.factor is None]
    tops = {top_knot(be.graph.records[f].keys) for f in released}
    assert len(released) == 10 and tops == set(range(2, 12))  # knots 2..11's constant-velocity factors
    assert all(r.rebuildable for r in be.graph.records.values() if r.factor is None)
    graph = be.blocks.whole_graph()
    be.blocks.planes.at(values)
    after = [graph.at(i).error(values) for i in range(graph.size())]
    be.blocks.planes.at(None)
    assert after == before
    assert all(be.graph.records[f].factor is None for f in released)  # built for the graph, not kept


def test_imu_and_bias_factors_left_behind_are_released_and_rebuilt_bit_for_bit() -> None:
    rng = np.random.default_rng(9)
    be = Backend(backend_defaults(imu=True))
    T = np.eye(4)
    for i in range(16):
        T = T.copy()
        T[:3, 3] += rng.normal(size=3) * 0.05
        be.add_pose(0.05 * i + 0.001 * i * i, T)
    for i in range(15):
        m = int(rng.integers(3, 12))
        be.add_imu(i, rng.normal(size=(m, 3)) + np.array([0.0, 0.0, 9.81]), rng.normal(size=(m, 3)) * 0.1,
                   rng.uniform(0.002, 0.008, m))
    kept = {f: r.factor for f, r in be.graph.records.items() if r.rebuildable}
    imu = [f for f, fac in kept.items() if isinstance(fac, gtsam.ImuFactor)]
    bias = [f for f, fac in kept.items() if isinstance(fac, gtsam.BetweenFactorConstantBias)]
    assert len(imu) == 15 and len(bias) == 15 and all(is_imu_keys(be.graph.records[f].keys) for f in imu)
    values = be.graph.values
    errors = {f: fac.error(values) for f, fac in kept.items()}
    jacobians = {f: fac.linearize(values).jacobian() for f, fac in kept.items()}
    stats = be.residual_statistics()
    be.blocks.hold_before(10)
    released = {f for f in kept if be.graph.records[f].factor is None}
    assert {top_knot(be.graph.records[f].keys) for f in released & set(imu)} == set(range(1, 10))  # intervals 0..8
    assert {top_knot(be.graph.records[f].keys) for f in released & set(bias)} == set(range(1, 10))
    for f in kept:  # built again (IMU: from the samples and the bias): the same factor to the last bit
        again = be.graph.factor(f)
        assert type(again) is type(kept[f]) and again.error(values) == errors[f]
        A, b = again.linearize(values).jacobian()
        assert np.array_equal(A, jacobians[f][0]) and np.array_equal(b, jacobians[f][1])
    assert be.residual_statistics() == stats  # released IMU factors still counted
    assert all(be.graph.records[f].factor is None for f in released)  # built for the question, not kept
    with pytest.raises(KeyError, match="interval 15"):
        be.knots.imu_samples.of(15)
