"""The final batch of a long walk solved one section at a time (slam/backend/sections.py): the
plan, the separator, and that its steps, estimate, error and plane covariances are the
whole-graph batch's, on a synthetic box room."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from backend_defaults import backend_defaults
from box_scene import Scene, make_scene, perturbed_backend

from slam.backend import Backend, BackendConfig
from slam.backend.sections import plan_sections, separator_knots
from slam.backend.solver import DAMPING, damping_rows
from slam.config import SlamConfig

DEG = np.pi / 180.0


@pytest.fixture(scope="module")
def scene() -> Scene:
    return make_scene(duration=2.0, beams=61, sigma_range=0.003, seed=11)


def _build(scene: Scene, config: BackendConfig, seed: int = 3) -> Backend:
    return perturbed_backend(scene, config, seed)


def _whole_linear_model(be: Backend, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
    """The whole graph linearised at ``values`` with the solves' damping rows."""
    whole = be.blocks.whole_graph()
    be.blocks.planes.at(values)
    try:
        lin = whole.linearize(values)
    finally:
        be.blocks.planes.at(None)
    lin.push_back(damping_rows([(int(k), int(d)) for k, d in values.dims().items()], set(), DAMPING))
    return lin


@pytest.mark.parametrize("n,size", [(10, 20), (100, 20), (101, 20), (7, 1), (1000, 333)])
def test_plan_cuts_every_knot_once(n: int, size: int) -> None:
    plan = plan_sections(n, size)
    assert plan[0][0] == 0 and plan[-1][1] == n
    assert all(a < b <= a + size for a, b in plan)
    assert all(plan[i][1] == plan[i + 1][0] for i in range(len(plan) - 1))  # no gap, no overlap
    assert len(plan) == -(-n // size)
    with pytest.raises(ValueError, match="plan_sections"):
        plan_sections(0, size)


def test_interiors_are_touched_by_their_section_alone(scene: Scene) -> None:
    be = _build(scene, replace(backend_defaults(), batch_section_knots=17, batch_whole_knots=0))
    assert be.sections.needed()
    plan = be.sections.plan()
    sep = separator_knots(plan)
    keys = [{int(k) for k in be.sections.factors(a, b, be.config.kernel).keyVector()} for a, b in plan]
    assert set().union(*keys) == {int(k) for k in be.blocks.whole_graph().keyVector()} - \
        {int(k) for k in be.sections.plane_factors().keyVector()} | set().union(*keys)
    for s, (a, b) in enumerate(plan):
        interior = {k for k in keys[s] if gtsam.Symbol(k).chr() != ord("p") and a <= gtsam.Symbol(k).index() < b
                    and gtsam.Symbol(k).index() not in sep}
        assert interior
        for t, other in enumerate(keys):
            assert t == s or not interior & other


def test_a_walk_up_to_batch_whole_knots_is_solved_whole(scene: Scene) -> None:
    n = len(_build(scene, replace(backend_defaults(), batch_section_knots=17, batch_whole_knots=0)).graph.times)
    assert n > 17
    for whole, needed in ((n - 1, True), (n, False), (n + 100, False)):
        be = _build(scene, replace(backend_defaults(), batch_section_knots=17, batch_whole_knots=whole))
        assert be.sections.needed() == needed
    assert backend_defaults().batch_whole_knots == round(SlamConfig().backend.batch_whole_seconds
                                                         * SlamConfig().trajectory.knot_rate)
    with pytest.raises(ValueError, match="batch_whole_knots"):
        replace(backend_defaults(), batch_whole_knots=-1)


def test_streamed_error_is_the_whole_graphs(scene: Scene) -> None:
    be = _build(scene, replace(backend_defaults(), batch_section_knots=17, batch_whole_knots=0))
    whole = be.batch.error()
    assert whole > 0.0
    assert be.sections.total_error() == pytest.approx(whole, rel=1e-12)
    assert be.error() == pytest.approx(whole, rel=1e-12)


def test_a_sectioned_step_is_the_whole_graphs_step(scene: Scene) -> None:
    be = _build(scene, replace(backend_defaults(), batch_section_knots=23, batch_whole_knots=0))
    values = gtsam.Values(be.graph.values)
    red = be.sections.reduce(values, be.config.kernel, DAMPING)
    delta = be.sections.back_substitute(values, be.config.kernel, DAMPING, red.graph.optimize())
    assert not be.blocks._groups and not be.blocks._factors  # nothing of a section kept
    assert red.error == pytest.approx(be.batch.error(), rel=1e-12)
    lin = _whole_linear_model(be, values)
    ref = lin.optimize()
    for k in values.keys():
        assert np.allclose(delta.at(k), ref.at(k), rtol=1e-7, atol=1e-10), gtsam.DefaultKeyFormatter(k)
    # the same step from the eliminations kept by reduce, without eliminating again
    solved = be.sections.sections_solved
    kept = be.sections.reduce(values, be.config.kernel, DAMPING, keep=True)
    assert kept.nets is not None and len(kept.nets) == len(be.sections.plan())
    assert all(n.data is not None for n in kept.nets) and be.sections.nets_spilled == 0
    again = be.sections.back_substitute(values, be.config.kernel, DAMPING, kept.graph.optimize(), kept.nets)
    assert be.sections.sections_solved == solved + len(be.sections.plan())
    for k in values.keys():
        assert np.array_equal(again.at(k), delta.at(k)), gtsam.DefaultKeyFormatter(k)
    # a memory budget for one section's elimination: the others go to disk and are read back,
    # not eliminated again, to the same step bit for bit
    first = kept.nets[0].nbytes + kept.nets[0].index_bytes
    tight = _build(scene, replace(backend_defaults(), batch_section_knots=23, batch_whole_knots=0, batch_cache_bytes=first))
    some = tight.sections.reduce(values, be.config.kernel, DAMPING, keep=True)
    assert some.nets is not None and some.nets[0].data is not None
    assert all(n.data is None and n.path is not None and n.path.exists() for n in some.nets[1:])
    assert tight.sections.nets_spilled == len(some.nets) - 1
    files = [n.path for n in some.nets[1:]]
    solved = tight.sections.sections_solved
    part = tight.sections.back_substitute(values, be.config.kernel, DAMPING, some.graph.optimize(), some.nets)
    assert tight.sections.sections_solved == solved
    for k in values.keys():
        assert np.array_equal(part.at(k), delta.at(k)), gtsam.DefaultKeyFormatter(k)
    folder = tight.sections._folder
    assert folder is not None and folder.is_dir()
    del some
    assert not any(f.exists() for f in files if f is not None)  # a let-go elimination's file goes with it
    del tight
    import gc
    gc.collect()
    assert not folder.exists()


def test_the_separators_error_at_its_step_is_the_linear_models(scene: Scene) -> None:
    """What the sectioned solve predicts a step to lower the error by (the separator system's
    error at its step, the interiors' conditionals holding) is the whole linear model's."""
    be = _build(scene, replace(backend_defaults(), batch_section_knots=23, batch_whole_knots=0))
    values = gtsam.Values(be.graph.values)
    red = be.sections.reduce(values, be.config.kernel, DAMPING)
    sep = red.graph.optimize()
    lin = _whole_linear_model(be, values)
    ref = lin.optimize()
    assert red.graph.error(sep) == pytest.approx(lin.error(ref), rel=1e-9)
    assert red.graph.error(sep) < 0.9 * red.error  # from the perturbed start the model lowers the error


def test_sectioned_batch_reaches_the_whole_batchs_estimate(scene: Scene) -> None:
    whole = _build(scene, backend_defaults())
    assert not whole.sections.needed()
    s_whole = whole.batch_optimize(graduated=False)
    cut = _build(scene, replace(backend_defaults(), batch_section_knots=20, batch_whole_knots=0))
    s_cut = cut.batch_optimize(graduated=False)
    n_sections = len(cut.sections.plan())
    # one elimination per section and iteration (the kept ones back-substituted), one more at the start
    assert n_sections * s_cut.iterations <= cut.sections.sections_solved <= n_sections * (s_cut.iterations + 1)
    assert s_cut.initial_error == pytest.approx(s_whole.initial_error, rel=1e-9)
    assert s_cut.final_error == pytest.approx(s_whole.final_error, rel=1e-6)
    assert s_cut.iterations == s_whole.iterations
    assert np.abs(cut.poses()[:, :3, 3] - whole.poses()[:, :3, 3]).max() < 1e-7
    _, n_c, d_c = cut.planes()
    _, n_w, d_w = whole.planes()
    assert np.abs(d_c - d_w).max() < 1e-7 and np.abs(n_c - n_w).max() < 1e-8
    # each section's factors were built once and kept through the solve; without the cache they
    # are built at every elimination and error, to the same estimate bit for bit
    assert cut.sections.sections_built == n_sections
    bare = _build(scene, replace(backend_defaults(), batch_section_knots=20, batch_whole_knots=0, batch_cache_bytes=0))
    s_bare = bare.batch_optimize(graduated=False)
    assert bare.sections.sections_built >= bare.sections.sections_solved > n_sections
    assert s_bare.final_error == s_cut.final_error and np.array_equal(bare.poses(), cut.poses())


def test_sectioned_plane_covariances_are_the_whole_graphs(scene: Scene) -> None:
    whole = _build(scene, backend_defaults())
    whole.batch_optimize(graduated=False)
    cut = _build(scene, replace(backend_defaults(), batch_section_knots=40, batch_whole_knots=0))
    cut.batch_optimize(graduated=False)
    for j in range(6):
        c_w, c_s = whole.plane_covariance(j), cut.plane_covariance(j)
        assert np.allclose(c_s, c_w, rtol=1e-5, atol=1e-14), j


def test_the_budget_bounds_eliminations_and_factors_together(scene: Scene) -> None:
    free = _build(scene, replace(backend_defaults(), batch_section_knots=20, batch_whole_knots=0))
    s_free = free.batch_optimize(graduated=False)
    everything = free.sections.peak_kept_bytes  # all eliminations and all factors
    assert everything > 0 and free.sections.peak_separator_bytes > 0
    budget = everything // 2
    bound = _build(scene, replace(backend_defaults(), batch_section_knots=20, batch_whole_knots=0, batch_cache_bytes=budget))
    s_bound = bound.batch_optimize(graduated=False)
    assert 0 < bound.sections.peak_kept_bytes <= budget
    assert 0 < free.sections.largest_net_bytes <= everything
    assert s_bound.final_error == s_free.final_error and np.array_equal(bound.poses(), free.poses())
    # the factors come first: a budget for exactly all of them caches them all, and every
    # elimination goes to disk (the same estimate, no elimination made twice)
    free.sections._caching = True
    for a, b in free.sections.plan():
        free.sections.factors(a, b, free.config.kernel)
    all_factors = free.sections._cache_bytes
    free.sections._caching = False
    free.sections.clear_cache()
    nets = free.sections.reduce(gtsam.Values(free.graph.values), free.config.kernel, DAMPING, keep=True).nets
    assert nets is not None
    # what stays in memory of an elimination on disk: its index without the parents' keys
    indices = sum(n.index_bytes - (0 if n.parents is None else n.parents.nbytes) for n in nets)
    tight = _build(scene, replace(backend_defaults(), batch_section_knots=20, batch_whole_knots=0,
                                  batch_cache_bytes=all_factors + indices))
    s_tight = tight.batch_optimize(graduated=False)
    n_sections = len(tight.sections.plan())
    assert tight.sections.sections_built == n_sections  # each built once
    assert tight.sections.nets_spilled == tight.sections.sections_solved > 0  # every elimination on disk
    assert tight.sections.sections_solved <= n_sections * (s_tight.iterations + 1)
    assert s_tight.final_error == s_free.final_error and np.array_equal(tight.poses(), free.poses())
    assert tight.sections.peak_kept_bytes <= all_factors + indices
    # a budget with room for the eliminations as well keeps them in memory
    assert free.sections.nets_spilled == 0


def test_plane_covariances_in_chunks_are_the_same(scene: Scene, monkeypatch: pytest.MonkeyPatch) -> None:
    """The inverse's columns solved a few planes at a time (the hour's separator is large) give
    the covariances of one solve for all planes."""
    import slam.backend.marginals as marginals

    cut = _build(scene, replace(backend_defaults(), batch_section_knots=40, batch_whole_knots=0))
    cut.batch_optimize(graduated=False)
    whole = cut.sections.plane_covariances()
    monkeypatch.setattr(marginals, "_CHUNK", 2)
    parts = cut.sections.plane_covariances()
    assert sorted(parts) == sorted(whole) and len(whole) >= 5
    for j, c in whole.items():
        np.testing.assert_allclose(parts[j], c, rtol=1e-12, atol=1e-18)


def _with_local_plane(scene: Scene, config: BackendConfig, last_knot: int) -> Backend:
    """The scene's backend with plane 99: a second copy of plane 2 seen only up to ``last_knot``."""
    be = _build(scene, config)
    n0, d0 = scene.planes[2, :3], scene.planes[2, 3]
    be.add_plane(99, n0 + 0.01, d0 + 0.01)
    for b in scene.blocks:
        if b["plane"] == 2 and b["knot"] < last_knot:
            be.add_observations(b["knot"], 99, b["points_body"], b["alphas"], b["sigmas"])
    return be


def test_a_plane_one_section_sees_is_eliminated_with_it(scene: Scene) -> None:
    """A plane seen from one section only (an edge, a room walked once) is that section's
    interior, not the separator's: the same step, estimate and covariances as the whole graph's,
    with a smaller separator system."""
    cfg = replace(backend_defaults(), batch_section_knots=23, batch_whole_knots=0)
    be = _with_local_plane(scene, cfg, 15)
    plan = be.sections.plan()
    assert plan[0][1] > 15 and len(plan) > 2
    p99 = int(gtsam.symbol("p", 99))
    assert be.sections.local_planes(plan) == {p99: 0}  # the room's planes are seen from every section
    assert be.sections.local_planes(plan, keep_planes=[99]) == {} and be.sections.local_planes(plan, None) == {}
    values = gtsam.Values(be.graph.values)
    red = be.sections.reduce(values, be.config.kernel, DAMPING)
    assert p99 not in {int(k) for k in red.graph.keyVector()}
    held = be.sections.reduce(values, be.config.kernel, DAMPING, keep_planes=None)
    assert p99 in {int(k) for k in held.graph.keyVector()}
    assert red.error == pytest.approx(held.error, rel=1e-12)
    delta = be.sections.back_substitute(values, be.config.kernel, DAMPING, red.graph.optimize())
    ref = be.sections.back_substitute(values, be.config.kernel, DAMPING, held.graph.optimize(), keep_planes=None)
    for k in values.keys():
        assert np.allclose(delta.at(k), ref.at(k), rtol=1e-7, atol=1e-10), gtsam.DefaultKeyFormatter(k)
    # the solve and the covariances, against the whole graph's
    whole = _with_local_plane(scene, backend_defaults(), 15)
    whole.batch_optimize(graduated=False)
    s_cut = be.batch_optimize(graduated=False)
    assert s_cut.iterations > 0
    assert np.abs(be.poses()[:, :3, 3] - whole.poses()[:, :3, 3]).max() < 1e-7
    cov = be.plane_covariances([0, 3, 99])
    assert sorted(cov) == [0, 3, 99]
    for j in (0, 3, 99):
        assert np.allclose(cov[j], whole.plane_covariance(j), rtol=1e-5, atol=1e-14), j
    assert sorted(be.plane_covariances([0, 12345])) == [0]  # an unknown plane has none
    assert sorted(be.sections.plane_covariances([0])) == [0]  # only the planes asked for
    assert 99 in be.sections.plane_covariances()  # None: every plane
    # a plane tied to another (a factor on planes alone) stays in the separator
    tied = _with_local_plane(scene, cfg, 15)
    tied.add_parallel(2, 99, 0.01)
    assert tied.sections.local_planes(tied.sections.plan()) == {}


@pytest.mark.parametrize("sectioned", [True, False])
def test_a_plane_the_system_leaves_indeterminate_has_no_covariance(scene: Scene, sectioned: bool) -> None:
    """A plane seen by two points only (its third direction undetermined: the separator's, or
    the whole graph's, system is singular) is left out of the covariances; the others still get
    theirs, no error raised."""
    cfg = replace(backend_defaults(), batch_section_knots=23, batch_whole_knots=0) if sectioned else backend_defaults()
    be = _build(scene, cfg)
    assert be.sections.needed() == sectioned
    n0, d0 = scene.planes[2, :3], scene.planes[2, 3]
    be.add_plane(98, n0, d0 + 0.05)
    b = next(b for b in scene.blocks if b["plane"] == 2 and b["alphas"] is not None)
    be.add_observations(b["knot"], 98, b["points_body"][:2], b["alphas"][:2], b["sigmas"][:2])
    be.batch_optimize(graduated=False)
    covs = be.plane_covariances([*range(len(scene.planes)), 98])
    assert 98 not in covs
    assert set(covs) == set(range(len(scene.planes)))
    assert all(np.all(np.isfinite(c)) and np.all(np.linalg.eigvalsh(c) > 0) for c in covs.values())


def test_each_pass_trims_the_heap_once_its_memory_has_risen_by_the_slack(
        scene: Scene, monkeypatch: pytest.MonkeyPatch) -> None:
    import slam.backend.sections as sections
    from slam.heap import HeapKeeper

    checks: list[int] = []
    trims: list[int] = []
    rss = iter(range(0, 10**9, 10))  # the resident memory rises by 10 bytes at every look

    def trim() -> bool:
        trims.append(1)
        return True

    class Counting(HeapKeeper):
        def __init__(self, slack: int) -> None:
            super().__init__(slack=slack, rss=lambda: next(rss), trim=trim)

        def check(self) -> None:
            checks.append(1)
            super().check()

    monkeypatch.setattr(sections, "HeapKeeper", Counting)
    be = _build(scene, replace(backend_defaults(), batch_section_knots=17, batch_whole_knots=0,
                               batch_heap_slack_bytes=0))
    values = be.graph.values
    n = len(be.sections.plan())
    red = be.sections.reduce(values, be.config.kernel, DAMPING)
    assert len(checks) == n and len(trims) == n  # no slack: a trim after every section
    be.sections.back_substitute(values, be.config.kernel, DAMPING, red.graph.optimize())
    be.sections.total_error()
    assert len(checks) == 3 * n and len(trims) == 3 * n
    slack = replace(be.config, batch_heap_slack_bytes=10**6)
    be.sections.config = slack
    be.sections.reduce(values, be.config.kernel, DAMPING)
    assert len(checks) == 4 * n and len(trims) == 3 * n  # under the slack: none
    with pytest.raises(ValueError, match="batch_heap_slack_bytes"):
        replace(backend_defaults(), batch_heap_slack_bytes=-1)


def test_a_variables_dimension_comes_from_its_symbol() -> None:
    from gtsam.symbol_shorthand import B, L, P, V, X

    from slam.backend.graph import key_dim

    assert [key_dim(int(k(3))) for k in (X, V, B, P)] == [6, 3, 6, 3]
    with pytest.raises(ValueError, match="unknown variable l7"):
        key_dim(int(L(7)))


def test_a_pass_holds_one_summed_separator_factor_whatever_the_sections(scene: Scene) -> None:
    """Each section's reduced system is added into one Hessian factor as the pass goes: kept one
    per section, they grew with the walk (docs/memory.md "Session 34")."""
    for knots in (20, 7):
        be = _build(scene, replace(backend_defaults(), batch_section_knots=knots, batch_whole_knots=0))
        red = be.sections.reduce(gtsam.Values(be.graph.values), be.config.kernel, DAMPING, keep=True)
        factors = [red.graph.at(i) for i in range(red.graph.size())]
        assert len(be.sections.plan()) > 2
        assert sum(isinstance(f, gtsam.HessianFactor) for f in factors) == 1
        assert be.sections.peak_separator_bytes > 0  # the summed factor is counted
