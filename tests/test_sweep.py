"""The sweep engine: config validation, grid, cache, resume, failures, pool/Dask, report.

Most engine tests inject a cheap cell function (module level, so that spawned pool workers
can import it); one test runs a real cell end to end (simulate, SLAM, evaluate, segmentation
scores) and accepts either outcome as long as it is recorded with its metrics or its error.
"""

from __future__ import annotations

import math
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from backpack_slam.cli import main
from backpack_slam.sweep.cache import cached_simulation
from backpack_slam.sweep.cell import run_cell
from backpack_slam.sweep.config import load_experiment
from backpack_slam.sweep.engine import run_sweep
from backpack_slam.sweep.perturb import perturb_rig
from backpack_slam.sweep.plan import Cell, plan_cells
from backpack_slam.sweep.report import mean_ci
from backpack_slam.sweep.results import append_rows, finished_cells, read_results, results_path
from common.config import ConfigError
from common.rig import resolve_rig

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "experiments"

TINY = """
name: tiny
duration: {duration}
seeds: [0, 1]
worlds: [demo]
segmenters:
  - {{method: ror, name: ror, params: {{direction: combined}}}}
  - {{method: iepf, name: iepf, grid: {{threshold: [0.011, 0.015]}}}}
slam:
  backend: {{final_batch: false}}
  output: {{rerun: false}}
segmentation_metrics: {{scans_per_scanner: 4}}
"""


def _write(tmp_path: Path, text: str, name: str = "exp.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def _cells(tmp_path: Path, duration: float = 2.0) -> list[Cell]:
    return plan_cells(load_experiment(_write(tmp_path, TINY.format(duration=duration))))


# ----------------------------------------------------------------- injectable cell functions


def fake_cell(cell: Cell, out: str) -> dict[str, Any]:
    """A deterministic stand-in for run_cell: a metric computed from the cell's axes."""
    thr = float(cell.params.get("threshold", 0.0))
    return cell.describe() | {"status": "ok", "stage": "", "error": "", "ate_rmse_m": 0.01 * (1 + cell.seed) + thr}


def failing_cell(cell: Cell, out: str) -> dict[str, Any]:
    if cell.method == "iepf":
        raise ValueError(f"iepf exploded on seed {cell.seed}")
    return fake_cell(cell, out)


class Interrupt(BaseException):
    """Stands for Ctrl-C / a killed sweep (not an Exception: the engine must not record it)."""


def interrupted_after_first(calls: list[str]) -> Any:
    def fn(cell: Cell, out: str) -> dict[str, Any]:
        if calls:
            raise Interrupt
        calls.append(cell.cell_id)
        return fake_cell(cell, out)

    return fn


# -------------------------------------------------------------------------------- config


def test_shipped_experiments_load_and_expand() -> None:
    study = plan_cells(load_experiment(CONFIGS / "segmentation_vs_drift.yaml"))
    variants = {c.variant for c in study}
    assert {"ror forward sigma=0.007", "ror combined sigma=0.0095", "ror backward sigma=0.015"} <= variants
    assert {c.world for c in study} == {"office", "corridor", "hall"}
    assert {c.noise for c in study} == {0.003, 0.010}
    assert {c.seed for c in study} == set(range(5))
    assert len(study) == len(variants) * 3 * 2 * 5
    # one simulation per world x noise x seed, shared by every segmenter
    assert len({c.sim_key for c in study}) == 3 * 2 * 5
    quick = plan_cells(load_experiment(CONFIGS / "quick.yaml"))
    assert 4 <= len({c.variant for c in quick}) <= 6 and len({c.seed for c in quick}) == 2


def test_grid_expansion_and_hashes(tmp_path: Path) -> None:
    cells = _cells(tmp_path)
    assert len(cells) == 2 * 3
    assert sorted({c.variant for c in cells}) == ["iepf threshold=0.011", "iepf threshold=0.015", "ror"]
    assert len({c.cell_id for c in cells}) == 6
    by_seed = {s: {c.sim_key for c in cells if c.seed == s} for s in (0, 1)}
    assert all(len(v) == 1 for v in by_seed.values()) and by_seed[0] != by_seed[1]
    # deterministic: the same config gives the same ids
    assert [c.cell_id for c in _cells(tmp_path)] == [c.cell_id for c in cells]
    # the SLAM config is part of the cell id but not of the simulation key
    other = plan_cells(load_experiment(_write(tmp_path, TINY.format(duration=2.0).replace("final_batch: false", "final_batch: true"), "b.yaml")))
    assert {c.sim_key for c in other} == {c.sim_key for c in cells}
    assert not {c.cell_id for c in other} & {c.cell_id for c in cells}


def test_parameter_range(tmp_path: Path) -> None:
    text = TINY.format(duration=2.0).replace("grid: {threshold: [0.011, 0.015]}", "grid: {threshold: {start: 0.007, stop: 0.015, num: 5}}")
    cells = plan_cells(load_experiment(_write(tmp_path, text)))
    assert sorted({c.params["threshold"] for c in cells if c.method == "iepf"}) == [0.007, 0.009, 0.011, 0.013, 0.015]


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("name: tiny", "name: tiny\nbogus: 1", "bogus"),
        ("seeds: [0, 1]", "seeds: [0, 0]", "seeds"),
        ("worlds: [demo]", "worlds: [atlantis]", "worlds"),
        ("{direction: combined}", "{direction: sideways}", "segmenters.0"),
        ("{method: ror,", "{method: nosuch,", "segmenters.0"),
        ("{final_batch: false}", "{final_batch: false, bogus: 2}", "slam.backend.bogus"),
        ("slam:", "simulation: {seed: 3}\nslam:", "simulation"),
        ("duration: 2.0", "duration: -1", "duration"),
    ],
)
def test_config_errors_name_file_and_key(tmp_path: Path, old: str, new: str, key: str) -> None:
    text = TINY.format(duration=2.0)
    assert old in text
    path = _write(tmp_path, text.replace(old, new))
    with pytest.raises(ConfigError) as e:
        load_experiment(path)
    msg = str(e.value)
    assert str(path) in msg and f"key '{key}" in msg and "\n" not in msg


