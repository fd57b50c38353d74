"""Exact plane summaries of held observation blocks (slam.backend.plane_summary) and the fixed-lag window
that uses them (slam.backend.incremental.WindowSolver)."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
from backend_defaults import backend_defaults
from box_scene import make_scene, perturb_pose
from gtsam.symbol_shorthand import P, X

from slam.backend import Backend
from slam.backend.factors import NO_KERNEL, RobustKernel
from slam.backend.incremental import WindowSolver
from slam.backend.plane_summary import plane_summary_factor, scatter, shift_anchor, square_root
from slam.backend.solver import damped_gauss_newton

DEG = np.pi / 180.0


def _random_plane_points(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, float]:
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    d = -2.0
    pts = rng.uniform(-3, 3, (n, 3))
    pts -= np.outer(pts @ normal + d, normal)  # onto the plane ...
    pts += np.outer(rng.normal(0, 0.003, n), normal)  # ... plus noise
    return pts, normal, d


def test_summary_error_is_the_weighted_sum_of_squares() -> None:
    rng = np.random.default_rng(0)
    pts, _, _ = _random_plane_points(rng, 200)
    w = rng.uniform(0.5, 2.0, 200) / 0.003**2
    anchor = np.array([1.0, -2.0, 0.5])
    M = scatter(pts, anchor, w)
    S = square_root(M)
    np.testing.assert_allclose(S.T @ S, M, rtol=1e-9, atol=1e-6 * np.abs(M).max())
    factor = plane_summary_factor(int(P(0)), M)
    for _ in range(5):  # at planes away from the true one
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        d_local = rng.normal()
        v = gtsam.Values()
        v.insert(P(0), gtsam.OrientedPlane3(gtsam.Unit3(n), d_local))
        expect = 0.5 * float(np.sum(w * ((pts - anchor) @ n + d_local) ** 2))
        assert abs(factor.error(v) - expect) <= 1e-9 * max(expect, 1.0)


def test_summary_jacobian_matches_numerical_differentiation() -> None:
    rng = np.random.default_rng(1)
    pts, n, d = _random_plane_points(rng, 50)
    factor = plane_summary_factor(int(P(3)), scatter(pts, np.zeros(3), np.full(50, 1e4)))
    plane = gtsam.OrientedPlane3(gtsam.Unit3(n + 0.1 * rng.normal(size=3)), d + 0.05)
    v = gtsam.Values()
    v.insert(P(3), plane)
    H = factor.linearize(v)
    A = H.jacobian()[0]  # whitened: the factor is unit-noise
    b0 = factor.unwhitenedError(v)
    num = np.zeros((4, 3))
    h = 1e-7
    for i in range(3):
        dv = np.zeros(3)
        dv[i] = h
        vp = gtsam.Values()
        vp.insert(P(3), plane.retract(dv))
        num[:, i] = (factor.unwhitenedError(vp) - b0) / h
    np.testing.assert_allclose(A, num, rtol=1e-5, atol=1e-5 * np.abs(num).max())


def test_shift_anchor_gives_the_scatter_about_the_new_anchor() -> None:
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(30, 3))
    w = rng.uniform(size=30)
    a, b = np.array([1.0, 2.0, 3.0]), np.array([-4.0, 0.5, 2.0])
    np.testing.assert_allclose(shift_anchor(scatter(pts, a, w), a, b), scatter(pts, b, w), atol=1e-10)


def _window(be: Backend) -> WindowSolver:
    assert isinstance(be.incremental, WindowSolver)
    return be.incremental


def _box_backend(kernel: RobustKernel) -> tuple[Backend, int]:
    scene = make_scene(duration=2.0, beams=61, sigma_range=0.003, seed=4)
    be = Backend(replace(backend_defaults(), kernel=kernel))
    rng = np.random.default_rng(5)
    for i, (t, T) in enumerate(zip(scene.knot_times, scene.knot_poses, strict=True)):
        be.add_pose(t, T if i == 0 else perturb_pose(T, rng, 0.01, 0.3 * DEG))
    for j, (n0, d0) in enumerate(zip(scene.planes[:, :3], scene.planes[:, 3], strict=True)):
        be.add_plane(j, n0 + rng.normal(0.0, 0.01, 3), d0 + rng.normal(0.0, 0.01))
    for blk in scene.blocks:
        be.add_observations(blk["knot"], blk["plane"], blk["points_body"], blk["alphas"], blk["sigmas"])
    return be, be.num_knots // 2


def test_window_with_summaries_equals_the_window_over_every_old_block() -> None:
    """With the old knots held, summarising their blocks changes nothing: the window solve gives
    the solution of the same window with every old block in the graph as it is."""
    be, first = _box_backend(NO_KERNEL)
    be.batch_optimize(3)
    rng = np.random.default_rng(6)
    for k in range(first, be.num_knots):
        be.graph.values.update(X(k), gtsam.Pose3(perturb_pose(be.pose(k), rng, 0.02, 0.5 * DEG)))
    # the reference: every factor touching the window's knots or its planes, older knots held
    active = {int(X(k)) for k in range(first, be.num_knots)} | {int(P(j)) for j in be.plane_ids()}
    graph = gtsam.NonlinearFactorGraph()
    used: set[int] = set()
    for fid in be.blocks.factor_ids().tolist():
        keys = be.blocks.factor_keys(fid)
        if any(k in active for k in keys):
            graph.add(be.blocks.factor(fid))
            used.update(keys)
    values = gtsam.Values()
    for k in used:
        if chr(gtsam.Symbol(k).chr()) == "x":
            values.insert(k, be.graph.values.atPose3(k))
        else:
            values.insert(k, be.graph.values.atOrientedPlane3(k))
    ref, _ = damped_gauss_newton(graph, values, 10, 1e-12, fixed=sorted(used - active))
    s = _window(be).optimize(first, max_iterations=10)
    assert be.blocks.summary, "the old blocks were summarised"
    assert s.final_error < s.initial_error
    for k in range(first, be.num_knots):
        got, want = be.pose(k), ref.atPose3(X(k)).matrix()
        np.testing.assert_allclose(got[:3, 3], want[:3, 3], atol=1e-6)
        np.testing.assert_allclose(got[:3, :3], want[:3, :3], atol=1e-6)
    for j in be.plane_ids():
        n, _ = be.plane(j)
        pl = ref.atOrientedPlane3(P(j))
        assert abs(float(n @ pl.normal().point3()) - 1.0) < 1e-9


def test_summaries_follow_merges_and_removals() -> None:
    be, first = _box_backend(RobustKernel("huber", 2.5))
    _window(be).optimize(first, 4)
    ids = be.plane_ids()
    j = ids[0]
    M = be.blocks.summary[j].copy()
    old = [b for b in be.blocks_of_plane(j) if b in be.blocks.cols.summarized()]
    be.remove_observations(old[0])
    assert not np.allclose(be.blocks.summary[j], M)
    # a duplicate plane of j, made of one late block, merged into j: the summaries add up
    n, d = be.plane(j)
    be.add_plane(77, n, d, anchor=np.array([3.0, 1.0, 0.5]))
    blk = be.block(old[1])
    be.add_observations(blk.knot, 77, blk.points, blk.alphas, blk.sigmas)  # an old knot: summarised at once
    before = be.blocks.summary[j] + shift_anchor(be.blocks.summary[77], be.graph.anchors[77], be.graph.anchors[j])
    be.merge_planes(j, 77)
    np.testing.assert_allclose(be.blocks.summary[j], before, rtol=1e-12, atol=1e-9)
    assert 77 not in be.blocks.summary
    be.batch_optimize(1)
    assert not be.blocks.summary and not be.blocks.cols.summarized()  # the held poses moved: summaries dropped


def test_coalesced_blocks_cost_what_the_separate_blocks_cost() -> None:
    scene = make_scene(duration=1.0, beams=61, sigma_range=0.003, seed=7)
    rng = np.random.default_rng(8)
    guesses = [T if i == 0 else perturb_pose(T, rng, 0.01, 0.3 * DEG) for i, T in enumerate(scene.knot_poses)]
    errors, counts = [], []
    for coalesce in (False, True):
        be = Backend(replace(backend_defaults(), coalesce_blocks=coalesce))
        for t, T in zip(scene.knot_times, guesses, strict=True):
            be.add_pose(t, T)
        for j, (n0, d0) in enumerate(zip(scene.planes[:, :3], scene.planes[:, 3], strict=True)):
            be.add_plane(j, n0, d0 + 0.01)
        for blk in scene.blocks:  # each block handed over in two halves
            h = blk["points_body"].shape[0] // 2
            for sl in (slice(0, h), slice(h, None)):
                if blk["points_body"][sl].shape[0]:
                    al = None if blk["alphas"] is None else blk["alphas"][sl]
                    be.add_observations(blk["knot"], blk["plane"], blk["points_body"][sl], al, blk["sigmas"][sl])
        errors.append(be.error())
        counts.append(len(be.blocks.blocks))
    assert counts[1] <= len(scene.blocks) < counts[0]
    assert abs(errors[0] - errors[1]) <= 1e-9 * errors[0]
