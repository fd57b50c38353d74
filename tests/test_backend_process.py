"""The back end in its own process (slam.backend_process): the same ids and estimates as in
process, errors raised in the parent, and a pipelined run that is deterministic and close to the
synchronous one."""

from __future__ import annotations

import os
import signal
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from backend_defaults import backend_defaults
from box_scene import Scene, make_scene, perturb_pose

from simulation.run import SimulationResult, simulate
from slam.backend import Backend, BackendConfig
from slam.backend_process import BackendProcess, FactorIds, make_backend
from slam.config import SlamConfig
from slam.forked import can_fork_reader
from slam.frontend.knots import KnotMirror
from slam.pipeline import SlamRunner
from slam.result import SlamResult

pytestmark = pytest.mark.skipif(not can_fork_reader(), reason="no fork here")

DEG = np.pi / 180.0


def _pair(config: BackendConfig, dt: float = 1.0 / 40.0, fold: bool = False) -> tuple[Backend, BackendProcess, KnotMirror]:
    knots = KnotMirror(dt)
    config = replace(config, fold_links_in_window=fold)
    return Backend(config), BackendProcess(config, knots, recent_knots=20), knots


def _both(be: Backend, proxy: BackendProcess, name: str, *args: Any, **kwargs: Any) -> Any:
    """The same call on both; their answers must agree."""
    a = getattr(be, name)(*args, **kwargs)
    b = getattr(proxy, name)(*args, **kwargs)
    assert a == b, f"{name}: {a} in process, {b} from the proxy"
    return a


def _planes(scene: Scene, rng: np.random.Generator) -> list[tuple[int, np.ndarray, float, bool, bool]]:
    """The scene's planes, perturbed: (id, normal, offset, horizontal, vertical)."""
    out = []
    for j, (n0, d0) in enumerate(zip(scene.planes[:, :3], scene.planes[:, 3], strict=True)):
        horizontal = abs(float(n0[2])) > 0.9
        out.append((j, n0 + rng.normal(0.0, 0.01, 3), float(d0 + rng.normal(0.0, 0.02)), horizontal,
                    not horizontal and j % 2 == 0))
    return out


def _blocks_by_knot(scene: Scene) -> dict[int, list[dict]]:
    by_knot: dict[int, list[dict]] = {}
    for b in scene.blocks:
        by_knot.setdefault(b["knot"], []).append(b)
    return by_knot


def _knot(be: Backend, proxy: BackendProcess, knots: KnotMirror, scene: Scene, rng: np.random.Generator,
          by_knot: dict[int, list[dict]], i: int) -> list[dict]:
    """Knot ``i`` of the scene on both (its pose perturbed) and the blocks of the interval before
    it; returns those blocks."""
    T = scene.knot_poses[0] if i == 0 else perturb_pose(scene.knot_poses[i], rng, 0.01, 0.3 * DEG)
    knots.append(T)
    assert _both(be, proxy, "add_pose", scene.knot_times[i], T) == i
    blocks = by_knot.get(i - 1, [])
    for b in blocks:
        _both(be, proxy, "add_observations", b["knot"], b["plane"], b["points_body"], b["alphas"], b["sigmas"])
    return blocks


