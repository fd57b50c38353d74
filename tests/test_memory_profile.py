"""scripts/memory_profile.py: deep sizes, stage peaks from the sampled series, slopes and extrapolation."""

from __future__ import annotations

import time
import types
from pathlib import Path
from types import ModuleType

import numpy as np
import psutil
import pytest
from script_module import load_script


def _script() -> ModuleType:
    return load_script("memory_profile")


mp = _script()


def test_deep_size_counts_array_buffers_and_shared_objects_once() -> None:
    a = np.zeros(1000)  # 8000 bytes of data
    seen: set[int] = set()
    b1, n1 = mp.deep_size({"a": a, "view": a[10:]}, seen)
    assert b1 >= 8000 and n1 >= 3
    b2, n2 = mp.deep_size([a], seen)  # the array was counted with the first root
    assert b2 < 200 and n2 == 1


def test_holder_sizes_leaves_out_missing_and_none_roots() -> None:
    roots = types.SimpleNamespace(runner=None, result={"rows": np.zeros(500)}, cloud=None)
    out = mp.holder_sizes(roots)
    assert list(out) == ["result (SlamResult: segment rows, poses)"]
    assert out["result (SlamResult: segment rows, poses)"]["bytes"] >= 4000


def test_window_peaks_takes_each_column_within_the_window() -> None:
    series = np.array([[0.0, 10, 5, 20, 2], [1.0, 30, 6, 25, 2], [2.0, 15, 7, 40, 3], [3.0, 50, 9, 60, 1]])
    p = mp.window_peaks(series, 0.5, 3.0)
    assert p == {"rss": 30.0, "pss_all": 40.0, "processes": 3.0}
    empty = mp.window_peaks(series, 5.0, 6.0)
    assert all(np.isnan(v) for v in empty.values())
    assert np.isnan(mp.window_peaks(np.zeros((0, 5)), 0.0, 1.0)["rss"])


def test_read_series_leaves_out_a_torn_last_line(tmp_path: Path) -> None:
    f = tmp_path / "s.tsv"
    f.write_text("1.0\t2\t3\t4\t1\n2.0\t5\t6\t7\t2\n3.0\t8\t9")
    s = mp.read_series(str(f))
    assert s.shape == (2, 5) and s[1, 3] == 7.0


def test_slope_line_and_stage_extrapolation() -> None:
    rows = [(60.0, 110.0), (120.0, 120.0), (180.0, 130.0)]  # 10 per data minute from 100
    assert mp.growth_per_minute(rows) == pytest.approx(10.0)
    assert mp.line_at(rows, 60.0) == pytest.approx(700.0)
    assert np.isnan(mp.line_at(rows[:1], 60.0))
    # a stage adding 50 over the 3-minute walk adds 1000 at 60 minutes, on top of the walk's line there
    assert mp.stage_at(180.0, 130.0, 700.0, 3.0, 60.0) == pytest.approx(1700.0)


def test_malloc_info_sees_a_large_allocation() -> None:
    before = mp.malloc_info()
    if not before:
        pytest.skip("no glibc mallinfo2")
    a = np.ones(8 << 20)  # 64 MB: above malloc's mmap threshold
    after = mp.malloc_info()
    assert after["mmapped"] - before["mmapped"] >= a.nbytes


def test_trim_heap_gives_freed_heap_pages_back() -> None:
    from slam.heap import trim_heap

    if not mp.malloc_info():
        pytest.skip("no glibc malloc")
    me = psutil.Process()
    blocks = [bytearray(64 << 10) for _ in range(1600)]  # 100 MB in malloc's heap (below its mmap threshold)
    keep = bytearray(64 << 10)  # above them: free() alone cannot give their pages back
    del blocks
    freed = me.memory_info().rss
    assert trim_heap()
    assert me.memory_info().rss < freed - 50e6
    assert len(keep) == 64 << 10


def test_sampler_samples_this_process_without_itself(tmp_path: Path) -> None:
    s = mp.Sampler(str(tmp_path / "samples.tsv"), period=0.05)
    try:
        deadline = time.monotonic() + 10.0
        while s.series().shape[0] < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        series = s.series()
        # children an earlier test of this worker left (multiprocessing's resource tracker, say)
        others = [p for p in psutil.Process().children(recursive=True) if p.pid != s.pid]
    finally:
        s.stop()
    assert series.shape[0] >= 3
    assert np.all(series[:, 1] == np.maximum(series[:, 1], 1e6))  # an RSS of at least 1 MB
    assert np.all(np.diff(series[:, 0]) > 0)
    # the sampler leaves itself out: this process and the others
    assert series[-1, 4] == 1 + len(others)
    if not others:
        assert np.all(series[:, 4] == 1) and np.all(series[:, 3] == series[:, 2])


def test_section_counts_of_a_sectioned_batch_only() -> None:
    class Sections:
        peak_kept_bytes, peak_separator_bytes, sections_built, sections_solved = 5_000, 700, 3, 6
        largest_net_bytes, nets_spilled = 900, 2

        def __init__(self, needed: bool) -> None:
            self._needed = needed

        def needed(self) -> bool:
            return self._needed

        def plan(self) -> list[tuple[int, int]]:
            return [(0, 10), (10, 20), (20, 25)]

    assert mp.section_counts(types.SimpleNamespace()) == {}  # a back end without sections
    assert mp.section_counts(types.SimpleNamespace(sections=Sections(False))) == {}  # solved whole
    out = mp.section_counts(types.SimpleNamespace(sections=Sections(True)))
    assert out == {"sections": 3, "section_kept_peak_bytes": 5_000, "separator_peak_bytes": 700,
                   "largest_elimination_bytes": 900, "sections_built": 3, "sections_solved": 6,
                   "eliminations_on_disk": 2}


def test_heap_keeper_trims_once_resident_memory_crept_up_by_its_slack() -> None:
    from slam.heap import HeapKeeper

    rss = [100]
    trims: list[int] = []

    def trim() -> bool:
        trims.append(rss[0])
        rss[0] -= 30  # what the trim gave back
        return True

    keeper = HeapKeeper(slack=50, rss=lambda: rss[0], trim=trim)
    for _ in range(12):
        rss[0] += 10
        keeper.check()
    # 100 -> 160 (over 100 + 50): trimmed to 130; 130 -> 190: trimmed to 160
    assert trims == [160, 190] and keeper.trims == 2 and rss[0] == 160
    unknown = HeapKeeper(slack=0, rss=lambda: None, trim=trim)
    unknown.check()
    assert keeper.trims == 2 and len(trims) == 2


def test_fewer_collections_sets_the_thresholds_for_its_block_and_restores_them() -> None:
    import gc

    from slam.heap import RUN_GC_THRESHOLDS, fewer_collections

    before = gc.get_threshold()
    with fewer_collections():
        assert gc.get_threshold() == RUN_GC_THRESHOLDS
    assert gc.get_threshold() == before
    with pytest.raises(RuntimeError), fewer_collections((5_000, 5, 5)):
        assert gc.get_threshold() == (5_000, 5, 5)
        raise RuntimeError("inside")
    assert gc.get_threshold() == before