def test_cli_config_error_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path, TINY.format(duration=2.0).replace("name: tiny", "name: tiny\nbogus: 1"))
    assert main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "bogus" in err[0]
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- perturbation


def test_perturb_rig_moves_only_tilted_scanners_by_the_magnitudes() -> None:
    rig = resolve_rig("itc_backpack")
    assert perturb_rig(rig, 0.0, 0.0, 1) is rig
    p = perturb_rig(rig, 0.5, 0.01, 3)
    assert p == perturb_rig(rig, 0.5, 0.01, 3)
    assert p != perturb_rig(rig, 0.5, 0.01, 4)
    for a, b in zip(rig.scanners, p.scanners, strict=True):
        Ta, Tb = a.T_body_scanner.matrix(), b.T_body_scanner.matrix()
        if a.name == rig.reference:
            np.testing.assert_array_equal(Ta, Tb)
            continue
        cos = (np.trace(Tb[:3, :3] @ Ta[:3, :3].T) - 1) / 2
        assert math.degrees(math.acos(min(1.0, cos))) == pytest.approx(0.5, abs=1e-6)
        assert np.linalg.norm(Tb[:3, 3] - Ta[:3, 3]) == pytest.approx(0.01, abs=1e-9)


# ----------------------------------------------------------------------------------- engine


def test_inline_sweep_resumes_after_interruption(tmp_path: Path) -> None:
    cells = _cells(tmp_path)
    out = tmp_path / "out"
    calls: list[str] = []
    with pytest.raises(Interrupt):
        run_sweep(cells, out, workers=0, cell_fn=interrupted_after_first(calls), progress=False)
    table = read_results(results_path(out))
    assert list(table["cell_id"]) == calls and len(calls) == 1
    seen: list[str] = []

    def recording(cell: Cell, o: str) -> dict[str, Any]:
        seen.append(cell.cell_id)
        return fake_cell(cell, o)

    s = run_sweep(cells, out, workers=0, cell_fn=recording, progress=False)
    assert s.n_skipped == 1 and s.n_ok == 5 and calls[0] not in seen
    assert sorted(read_results(results_path(out))["cell_id"]) == sorted(c.cell_id for c in cells)
    # everything done: nothing runs again
    assert run_sweep(cells, out, workers=0, cell_fn=recording, progress=False).n_skipped == 6
    assert len(seen) == 5


def test_failed_cells_are_recorded_and_retried_on_request(tmp_path: Path) -> None:
    cells = _cells(tmp_path)
    out = tmp_path / "out"
    s = run_sweep(cells, out, workers=0, cell_fn=failing_cell, progress=False)
    assert (s.n_ok, s.n_failed) == (2, 4)
    t = read_results(results_path(out))
    bad = t[t["status"] == "failed"]
    assert len(bad) == 4 and set(bad["method"]) == {"iepf"}
    assert all("iepf exploded on seed" in e for e in bad["error"])
    assert finished_cells(t) == {c.cell_id for c in cells}
    s2 = run_sweep(cells, out, workers=0, cell_fn=fake_cell, retry_failed=True, progress=False)
    assert (s2.n_skipped, s2.n_ok) == (2, 4)
    t2 = read_results(results_path(out))
    assert len(t2) == 6 and set(t2["status"]) == {"ok"}


