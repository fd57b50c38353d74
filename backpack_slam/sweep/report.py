"""The sweep's report: ``DIR/report.md`` and PNG plots from ``DIR/results.parquet``.

Every metric is summarised per segmenter variant (family + swept parameters) and condition
(world, noise, calibration error) over the seeds: mean and a 95 % confidence interval of the
mean from Student's t distribution (``t_{0.975, n-1} s / sqrt(n)``; no interval with one
seed). Only successful cells enter the statistics; failed cells are listed with their errors.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from backpack_slam.sweep.results import read_results, results_path
from common.atomic import atomic_path

CONDITION = ["world", "noise", "calib_rotation_deg", "calib_translation_m"]


@dataclass(frozen=True)
class Metric:
    column: str
    title: str
    unit: str
    scale: float = 1.0  # displayed value = stored value * scale


DRIFT = [
    Metric("ate_rmse_m", "ATE RMSE (SE(3)-aligned)", "cm", 100.0),
    Metric("drift_rpe_pct", "drift, RPE over 10 m", "% (m/100 m)"),
    Metric("drift_endpoint_pct", "drift, end point", "% (m/100 m)"),
    Metric("drift_rot_deg_per_100m", "rotation drift", "deg/100 m"),
]
MAP = [
    Metric("cloud_median_m", "cloud-to-mesh median", "mm", 1000.0),
    Metric("cloud_p95_m", "cloud-to-mesh p95", "mm", 1000.0),
    Metric("plane_angle_median_deg", "plane angle error, median", "deg"),
    Metric("assoc_fraction_correct", "segments correctly associated", "fraction"),
]
SEGMENTATION = [
    Metric("seg_overlap1", "overlap1", ""),
    Metric("seg_overlap2", "overlap2", ""),
    Metric("seg_segments_per_gt", "segments per GT segment (1 ideal)", ""),
    Metric("seg_median_angle_deg", "median angle", "deg"),
    Metric("seg_boundary_precision", "boundary precision", ""),
    Metric("seg_boundary_recall", "boundary recall", ""),
]
TIME = [
    Metric("seg_ms_per_scan", "segmentation time per scanline", "ms"),
    Metric("t_slam_segmentation_s", "segmentation time in SLAM", "s"),
    Metric("t_slam_s", "SLAM wall time", "s"),
    Metric("cpu_cell_s", "CPU time per cell (simulation included when not cached)", "s"),
]


def mean_ci(values: Sequence[float] | np.ndarray, level: float = 0.95) -> tuple[float, float, int]:
    """(mean, half-width of the ``level`` t-interval of the mean, n) of the finite values;
    the half-width is NaN for n < 2 and 0 when every value is equal."""
    x = np.asarray(values, dtype=np.float64)
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return math.nan, math.nan, 0
    m = float(x.mean())
    if n < 2:
        return m, math.nan, n
    half = float(stats.t.ppf(0.5 + level / 2, n - 1) * x.std(ddof=1) / math.sqrt(n))
    return m, half, n


def summarise(ok: pd.DataFrame, metrics: Sequence[Metric]) -> pd.DataFrame:
    """One row per (condition, segmenter, variant): mean, CI half-width and n per metric."""
    keys = [*CONDITION, "segmenter", "variant"]
    rows = []
    for key, g in ok.groupby(keys, sort=True, dropna=False):
        row = dict(zip(keys, key, strict=True))
        row["seeds"] = int(g["seed"].nunique())
        for m in metrics:
            if m.column in g:
                mean, half, n = mean_ci(g[m.column].to_numpy(dtype=np.float64) * m.scale)
            else:
                mean, half, n = math.nan, math.nan, 0
            row[m.column] = mean
            row[m.column + "_ci"] = half
            row[m.column + "_n"] = n
        rows.append(row)
    return pd.DataFrame(rows)


def fmt(mean: float, half: float) -> str:
    if not math.isfinite(mean):
        return "n/a"
    digits = 3 if abs(mean) < 10 else 1
    s = f"{mean:.{digits}f}"
    return s + (f" ± {half:.{digits}f}" if math.isfinite(half) else "")


def condition_label(row: pd.Series | dict) -> str:
    cal = ""
    if row["calib_rotation_deg"] or row["calib_translation_m"]:
        cal = f", calibration error {row['calib_rotation_deg']:g} deg / {1000 * row['calib_translation_m']:g} mm"
    return f"{row['world']}, noise {1000 * row['noise']:g} mm{cal}"


def markdown_table(summary: pd.DataFrame, metrics: Sequence[Metric]) -> list[str]:
    head = ["segmenter", "seeds", *[f"{m.title} ({m.unit})" if m.unit else m.title for m in metrics]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for _, r in summary.iterrows():
        cells = [str(r["variant"]), str(r["seeds"])]
        cells += [fmt(r[m.column], r[m.column + "_ci"]) for m in metrics]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _swept_sort_key(swept_json: str) -> tuple[Any, ...]:
    """Variants of a family ordered by their swept values (numbers numerically)."""
    d = json.loads(swept_json) if swept_json else {}
    return tuple((0, float(v), "") if isinstance(v, int | float) else (1, 0.0, str(v)) for _, v in sorted(d.items()))


def variant_order(ok: pd.DataFrame) -> list[str]:
    """Every variant, grouped by family (in order of appearance), by swept value within one."""
    first = ok.drop_duplicates("variant")
    families = list(dict.fromkeys(first["segmenter"]))
    out: list[str] = []
    for fam in families:
        sub = first[first["segmenter"] == fam]
        out += sorted(sub["variant"], key=lambda v: _swept_sort_key(str(sub[sub["variant"] == v]["swept"].iloc[0])))
    return out


def plot_metrics(ok: pd.DataFrame, summary: pd.DataFrame, metrics: Sequence[Metric], path: Path, title: str) -> None:
    """One panel per metric: mean ± 95 % CI of every variant (x, grouped and coloured by
    family, ordered by swept value); one marker per condition (world, noise, calibration)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = variant_order(ok)
    xpos = {v: i for i, v in enumerate(order)}
    family = ok.drop_duplicates("variant").set_index("variant")["segmenter"].to_dict()
    colors = {f: f"C{i % 10}" for i, f in enumerate(dict.fromkeys(family[v] for v in order))}
    labels = [condition_label(r) for _, r in summary.iterrows()]
    conds = list(dict.fromkeys(labels))
    markers = "osD^v<>p*h"
    width = max(4.5, 0.35 * len(order) + 1.5)
    fig, axes = plt.subplots(len(metrics), 1, figsize=(width, 2.6 * len(metrics) + 1.2), squeeze=False, sharex=True)
    for ax, m in zip(axes[:, 0], metrics, strict=True):
        drawn = False
        for ci, cond in enumerate(conds):
            sub = summary[[lab == cond for lab in labels]]
            off = (ci - (len(conds) - 1) / 2) * min(0.6 / max(len(conds), 1), 0.15)
            for _, r in sub.iterrows():
                y, e = float(r[m.column]), float(r[m.column + "_ci"])
                if not math.isfinite(y):
                    continue
                drawn = True
                ax.errorbar(xpos[r["variant"]] + off, y, yerr=e if math.isfinite(e) else None, marker=markers[ci % 10],
                            color=colors[family[r["variant"]]], capsize=3, markersize=5)
        if not drawn:
            ax.text(0.5, 0.5, "no data", transform=ax.transAxes, ha="center", va="center", color="0.5")
        ax.set_ylabel(f"{m.title}\n({m.unit})" if m.unit else m.title, fontsize=8)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xticks(range(len(order)), order, rotation=60, ha="right", fontsize=8)
    for lab in axes[-1, 0].get_xticklabels():
        lab.set_color(colors[family[lab.get_text()]])
    legend = "; ".join(f"{markers[i % 10]} {c}" for i, c in enumerate(conds))
    axes[0, 0].set_title(f"{title}: mean ± 95 % CI over seeds\n{legend}", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def write_report(out_dir: str | Path) -> Path:
    """Write ``report.md`` and its PNGs into ``out_dir`` from its ``results.parquet``."""
    out = Path(out_dir)
    table = read_results(results_path(out))
    if table.empty:
        raise ValueError(f"{results_path(out)}: no results (run 'backpack-slam sweep' first)")
    for col in ("status", "variant", "segmenter", "seed", *CONDITION):
        if col not in table:
            raise ValueError(f"{results_path(out)}: column '{col}' missing")
    ok = table[table["status"] == "ok"]
    failed = table[table["status"] != "ok"]
    lines = [
        f"# Segmentation vs drift: {out.name}",
        "",
        f"{len(table)} cells: {len(ok)} succeeded, {len(failed)} failed. "
        f"Worlds: {', '.join(sorted(table['world'].astype(str).unique()))}; seeds: "
        f"{table['seed'].nunique()}. Values are means over seeds ± the half-width of the 95 % "
        "confidence interval of the mean (Student's t; none with one seed).",
        "",
    ]
    groups = [
        ("Drift", DRIFT, "drift.png"),
        ("Map error", MAP, "map_error.png"),
        ("Segmentation against the per-beam ground truth", SEGMENTATION, "segmentation.png"),
        ("Time", TIME, "time.png"),
    ]
    if not ok.empty:
        best = _ranking(ok, table)
        if best:
            lines += ["## Finding", "", *best, ""]
        for title, all_metrics, png in groups:
            # a column no cell wrote (an older engine's table) gets no empty panel
            metrics = [m for m in all_metrics if m.column in ok] or all_metrics
            summary = summarise(ok, metrics)
            plot_metrics(ok, summary, metrics, out / png, title)
            lines += [f"## {title}", "", f"![{title}]({png})", ""]
            for cond, sub in summary.groupby([*CONDITION], sort=True, dropna=False):
                lines += [f"### {condition_label(dict(zip(CONDITION, cond, strict=True)))}", ""]
                order = {v: i for i, v in enumerate(variant_order(ok))}
                lines += markdown_table(sub.sort_values("variant", key=lambda c: c.map(order)), metrics)
                lines.append("")
    lines += ["## Failed cells", ""]
    if failed.empty:
        lines.append("None.")
    else:
        lines += ["| variant | world | noise (mm) | seed | stage | error |", "|---|---|---|---|---|---|"]
        for _, r in failed.iterrows():
            err = str(r.get("error", "")).replace("|", "\\|")
            lines.append(f"| {r['variant']} | {r['world']} | {1000 * r['noise']:g} | {r['seed']} | {r.get('stage', '')} | {err} |")
    lines.append("")
    path = out / "report.md"
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines))
    return path


