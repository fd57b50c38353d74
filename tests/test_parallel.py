"""The second core: scans prepared in a reader process (slam.prefetch) and the cloud written by
several processes (slam.cloud_pass) give the same results, bit for bit, as one process; errors in
those processes reach the caller; each process opens the bag once."""

from __future__ import annotations

import os
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.rig import resolve_rig
from simulation.run import SimulationResult, simulate
from slam.config import SlamConfig
from slam.forked import can_fork_reader
from slam.frontend.scan_prep import ScanPreparer, knot_deskew
from slam.io.bag import time_range as bag_time_range
from slam.io.errors import InputError
from slam.io.source import BagSource
from slam.prefetch import prepared_scans
from slam.run import load_imu, run_slam

pytestmark = pytest.mark.skipif(not can_fork_reader(), reason="needs fork")

# a corridor with doors set into its walls, walked with an IMU: deskew, edges and planes all in play
WORLD = """
name: door_corridor_short
floor_z: 0.0
ceiling_z: 2.6
spaces:
  - {name: corridor, rect: [0.0, 0.0, 30.0, 2.0]}
doors:
  - {space: corridor, side: north, at: 6.0, recess: 0.015}
  - {space: corridor, side: south, at: 8.5, recess: 0.01}
walk:
  speed: 1.2
  waypoints:
    - [3.0, 1.0]
    - [20.0, 1.0]
"""