def test_process_pool(tmp_path: Path) -> None:
    cells = _cells(tmp_path)[:2]
    s = run_sweep(cells, tmp_path / "out", workers=2, cell_fn=failing_cell, progress=False)
    assert s.n_ok + s.n_failed == 2
    t = read_results(results_path(tmp_path / "out"))
    expected = {c.cell_id: fake_cell(c, "")["ate_rmse_m"] for c in cells if c.method != "iepf"}
    ok = t[t["status"] == "ok"]
    assert dict(zip(ok["cell_id"], ok["ate_rmse_m"], strict=True)) == pytest.approx(expected)


@pytest.mark.parametrize("by_address", [False, True])
def test_dask_local_cluster(tmp_path: Path, by_address: bool) -> None:
    from distributed import Client, LocalCluster

    cells = _cells(tmp_path)[:3]
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, Client(cluster) as client:
        target = cluster.scheduler_address if by_address else client
        s = run_sweep(cells, tmp_path / "out", dask=target, cell_fn=failing_cell, progress=False)
    assert s.n_ok + s.n_failed == 3 and s.n_failed == sum(c.method == "iepf" for c in cells)
    t = read_results(results_path(tmp_path / "out"))
    assert sorted(t["cell_id"]) == sorted(c.cell_id for c in cells)


def test_run_cell_records_a_bad_cell_with_its_stage(tmp_path: Path) -> None:
    cell = replace(_cells(tmp_path)[0], rig="no_such_rig")
    row = run_cell(cell, str(tmp_path / "out"))
    assert row["status"] == "failed" and row["stage"] == "config" and "no_such_rig" in row["error"]
    assert (tmp_path / "out" / "cells" / cell.cell_id / "error.txt").is_file()


# ------------------------------------------------------------------------------------ cache


def test_simulation_cache_simulates_once_under_concurrency(tmp_path: Path) -> None:
    cells = _cells(tmp_path, duration=0.5)
    a, b = (c for c in cells if c.seed == 0 and c.method == "ror"), (c for c in cells if c.seed == 0 and c.method == "iepf")
    ca, cb = next(a), next(b)
    assert ca.sim_key == cb.sim_key
    results: list[Any] = []

    def get(cell: Cell) -> None:
        results.append(cached_simulation(tmp_path / "cache", cell.sim_key, cell.simulation))

    threads = [threading.Thread(target=get, args=(c,)) for c in (ca, cb)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert sorted(r.cached for r in results) == [False, True]
    entry = tmp_path / "cache" / ca.sim_key
    assert results[0].bag == results[1].bag == entry / "run.bag" and (entry / "run.gt" / "beams.npz").is_file()
    mtime = results[0].bag.stat().st_mtime_ns
    again = cached_simulation(tmp_path / "cache", cb.sim_key, cb.simulation)
    assert again.cached and again.bag.stat().st_mtime_ns == mtime
    assert not [p for p in (tmp_path / "cache").iterdir() if ".tmp" in p.name]


# ------------------------------------------------------------------------------ end to end


def test_real_cell_end_to_end_is_recorded(tmp_path: Path) -> None:
    """Simulate 2 s of the demo world, SLAM with RoR, evaluate, score: success or failure,
    the row must say which, with the metrics or the error."""
    cells = [c for c in _cells(tmp_path, duration=2.0) if c.method == "ror" and c.seed == 0]
    out = tmp_path / "out"
    assert main(["sweep", str(tmp_path / "exp.yaml"), "--out", str(out), "--workers", "0", "--quiet", "--dry-run"]) == 0
    s = run_sweep(cells, out, workers=0, progress=False)
    assert s.n_ok + s.n_failed == 1
    row = read_results(results_path(out)).iloc[0]
    assert row["cell_id"] == cells[0].cell_id and row["sim_cached"] == False  # noqa: E712
    assert 0 < row["cpu_cell_s"] and np.isfinite(row["t_cell_s"])
    assert (out / "cache" / cells[0].sim_key / "run.bag").is_file()
    assert not (out / "cells" / cells[0].cell_id / "run").exists()  # run folders are not kept
    if row["status"] == "ok":
        assert np.isfinite(row["ate_rmse_m"]) and np.isfinite(row["seg_overlap1"]) and row["seg_n_scans"] > 0
        assert (out / "cells" / cells[0].cell_id / "eval.json").is_file()
    else:
        assert row["status"] == "failed" and row["stage"] in ("slam", "evaluate", "segmentation metrics") and row["error"]


# ----------------------------------------------------------------------------------- report


def test_mean_ci_is_the_t_interval() -> None:
    m, h, n = mean_ci([1.0, 2.0, 3.0, float("nan")])
    assert (m, n) == (2.0, 3) and h == pytest.approx(stats.t.ppf(0.975, 2) / math.sqrt(3))
    assert math.isnan(mean_ci([4.0])[1]) and mean_ci([])[2] == 0


def _row(variant: str, seed: int, ate: float, status: str = "ok", **kw: Any) -> dict[str, Any]:
    fam, _, swept = variant.partition(" sigma=")
    return {
        "cell_id": f"{variant}-{seed}", "status": status, "stage": "" if status == "ok" else "slam",
        "error": "" if status == "ok" else "RuntimeError: diverged", "world": "demo", "noise": 0.003,
        "calib_rotation_deg": 0.0, "calib_translation_m": 0.0, "seed": seed, "segmenter": fam,
        "method": fam.split()[0], "variant": variant, "swept": f'{{"sigma": {swept}}}' if swept else "{}",
        "ate_rmse_m": ate, "drift_rpe_pct": 10 * ate, "cloud_median_m": ate / 10, "seg_overlap1": 0.9,
        "seg_ms_per_scan": 1.5, **kw,
    }


def test_report_on_a_hand_made_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rows = [_row("ror sigma=0.0095", s, a) for s, a in enumerate([0.010, 0.012, 0.014])]
    rows += [_row("ror sigma=0.011", s, a) for s, a in enumerate([0.020, 0.020, 0.020])]
    rows += [_row("iepf", s, a) for s, a in enumerate([0.05, 0.07, 0.06])]
    rows.append(_row("iepf", 3, math.nan, status="failed"))
    append_rows(results_path(tmp_path), rows)
    assert main(["report", str(tmp_path)]) == 0
    md = (tmp_path / "report.md").read_text()
    half = stats.t.ppf(0.975, 2) * 0.2 / math.sqrt(3)  # ATE in cm: 1.0, 1.2, 1.4
    assert f"| ror sigma=0.0095 | 3 | 1.200 ± {half:.3f} |" in md
    assert "| ror sigma=0.011 | 3 | 2.000 ± 0.000 |" in md
    assert "lowest mean ATE 1.200" in md and "**ror sigma=0.0095**" in md
    # map error (cloud_median = ATE / 10, in mm): ranked too; iepf's interval is disjoint from the best
    assert "lowest mean cloud-to-mesh median 1.200" in md and "worst iepf (3 of 4 seeds; 1 failed) 6.000" in md
    assert "demo, noise 3 mm: failed cells (seeds): iepf 1 of 4." in md
    assert "runner-up ror sigma=0.011 2.000 ± 0.000 mm (intervals disjoint)" in md
    assert "| iepf | demo | 3 | 3 | slam | RuntimeError: diverged |" in md
    for png in ("drift.png", "map_error.png", "segmentation.png", "time.png"):
        assert (tmp_path / png).stat().st_size > 1000 and f"]({png})" in md
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


def test_report_without_results_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["report", str(tmp_path)]) == 2
    assert "results.parquet" in capsys.readouterr().err