RANKED = [
    (DRIFT[0], "ATE"),
    (DRIFT[1], "RPE drift"),
    (MAP[0], "cloud-to-mesh median"),
]


def _named(r: pd.Series, n_all: dict[str, int]) -> str:
    """A summary row's variant, with its number of successful seeds when some failed."""
    v = str(r["variant"])
    n = n_all.get(v, 0)
    return v + (f" ({r['seeds']} of {n} seeds; {n - r['seeds']} failed)" if r["seeds"] < n else "")


def _ranking(ok: pd.DataFrame, table: pd.DataFrame) -> list[str]:
    """Per condition and ranked metric (ATE, RPE drift, map error), the variants ordered by
    mean (lower is better) and whether the best one's interval overlaps the runner-up's, as
    plain sentences; a variant with failed cells says on how many seeds its mean rests, and
    the failures per variant come first (a variant that fails is not a winner)."""
    out = []
    summary = summarise(ok, [m for m, _ in RANKED])
    for cond, sub in summary.groupby([*CONDITION], sort=True, dropna=False):
        label = condition_label(dict(zip(CONDITION, cond, strict=True)))
        in_cond = table[(table[CONDITION] == pd.Series(cond, index=CONDITION)).all(axis=1)]
        n_all = in_cond.groupby("variant")["seed"].nunique().to_dict()
        n_bad = in_cond[in_cond["status"] != "ok"].groupby("variant")["seed"].nunique().to_dict()
        if n_bad:
            bad = ", ".join(f"{v} {n_bad[v]} of {n_all[v]}" for v in sorted(n_bad))
            out.append(f"- {label}: failed cells (seeds): {bad}.")
        for m, name in RANKED:
            col, ci = m.column, m.column + "_ci"
            ranked = sub[np.isfinite(sub[col])].sort_values(col)
            if ranked.empty:
                continue
            b = ranked.iloc[0]
            text = f"- {label}: lowest mean {name} {fmt(b[col], b[ci])} {m.unit} with **{_named(b, n_all)}**"
            if len(ranked) > 1:
                r = ranked.iloc[1]
                overlap = (
                    not math.isfinite(b[ci]) or not math.isfinite(r[ci]) or b[col] + b[ci] >= r[col] - r[ci]
                )
                text += f"; runner-up {_named(r, n_all)} {fmt(r[col], r[ci])} {m.unit}" + (
                    " (confidence intervals overlap: not a significant difference)" if overlap else " (intervals disjoint)"
                )
            w = ranked.iloc[-1]
            text += f"; worst {_named(w, n_all)} {fmt(w[col], w[ci])} {m.unit}."
            out.append(text)
    return out