@pytest.fixture(scope="module")
def walk(tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    folder = tmp_path_factory.mktemp("parallel")
    world = folder / "world.yaml"
    world.write_text(WORLD)
    return simulate(world, "itc_backpack", duration=3.0, seed=5, out=folder / "walk.bag", imu=True, progress=False)


@pytest.fixture(scope="module")
def rig() -> Any:
    return resolve_rig("itc_backpack")


def _cfg(reader: bool, export_processes: int) -> SlamConfig:
    return SlamConfig.model_validate({"parallel": {"reader": reader, "export_processes": export_processes}})


def test_the_reader_process_prepares_the_same_scans(walk: SimulationResult, rig: Any) -> None:
    cfg = SlamConfig()
    t0, t1 = bag_time_range(walk.bag)
    imu = load_imu(walk.bag, cfg, t0, t1)
    assert imu is not None  # the deskew is part of what is compared
    with BagSource(walk.bag) as source:
        in_process = prepared_scans(source, rig, cfg, imu, process=False)
        here = list(in_process)
        span = source.time_range()
        reader = prepared_scans(source, rig, cfg, imu, process=True, chunk=7, max_chunks=2)
        assert source._held is None  # this process let go of its index while the reader reads
        there = list(reader)
        assert source.time_range() == span and source._held is not None  # opened again when read
        again = list(prepared_scans(source, rig, cfg, imu, process=False))
    assert len(here) == len(there) == len(again) > 100
    assert [s.stamp for s in again] == [s.stamp for s in here]
    # the reader process hands back its stream's index: the same as this process's
    assert reader.index == in_process.index and len(reader.index) == len(here)
    assert reader.index.stamps == [s.stamp for s in here] and reader.index.lag_ns is not None
    n_segs = n_tests = 0
    for a, b in zip(here, there, strict=True):
        assert (a.scanner, a.scan_index, a.stamp, a.skipped) == (b.scanner, b.scan_index, b.stamp, b.skipped)
        assert (a.segs is None) == (b.segs is None)
        assert a.edge_tests.keys() == b.edge_tests.keys()
        assert all(repr(a.edge_tests[k]) == repr(b.edge_tests[k]) for k in a.edge_tests)
        n_tests += len(a.edge_tests)
        if a.segs is not None and b.segs is not None:
            n_segs += a.segs.n_segments
            for name in ("first_beam", "last_beam", "points_body", "times", "virtual_body", "virtual_times",
                         "virtual_sigma", "line_direction"):
                np.testing.assert_array_equal(getattr(a.segs, name), getattr(b.segs, name), err_msg=name)
    assert n_segs > 1000 and n_tests > 100
    # a scanner's equal beam angles come as one array (sent once per chunk)
    for s in {b.scanner for b in there if b.segs is not None}:
        arrays = [b.segs.beam_angles for b in there[:7] if b.segs is not None and b.scanner == s]
        assert len(arrays) >= 2 and all(a is arrays[0] for a in arrays), s
    # the first scan hands on the reader's deskew table (the runner does not build it again)
    table = knot_deskew(cfg, imu, here[0].stamp)
    assert table is not None and there[0].deskew is not None and all(s.deskew is None for s in there[1:])
    np.testing.assert_array_equal(there[0].deskew.rotvec, table.rotvec)
    np.testing.assert_array_equal(there[0].deskew.times, table.times)


def test_an_error_in_the_reader_process_is_raised_here(walk: SimulationResult, rig: Any,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    original = ScanPreparer.prepare
    calls = {"n": 0}

    def failing(self: ScanPreparer, line: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 40:
            raise InputError(f"{walk.bag} topic /scan: bad LaserScan")
        return original(self, line)

    monkeypatch.setattr(ScanPreparer, "prepare", failing)  # the forked reader inherits the patch
    with pytest.raises(InputError, match="bad LaserScan"), BagSource(walk.bag) as source:
        for _ in prepared_scans(source, rig, SlamConfig(), None, process=True, chunk=4):
            pass
    assert calls["n"] == 0  # the scans were prepared in the reader, not here


def test_parallel_runs_write_the_same_outputs(walk: SimulationResult, rig: Any, tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    opens = _count_bag_opens(monkeypatch, tmp_path / "opens.log")
    one = run_slam(walk.bag, rig, _cfg(False, 1), tmp_path / "one", progress=False)
    assert list(opens().values()) == [1]  # one process, one open
    par = run_slam(walk.bag, rig, _cfg(True, 3), tmp_path / "par", progress=False)
    # the reader and two cloud parts open the bag once each; this process twice: it lets go of
    # its index while the reader reads and opens the bag again for the export
    assert list(opens().values()) == [2, 1, 1, 1]
    for name in ("trajectory.tum", "trajectory_online.tum", "planes.json", "segments.npz", "cloud.ply"):
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "par" / name).read_bytes(), name
    assert one["counts"] == par["counts"]
    assert one["counts"]["cloud_points"] > 100_000
    # no part files are left beside the cloud
    assert sorted(p.name for p in (tmp_path / "par").iterdir()) == sorted(p.name for p in (tmp_path / "one").iterdir())


def _count_bag_opens(monkeypatch: pytest.MonkeyPatch, log: Path) -> Any:
    """Records each ``AnyReader`` made, by process id, in ``log`` (forked processes inherit the
    patch); returns a function that gives the counts per process so far and starts over."""
    from rosbags.highlevel import AnyReader

    original = AnyReader.__init__

    def counted(self: Any, *args: Any, **kwargs: Any) -> None:
        with log.open("a") as f:
            f.write(f"{os.getpid()}\n")
        original(self, *args, **kwargs)

    monkeypatch.setattr(AnyReader, "__init__", counted)

    def counts() -> Counter[str]:
        got = Counter(log.read_text().split()) if log.exists() else Counter()
        log.unlink(missing_ok=True)
        return got

    return counts


def test_an_error_in_an_export_process_leaves_no_output(walk: SimulationResult, rig: Any, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    import slam.cloud_pass as cloud_mod

    original = cloud_mod.cloud_part

    def failing(scans: Any, part: Any, rig: Any, res: Any, writer: Any, bar: Any = None, **kw: Any) -> Any:
        if part.lo > 0:  # the forked parts only
            raise OSError("disk full")
        return original(scans, part, rig, res, writer, bar, **kw)

    monkeypatch.setattr(cloud_mod, "cloud_part", failing)
    out = tmp_path / "run"
    with pytest.raises(OSError, match="disk full"):
        run_slam(walk.bag, rig, _cfg(True, 2), out, progress=False)
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_the_front_end_takes_the_edge_tests_from_the_prepared_scan(walk: SimulationResult, rig: Any) -> None:
    """The scan-only edge tests (recesses past a wall segment's end, steps inside it) are computed
    once, when the scan is prepared, and the front end only looks them up: the same run from scans
    stripped of them finds the segment pairs' breaks only."""
    from slam.pipeline import SlamRunner

    cfg = SlamConfig()
    t0, t1 = bag_time_range(walk.bag)
    imu = load_imu(walk.bag, cfg, t0, t1)
    runs = []
    for keep in (True, False):
        runner = SlamRunner(rig, cfg, imu)
        n_tests = 0
        with BagSource(walk.bag) as source:
            for scan in prepared_scans(source, rig, cfg, imu, process=False):
                n_tests += len(scan.edge_tests)
                runner.add_prepared(scan if keep else replace(scan, edge_tests={}))
        runner.finish()
        runs.append(runner.result(batch=False, covariances=False))
        assert n_tests > 0
    a, b = runs
    assert a.stats.edge_observations > b.stats.edge_observations > 0


def test_scans_fed_raw_or_prepared_elsewhere_give_the_same_run(walk: SimulationResult, rig: Any) -> None:
    """``add_scan`` (the runner prepares each scan itself, and reuses its preparer's deskew table)
    and ``add_prepared`` from the reader process give the same estimate."""
    from slam.io.bag import read_scans
    from slam.pipeline import SlamRunner

    cfg = SlamConfig()
    t0, t1 = bag_time_range(walk.bag)
    imu = load_imu(walk.bag, cfg, t0, t1)
    raw, prepared = SlamRunner(rig, cfg, imu), SlamRunner(rig, cfg, imu)
    for line in read_scans(walk.bag, rig=rig):
        raw.add_scan(line)
    with BagSource(walk.bag) as source:
        for scan in prepared_scans(source, rig, cfg, imu, process=True):
            prepared.add_prepared(scan)
    results = []
    for runner in (raw, prepared):
        runner.finish()
        results.append(runner.result(batch=False))
    assert raw.preparer.deskew is not None and results[0].deskew is raw.preparer.deskew
    np.testing.assert_array_equal(results[0].T_world_body, results[1].T_world_body)
    np.testing.assert_array_equal(results[0].deskew.rotvec, results[1].deskew.rotvec)


def _deaf_helper(q: Any) -> None:
    """A forked helper as the hang left it: SIGTERM not acted on, and its exit waiting for its
    queue's feeder thread, blocked on a pipe that nobody reads."""
    import signal

    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    q.put(np.zeros(1 << 20))  # 8 MB: far past a pipe's buffer


def test_stopping_helpers_is_bounded_when_one_does_not_answer_sigterm() -> None:
    import multiprocessing as mp
    import time

    from slam.forked import stop_children

    ctx = mp.get_context("fork")
    q = ctx.Queue()
    deaf = ctx.Process(target=_deaf_helper, args=(q,), daemon=True)
    done = ctx.Process(target=int, daemon=True)  # one that has already exited
    deaf.start()
    done.start()
    done.join()
    time.sleep(0.3)  # the deaf helper is in its exit, waiting on the feeder thread
    assert deaf.is_alive()
    t0 = time.monotonic()
    stop_children([deaf, done], grace_s=0.3)
    assert time.monotonic() - t0 < 5.0
    assert not deaf.is_alive() and deaf.exitcode == -9 and done.exitcode == 0
    q.close()
    q.cancel_join_thread()


def _orphan_maker(w: int) -> None:
    """A helper's parent: forks a helper that sleeps, sends its pid down ``w`` and exits."""
    from slam.forked import die_with_parent

    me = os.getpid()
    pid = os.fork()
    if pid == 0:
        die_with_parent(me)
        import time

        time.sleep(60)
        os._exit(0)
    os.write(w, str(pid).encode())
    os._exit(0)


@pytest.mark.skipif(not os.uname().sysname == "Linux", reason="the kernel's parent-death signal is Linux's")
def test_a_helper_does_not_outlive_its_parent() -> None:
    import time

    r, w = os.pipe()
    maker = os.fork()
    if maker == 0:
        try:
            _orphan_maker(w)
        finally:
            os._exit(1)  # never back into pytest from the forked child
    os.waitpid(maker, 0)
    helper = int(os.read(r, 32))
    os.close(r)
    os.close(w)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.kill(helper, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    else:
        os.kill(helper, 9)
        raise AssertionError("the helper outlived its parent")