def test_append_replaces_a_cells_row(tmp_path: Path) -> None:
    p = results_path(tmp_path)
    append_rows(p, [_row("iepf", 0, 0.1, status="failed")])
    t = append_rows(p, [_row("iepf", 0, 0.2)])
    assert len(t) == 1 and t.iloc[0]["status"] == "ok"
    assert isinstance(read_results(p), pd.DataFrame) and len(read_results(p)) == 1


# --------------------------------------------------------------------- segmentation scores


def test_true_line_normals_in_the_scanner_frame() -> None:
    from backpack_slam.sweep.segeval import true_line_normals

    T = np.stack([np.eye(4), np.eye(4), np.eye(4)])
    T[1, :3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # yaw 90 deg: scanner x = world y
    n = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0]])  # wall x = 2 (twice), floor z = 0
    d = np.array([-2.0, -2.0, 0.0])
    out = true_line_normals(n, d, T)
    np.testing.assert_allclose(out[0], [1, 0], atol=1e-12)
    np.testing.assert_allclose(out[1], [0, -1], atol=1e-12)  # the wall is at scanner y = -2
    assert np.isnan(out[2]).all()


def test_segmentation_scores_rank_a_good_and_a_bad_segmenter(tmp_path: Path) -> None:
    from backpack_slam.sweep.segeval import score_segmenter

    cell = _cells(tmp_path, duration=0.5)[0]
    sim = cached_simulation(tmp_path / "cache", cell.sim_key, cell.simulation)
    rig = resolve_rig("itc_backpack")
    good = score_segmenter(sim.bag, sim.gt, rig, "ror", {}, scans_per_scanner=5)
    # a line-tracking threshold at 1 sigma of the noise cuts walls into pieces
    bad = score_segmenter(sim.bag, sim.gt, rig, "line_tracking", {"threshold": 0.003}, scans_per_scanner=5)
    assert good.n_scans == bad.n_scans == 15 and good.n_gt_segments > 15
    assert good.overlap1 > 0.6 and good.median_angle_deg < 0.5 and good.ms_per_scan > 0
    assert bad.overlap1 < good.overlap1 - 0.3