def test_the_proxy_gives_the_back_ends_ids_and_replays_to_the_same_estimates() -> None:
    """Knots, blocks, ties and links get the in-process ids; steps applied at the same points give
    the same estimates, bit for bit, and so does the final batch."""
    scene = make_scene(duration=1.0, beams=61, sigma_range=0.003, seed=3)
    rng = np.random.default_rng(4)
    be, proxy, knots = _pair(backend_defaults())
    try:
        for j, n, d, hor, ver in _planes(scene, rng):
            _both(be, proxy, "add_plane", j, n, d, horizontal=hor, vertical=ver, anchor=scene.planes[j, :3] * 0.5)
        wall = next(j for j in range(6) if abs(scene.planes[j, 2]) < 0.1)
        n_w, d_w = scene.planes[wall, :3], float(scene.planes[wall, 3])
        by_knot = _blocks_by_knot(scene)
        steps = 0
        for i in range(len(scene.knot_times)):
            _knot(be, proxy, knots, scene, rng, by_knot, i)
            if i == 10:  # a duplicate of the wall (linked), a door in it (parallel), one across it, removed
                _both(be, proxy, "add_plane", 10, n_w, d_w + 0.001, vertical=True)
                _both(be, proxy, "add_plane", 11, n_w, d_w + 0.02)
                _both(be, proxy, "add_plane", 12, np.cross(n_w, [0.0, 0.0, 1.0]), 0.3, vertical=True)
                for b in by_knot.get(i - 2, []):
                    if b["plane"] == wall:
                        _both(be, proxy, "add_observations", b["knot"], 10, b["points_body"], b["alphas"],
                              b["sigmas"])
                _both(be, proxy, "link_planes", wall, 10, 1e-3, 1e-3)
                _both(be, proxy, "add_parallel", wall, 11, 0.01)
                _both(be, proxy, "add_perpendicular", wall, 12, 0.01)
                be.remove_plane(12)
                proxy.remove_plane(12)
                be.remove_plane(11)
                proxy.remove_plane(11)
            if i >= 8 and i % 4 == 0:
                report = be.step()
                assert not proxy.step().solved  # nothing outstanding: each step is collected at once here
                assert proxy.collect() == report
                steps += 1
                for k in range(max(0, i + 1 - 20), i + 1):
                    np.testing.assert_array_equal(proxy.pose(k), be.pose(k))
                for j in be.plane_ids():
                    n_be, d_be = be.plane(j)
                    n_px, d_px = proxy.plane(j)
                    np.testing.assert_array_equal(n_px, n_be)
                    assert d_px == d_be
        assert steps >= 3
        assert proxy.num_knots == be.num_knots
        assert _both(be, proxy, "fold_links") == {10: wall}
        s_be, s_px = be.batch_optimize(5), proxy.batch_optimize(5)
        assert (s_px.initial_error, s_px.final_error, s_px.iterations) == (s_be.initial_error, s_be.final_error,
                                                                           s_be.iterations)
        np.testing.assert_array_equal(proxy.poses(), be.poses())
        for a, b in zip(proxy.planes(), be.planes(), strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(proxy.plane_covariance(wall), be.plane_covariance(wall))
        assert proxy.residual_statistics() == be.residual_statistics()
        # after a change the counters do not follow, ids come from the worker
        b = scene.blocks[0]
        _both(be, proxy, "add_observations", b["knot"], b["plane"], b["points_body"], b["alphas"], b["sigmas"])
    finally:
        proxy.close()


def test_the_counters_follow_the_folds_at_a_step() -> None:
    """With the links folded at every step (``fold_links_in_window``), the counters follow the
    fold: the surviving plane's new prior, the dropped planes' ties made again on it, a tie or link
    asked for later between planes that became one (the pair's tie's id, -1), and the mirror
    answers a dropped plane as its survivor; the estimates stay the in-process ones, bit for bit."""
    scene = make_scene(duration=1.0, beams=61, sigma_range=0.003, seed=3)
    rng = np.random.default_rng(5)
    be, proxy, knots = _pair(backend_defaults(), fold=True)
    try:
        planes = _planes(scene, rng)
        for j, n, d, hor, ver in planes:
            _both(be, proxy, "add_plane", j, n, d, horizontal=hor, vertical=ver, anchor=scene.planes[j, :3] * 0.5)
        walls = [j for j, n, _, hor, ver in planes if abs(scene.planes[j, 2]) < 0.1]
        wall = next(j for j in walls if not planes[j][4])  # a wall without a verticality prior
        n_w, d_w = scene.planes[wall, :3], float(scene.planes[wall, 3])
        across = np.cross(n_w, [0.0, 0.0, 1.0])
        by_knot = _blocks_by_knot(scene)
        for i in range(len(scene.knot_times)):
            for b in _knot(be, proxy, knots, scene, rng, by_knot, i):
                if i > 10 and b["plane"] == wall:  # its duplicates observe it too
                    for dup in (10, 11):
                        _both(be, proxy, "add_observations", b["knot"], dup, b["points_body"], b["alphas"],
                              b["sigmas"])
            if i == 10:  # two duplicates of the wall (one with a prior the wall lacks), each with ties
                _both(be, proxy, "add_plane", 10, n_w, d_w + 0.001, vertical=True)
                _both(be, proxy, "add_plane", 11, n_w, d_w - 0.001)
                _both(be, proxy, "add_plane", 12, across, 0.3, vertical=True)
                _both(be, proxy, "add_plane", 13, n_w, d_w + 0.03)
                _both(be, proxy, "add_perpendicular", 10, 12, 0.01)
                _both(be, proxy, "add_perpendicular", 11, 12, 0.01)  # the same pair once folded
                _both(be, proxy, "add_parallel", wall, 13, 0.01)
                _both(be, proxy, "add_parallel", 11, 13, 0.01)
                _both(be, proxy, "link_planes", wall, 10, 1e-3, 1e-3)
                _both(be, proxy, "link_planes", 10, 11, 1e-3, 1e-3)
            if i == 14:  # after the fold: the same surface asked again
                assert _both(be, proxy, "link_planes", 11, wall, 1e-3, 1e-3) == -1
                assert _both(be, proxy, "add_perpendicular", 11, 12, 0.01) >= 0
                assert _both(be, proxy, "add_parallel", 10, 13, 0.01) >= 0
                _both(be, proxy, "remove_plane", 13)
            if i >= 8 and i % 4 == 0:
                report = be.step()
                proxy.step()
                assert proxy.collect() == report
                for k in range(max(0, i + 1 - 20), i + 1):
                    np.testing.assert_array_equal(proxy.pose(k), be.pose(k))
                for j in [*be.plane_ids(), 10, 11] if i >= 12 else be.plane_ids():
                    n_be, d_be = be.plane(j)
                    n_px, d_px = proxy.plane(j)
                    np.testing.assert_array_equal(n_px, n_be)
                    assert d_px == d_be
        assert proxy._ids is not None and proxy._ids.folded == {10: wall, 11: wall}
        assert 10 not in proxy.plane_ids() and 11 not in proxy.plane_ids()
        assert _both(be, proxy, "fold_links") == {}
        np.testing.assert_array_equal(proxy.poses(), be.poses())
    finally:
        proxy.close()


def test_imu_factors_count_as_in_the_back_end() -> None:
    """With an IMU: velocity and bias states, IMU intervals and velocity priors advance the
    counter as in process."""
    be, proxy, knots = _pair(backend_defaults(imu=True), dt=0.05)
    try:
        _both(be, proxy, "add_plane", 0, np.array([0.0, 0.0, 1.0]), 0.0, horizontal=True)
        accel = np.tile([0.0, 0.0, 9.81], (10, 1))
        for i in range(4):
            T = np.eye(4)
            T[0, 3] = 0.05 * i
            knots.append(T, np.array([1.0, 0.0, 0.0]))
            v = knots.V[i]  # a view, as the runner passes it: the proxy must send its value at the call
            assert be.add_pose(0.05 * i, T, velocity_world=v.copy()) == proxy.add_pose(0.05 * i, T, velocity_world=v)
            knots.V[i] = -7.0
            if i:
                _both(be, proxy, "add_imu", i - 1, accel, np.zeros((10, 3)), np.full(10, 0.005))
            if i == 2:
                _both(be, proxy, "add_velocity_prior", i, np.zeros(3), 0.01)
        pts = np.array([[1.0, 0.0, -1.0], [0.0, 1.0, -1.0]])
        assert _both(be, proxy, "add_observations", 1, 0, pts, None, np.full(2, 0.01)) > 8
        report = be.step()
        proxy.step()
        assert proxy.collect() == report
        np.testing.assert_array_equal(proxy.velocity(3), be.velocity(3))
        np.testing.assert_array_equal(proxy.bias(3), be.bias(3))
    finally:
        proxy.close()


def test_knots_added_after_a_step_take_its_velocity_change() -> None:
    """The front end integrates the IMU on from the newest velocity it has: knots added after a
    step get the velocity the step gave its last knot plus the front end's change since (rotated
    like the poses), not only the rotation. A front end whose velocities are 1 m/s off for a
    standing rig (the IMU and a zero-velocity prior say 0) gets them back near 0: without the
    step's change, the front end's velocity was never corrected one update late (issue 23: the
    10-minute walk with its IMU diverged)."""
    be, proxy, knots = _pair(backend_defaults(imu=True), dt=0.05)
    try:
        _both(be, proxy, "add_plane", 0, np.array([0.0, 0.0, 1.0]), 1.0, horizontal=True)
        accel = np.tile([0.0, 0.0, 9.81], (10, 1))  # standing still, level
        pts = np.array([[1.0, 0.0, -1.0], [0.0, 1.0, -1.0], [-1.0, 0.5, -1.0]])
        wrong = np.array([1.0, 0.0, 0.0])

        def knot(i: int) -> None:
            knots.append(np.eye(4), wrong + 0.01 * i)  # the front end's velocities: off, and changing
            _both(be, proxy, "add_pose", 0.05 * i, np.eye(4), velocity_world=knots.V[i].copy())
            if i:
                _both(be, proxy, "add_imu", i - 1, accel, np.zeros((10, 3)), np.full(10, 0.005))
                _both(be, proxy, "add_observations", i - 1, 0, pts, None, np.full(3, 0.01))
            _both(be, proxy, "add_velocity_prior", i, np.zeros(3), 0.01)

        for i in range(4):
            knot(i)
        be.step()
        assert not proxy.step().solved  # sent; its result comes with the next step
        v3 = be.velocity(3)
        assert np.linalg.norm(v3) < 0.05
        for i in range(4, 6):
            knot(i)
        assert proxy.step().solved  # the first step's result, one update late
        np.testing.assert_array_equal(proxy.velocity(3), v3)
        R = (proxy.pose(5) @ np.linalg.inv(knots.T[5]))[:3, :3]
        np.testing.assert_allclose(proxy.velocity(5), v3 + R @ (knots.V[5] - knots.V[3]), atol=1e-12)
        assert np.linalg.norm(proxy.velocity(5)) < 0.1, proxy.velocity(5)
    finally:
        proxy.close()


def test_a_failing_worker_raises_in_the_parent() -> None:
    """A call the back end refuses, an id the counters got wrong and a killed worker each end in a
    one-line RuntimeError in the parent, not a hang."""
    config = backend_defaults()
    proxy = BackendProcess(config, KnotMirror(0.05), recent_knots=20)
    t = time.perf_counter()
    proxy.add_pose(0.0, np.eye(4))
    proxy.add_observations(0, 99, np.zeros((2, 3)), None, np.full(2, 0.01))  # no plane 99
    proxy.step()
    with pytest.raises(RuntimeError, match=r"the back-end process failed: ValueError: plane_id: no plane 99$"):
        proxy.collect()
    proxy.close()

    proxy = BackendProcess(config, KnotMirror(0.05), recent_knots=20)
    proxy.add_plane(0, np.array([0.0, 0.0, 1.0]), 0.0, horizontal=True)
    proxy.add_pose(0.0, np.eye(4))
    assert proxy._ids is not None
    proxy._ids.next_factor += 1  # a counter that drifted from the back end's
    proxy.add_observations(0, 0, np.zeros((2, 3)), None, np.full(2, 0.01))
    with pytest.raises(RuntimeError, match="FactorIds no longer counts as the back end does"):
        proxy.residual_statistics()
    proxy.close()

    proxy = BackendProcess(config, KnotMirror(0.05), recent_knots=20)
    os.kill(proxy._proc.pid, signal.SIGKILL)
    proxy.step()
    with pytest.raises(RuntimeError, match=r"the back-end process: stopped without a result \(exit code -9\)"):
        proxy.collect()
    proxy.close()
    assert time.perf_counter() - t < 30.0


def test_a_synchronous_query_error_is_the_callers() -> None:
    """An error of a synchronous query (a plane that does not exist) is raised as in process, and
    the worker goes on."""
    proxy = BackendProcess(backend_defaults(), KnotMirror(0.05), recent_knots=20)
    try:
        with pytest.raises(ValueError, match="plane_id: no plane 5"):
            proxy.plane_covariance(5)
        assert proxy.residual_statistics()["blocks"] == 0.0
    finally:
        proxy.close()


def test_the_switch_chooses_the_back_end() -> None:
    knots = KnotMirror(0.05)
    assert isinstance(make_backend(backend_defaults(), False, knots, 80), Backend)
    proxy = make_backend(backend_defaults(), None, knots, 80)
    assert isinstance(proxy, BackendProcess)
    proxy.close()
    assert not proxy._proc.is_alive()
    assert SlamConfig().backend.pipelined is False  # experimental: off unless asked for (None: where forking works)
    with pytest.raises(ValueError, match="pipelined"):
        SlamConfig.model_validate({"backend": {"pipelined": "often"}})


def test_factor_ids_follow_the_configuration() -> None:
    ids = FactorIds(backend_defaults())
    assert [ids.add_pose() for _ in range(3)] == [0, 1, 2]
    assert ids.one() == 3  # datum, first interval, one constant-velocity factor before it


# ---------------------------------------------------------------------------- a short walk

BOX_WORLD = """
name: box
floor_z: 0.0
ceiling_z: 2.8
spaces:
  - {name: room, rect: [0.0, 0.0, 8.0, 6.0]}
walk:
  speed: 1.2
  waypoints:
    - [1.5, 1.5]
    - [6.0, 2.0]
    - [6.0, 4.5]
"""


def _box_walk(tmp_path_factory: pytest.TempPathFactory, imu: bool) -> SimulationResult:
    """6 s through the box (with an IMU, or none)."""
    folder = tmp_path_factory.mktemp("box_imu_walk" if imu else "box_walk")
    world = folder / "box.yaml"
    world.write_text(BOX_WORLD)
    return simulate(world, "itc_backpack", duration=6.0, seed=3, out=folder / "box.bag", imu=imu, progress=False)


@pytest.fixture(scope="module")
def box_walk(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    return _box_walk(tmp_path_factory, imu=False)


@pytest.fixture(scope="module")
def box_imu_walk(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    return _box_walk(tmp_path_factory, imu=True)


def _runner(bag: Path, pipelined: bool, **backend: Any) -> SlamRunner:
    """A runner over the whole bag (with its IMU, if it has one), finished; ``backend``: more of
    the back end's configuration."""
    from common.rig import resolve_rig
    from slam.io.bag import read_scans, time_range
    from slam.run import load_imu

    rig = resolve_rig("itc_backpack")
    cfg = SlamConfig.model_validate({"backend": {"pipelined": pipelined, **backend}})
    imu = load_imu(bag, cfg, *time_range(bag), rig=rig)
    runner = SlamRunner(rig, cfg, imu)
    assert isinstance(runner.backend, BackendProcess) == pipelined
    for line in read_scans(bag, rig=rig):
        runner.add_scan(line)
    runner.finish()
    return runner


def _run(bag: Path, pipelined: bool, **backend: Any) -> SlamResult:
    runner = _runner(bag, pipelined, **backend)
    try:
        return runner.result()
    finally:
        runner.close()


def test_a_pipelined_walk_is_deterministic_and_close_to_the_synchronous_one(box_walk: SimulationResult) -> None:
    a, b, sync = _run(box_walk.bag, True), _run(box_walk.bag, True), _run(box_walk.bag, False)
    np.testing.assert_array_equal(a.T_world_body, b.T_world_body)
    np.testing.assert_array_equal(a.plane_ids, b.plane_ids)
    np.testing.assert_array_equal(a.plane_offsets, b.plane_offsets)
    assert a.stats["updates"] == sync.stats["updates"]  # every step's result applied, one update late
    assert a.T_world_body.shape == sync.T_world_body.shape
    gap = np.linalg.norm(a.T_world_body[:, :3, 3] - sync.T_world_body[:, :3, 3], axis=1)
    assert gap.max() < 0.005, f"{1000 * gap.max():.2f} mm from the synchronous run"
    assert len(a.plane_ids) == len(sync.plane_ids)


def test_a_pipelined_front_end_can_take_a_steps_result_before_the_next_step(box_walk: SimulationResult,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``pipelined_collect_after`` below ``update_every`` the front end takes each step's
    result that many knots after sending it (not at the next step): deterministic, every step
    applied, near the synchronous run."""
    applied: list[int] = []
    after = SlamRunner._after_update

    def record(self: SlamRunner) -> None:
        after(self)
        applied.append(self.knots.n)

    monkeypatch.setattr(SlamRunner, "_after_update", record)
    runs, at = [], []
    for _ in range(2):
        applied.clear()
        runs.append(_run(box_walk.bag, True, update_every=10, pipelined_collect_after=3))
        at.append(list(applied))
    applied.clear()
    _run(box_walk.bag, True, update_every=10)  # each result taken at the next step
    late = list(applied)
    sync = _run(box_walk.bag, False, update_every=10)
    a, b = runs
    np.testing.assert_array_equal(a.T_world_body, b.T_world_body)
    np.testing.assert_array_equal(a.plane_offsets, b.plane_offsets)
    assert at[0] == at[1]
    # every step's result taken 3 knots after it was sent instead of 10 (the last two: at the end)
    assert len(late) == len(at[0]) >= 5
    assert [n - m for n, m in zip(late[:-2], at[0][:-2], strict=True)] == [7] * (len(late) - 2), (late, at[0])
    assert a.stats["updates"] == sync.stats["updates"]
    gap = np.linalg.norm(a.T_world_body[:, :3, 3] - sync.T_world_body[:, :3, 3], axis=1)
    assert gap.max() < 0.005, f"{1000 * gap.max():.2f} mm from the synchronous run"
    with pytest.raises(ValueError, match="pipelined_collect_after"):
        SlamConfig.model_validate({"backend": {"pipelined_collect_after": 0}})


def test_a_pipelined_imu_walk_keeps_the_front_ends_velocities(box_imu_walk: SimulationResult,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """With an IMU the front end predicts every knot from its newest velocity: one update behind
    the back end, that velocity still follows the back end's estimates (the newest knot's after
    each update, against the final ones: within a few cm/s, as in sync), and the trajectory stays
    near the synchronous one. Before the fix (the knots after a step only rotated), the pipelined
    front end's velocities were the IMU's dead reckoning since the start (issue 23)."""
    newest: list[tuple[int, np.ndarray]] = []
    after = SlamRunner._after_update

    def record(self: SlamRunner) -> None:
        after(self)
        newest.append((self.knots.n - 1, self.knots.V[self.knots.n - 1].copy()))

    monkeypatch.setattr(SlamRunner, "_after_update", record)
    errors = {}
    results = {}
    for pipelined in (False, True):
        newest.clear()
        runner = _runner(box_imu_walk.bag, pipelined, update_every=20)  # five updates in the 6 s
        try:
            results[pipelined] = runner.result()
            final = runner.backend.velocities()
        finally:
            runner.close()
        assert len(newest) >= 5
        errors[pipelined] = max(float(np.linalg.norm(v - final[k])) for k, v in newest)
    assert errors[True] < max(0.03, 3.0 * errors[False]), errors
    gap = np.linalg.norm(results[True].T_world_body[:, :3, 3] - results[False].T_world_body[:, :3, 3], axis=1)
    assert gap.max() < 0.01, f"{1000 * gap.max():.2f} mm from the synchronous run"


@pytest.fixture(scope="module")
def ring_walk(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    """Once round the ring corridor: the start corridor's walls come back into view."""
    from tests.test_slam_pipeline import RING_WORLD

    folder = tmp_path_factory.mktemp("ring_walk")
    world = folder / "ring.yaml"
    world.write_text(RING_WORLD)
    return simulate(world, "itc_backpack", duration=14.5, seed=3, out=folder / "ring.bag", progress=False)


def test_a_pipelined_walk_folds_a_revisited_wall_at_the_step(ring_walk: SimulationResult) -> None:
    """``fold_links: step`` in the worker too: the walls seen again after the loop, linked to their
    first copies, become one variable at the next step (the worker's window holds one plane per
    surface, as in sync, not two tied by a link), and the walk ends where the synchronous one does,
    the same way every time."""
    planes = {}
    folded = {}
    for pipelined in (False, True):
        runner = _runner(ring_walk.bag, pipelined)
        try:
            planes[pipelined] = runner.backend.plane_ids()
            if isinstance(runner.backend, BackendProcess):
                assert runner.backend._ids is not None
                folded = dict(runner.backend._ids.folded)
            assert runner.stats.planes_merged >= 2
        finally:
            runner.close()
    assert len(folded) >= 2, folded  # linked during the walk, folded at a step
    assert not set(folded) & set(planes[True])
    assert planes[True] == planes[False]
    a, b, sync = _run(ring_walk.bag, True), _run(ring_walk.bag, True), _run(ring_walk.bag, False)
    np.testing.assert_array_equal(a.T_world_body, b.T_world_body)
    np.testing.assert_array_equal(a.plane_offsets, b.plane_offsets)
    np.testing.assert_array_equal(a.plane_ids, sync.plane_ids)
    gap = np.linalg.norm(a.T_world_body[:, :3, 3] - sync.T_world_body[:, :3, 3], axis=1)
    assert gap.max() < 0.002, f"{1000 * gap.max():.2f} mm from the synchronous run"
    np.testing.assert_allclose(a.plane_offsets, sync.plane_offsets, atol=0.002)
