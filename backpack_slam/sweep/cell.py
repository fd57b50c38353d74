"""One cell of a sweep: simulate (cached), run SLAM, evaluate, score the segmenter.

``run_cell(cell, out_dir)`` never raises for a failure of the work itself: it returns the
result row with ``status = "failed"``, the stage that failed and the error on one line, so a
sweep goes on. The row is a flat dict of plain values (a row of ``results.parquet``).
Folders: ``DIR/cache/<sim_key>/`` (shared bags), ``DIR/cells/<cell_id>/`` (``summary.json``
and ``eval.json`` of the run; the whole run folder too with ``keep_runs``).
"""

from __future__ import annotations

import math
import shutil
import time
import traceback
from pathlib import Path
from typing import Any

from backpack_slam.sweep.plan import Cell

STATUS_OK = "ok"
STATUS_FAILED = "failed"


def _get(d: Any, *keys: str) -> float:
    """A nested number of an eval/summary dict, NaN when absent."""
    for k in keys:
        if not isinstance(d, dict) or d.get(k) is None:
            return math.nan
        d = d[k]
    try:
        return float(d)
    except (TypeError, ValueError):
        return math.nan


def eval_metrics(ev: dict[str, Any]) -> dict[str, float]:
    """The result-table columns of an ``eval.json`` dict."""
    tr = ev.get("trajectory", {})
    return {
        "path_length_m": _get(tr, "path_length_m"),
        "ate_rmse_m": _get(tr, "ate_m", "se3_aligned", "rmse"),
        "ate_start_rmse_m": _get(tr, "ate_m", "start_aligned", "rmse"),
        "rpe_1m_mean_m": _get(tr, "rpe_1m", "translation_m", "mean"),
        "rpe_10m_mean_m": _get(tr, "rpe_10m", "translation_m", "mean"),
        "drift_endpoint_pct": _get(tr, "drift_per_100m", "endpoint_percent"),
        "drift_rpe_pct": _get(tr, "drift_per_100m", "rpe_percent"),
        "drift_rot_deg_per_100m": _get(tr, "drift_per_100m", "rotation_deg"),
        "plane_angle_median_deg": _get(ev, "planes", "angle_deg", "median"),
        "plane_angle_p95_deg": _get(ev, "planes", "angle_deg", "p95"),
        "plane_offset_median_m": _get(ev, "planes", "offset_m", "median"),
        "planes_matched": _get(ev, "planes", "n_matched"),
        "planes_duplicated": _get(ev, "planes", "n_duplicates"),
        "cloud_median_m": _get(ev, "cloud", "distance_m", "median"),
        "cloud_p95_m": _get(ev, "cloud", "distance_m", "p95"),
        "cloud_mean_m": _get(ev, "cloud", "distance_m", "mean"),
        "assoc_fraction_associated": _get(ev, "association", "fraction_associated"),
        "assoc_fraction_correct": _get(ev, "association", "fraction_correct"),
    }


def summary_metrics(summary: dict[str, Any]) -> dict[str, float]:
    """Counts and timings of a run's ``summary.json`` dict."""
    out = {f"t_slam_{k}_s": float(v) for k, v in summary.get("timings", {}).items()}
    for k in ("segments", "segments_associated", "planes", "knots"):
        out[f"n_{k}"] = _get(summary, "counts", k)
    out["realtime_factor"] = _get(summary, "realtime_factor")
    return out


def run_cell(cell: Cell, out_dir: str) -> dict[str, Any]:
    """Run ``cell`` under the sweep folder ``out_dir``; the result row (see the module doc)."""
    from backpack_slam.sweep.cache import cached_simulation
    from backpack_slam.sweep.perturb import perturb_rig
    from backpack_slam.sweep.segeval import score_segmenter
    from common.atomic import read_json, write_json
    from common.rig import resolve_rig
    from slam.config import SlamConfig
    from slam.evaluate import evaluate, write_eval_json
    from slam.run import run_slam

    out = Path(out_dir)
    row: dict[str, Any] = cell.describe()
    row.update(status=STATUS_FAILED, stage="", error="")
    cell_dir = out / "cells" / cell.cell_id
    run_dir = (out / "runs" / cell.cell_id) if cell.keep_runs else (cell_dir / "run")
    t_cell, cpu_cell = time.perf_counter(), time.process_time()
    stage = "config"
    try:
        true_rig = resolve_rig(cell.rig)
        slam_rig = perturb_rig(true_rig, cell.calib_rotation_deg, cell.calib_translation_m, cell.seed)
        cfg = SlamConfig.model_validate(cell.slam)

        stage = "simulate"
        sim = cached_simulation(out / "cache", cell.sim_key, cell.simulation)
        row.update(sim_cached=sim.cached, t_simulate_s=sim.seconds)

        stage = "slam"
        cell_dir.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        summary = run_slam(sim.bag, slam_rig, cfg, run_dir, progress=False)
        row["t_slam_s"] = time.perf_counter() - t0
        row.update(summary_metrics(summary))

        stage = "evaluate"
        t0 = time.perf_counter()
        result = evaluate(run_dir, sim.gt)
        write_eval_json(cell_dir / "eval.json", result)
        row.update(eval_metrics(read_json(cell_dir / "eval.json")))
        row["t_evaluate_s"] = time.perf_counter() - t0

        stage = "segmentation metrics"
        sm = cell.segmentation_metrics
        if sm["scans_per_scanner"] > 0:
            t0 = time.perf_counter()
            scores = score_segmenter(
                sim.bag, sim.gt, true_rig, cell.method, cell.params,
                scans_per_scanner=sm["scans_per_scanner"], gt_min_run=sm["gt_min_run"], tolerance=sm["tolerance"],
            )
            row.update(scores.row())
            row["t_segeval_s"] = time.perf_counter() - t0
        write_json(cell_dir / "summary.json", summary)
        row.update(status=STATUS_OK, stage="")
    except Exception as e:
        row.update(stage=stage, error=one_line_error(e))
        cell_dir.mkdir(parents=True, exist_ok=True)
        (cell_dir / "error.txt").write_text(traceback.format_exc())
    finally:
        if not cell.keep_runs:
            shutil.rmtree(run_dir, ignore_errors=True)
    row["t_cell_s"] = time.perf_counter() - t_cell
    # CPU seconds of this worker: the cost of the cell on an idle core, whatever the load
    row["cpu_cell_s"] = time.process_time() - cpu_cell
    return row


def one_line_error(e: BaseException) -> str:
    """``Type: message`` on one line (at most 500 characters)."""
    text = " ".join(str(e).split()) or "(no message)"
    return f"{type(e).__name__}: {text}"[:500]
