"""Plot peak memory against walk length (issue 27) from measured points.

The input is a JSON list of measurements ``{"label", "minutes", "peak_gb", "source"}`` (one
line per code revision: the points of one label are joined, dashed when their ``source`` is
``"extrapolated"``); the goal lines of issue 27 (4 GB
at 60 minutes, and from the 60-minute point of the latest revision measured beyond an hour,
growth under 0.5 GB per further hour) are drawn for reference. Records that also
give ``"cpu_per_data_s"`` (CPU seconds per data second, every process of the run) and
``"wall_per_data_s"`` are drawn in a second panel beside: time per data second against length.

Usage:
    .venv/bin/python scripts/plot_memory.py docs/figures/memory_vs_length.json docs/figures/memory_vs_length.png
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def _style(ax: Any, ylabel: str, fontsize: int, legend_loc: str, x_max: float = 60.0) -> None:
    """Axes against walk length (0 to ``x_max`` + 5 data minutes), from zero up, with a grid and
    a legend."""
    ax.set_xlabel("walk length (data minutes, office world)")
    ax.set_ylabel(ylabel)
    ax.set_xlim(0, max(60.0, x_max) + 5)
    ax.set_ylim(0, None)
    ax.grid(alpha=0.3)
    # below the axes: with a line per code revision the legend would cover the points
    ax.legend(fontsize=fontsize, loc="upper left", bbox_to_anchor=(0.0, -0.14), frameon=False)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path, help="JSON list of {label, minutes, peak_gb, source}")
    ap.add_argument("out", type=Path, help="image to write (.png or .svg)")
    args = ap.parse_args()
    rows = json.loads(args.data.read_text())
    if not isinstance(rows, list) or not all({"label", "minutes", "peak_gb"} <= set(r) for r in rows):
        ap.error(f"{args.data}: expected a list of {{label, minutes, peak_gb}} records")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    timed = [r for r in rows if "cpu_per_data_s" in r]
    x_max = max(float(r["minutes"]) for r in rows)
    n_lines = max(len({r["label"] for r in rows}), 2 * len({r["label"] for r in timed}))
    height = 4.2 + 0.16 * n_lines
    if timed:
        fig, (ax, ax_t) = plt.subplots(1, 2, figsize=(12, height), gridspec_kw={"width_ratios": [1.4, 1.0]})
        for label in dict.fromkeys(r["label"] for r in timed):
            mine = sorted((r for r in timed if r["label"] == label), key=lambda r: r["minutes"])
            m = [r["minutes"] for r in mine]
            ax_t.plot(m, [r["cpu_per_data_s"] for r in mine], "o-", label=f"CPU s / data s: {label}")
            if all("wall_per_data_s" in r for r in mine):
                ax_t.plot(m, [r["wall_per_data_s"] for r in mine], "s:", label=f"wall s / data s: {label}")
        _style(ax_t, "seconds per data second", 7, "lower right", x_max)
    else:
        fig, ax = plt.subplots(figsize=(7, height))
    for label in dict.fromkeys(r["label"] for r in rows):
        mine = [r for r in rows if r["label"] == label]
        pts = sorted((r["minutes"], r["peak_gb"]) for r in mine)
        style = "o--" if any(r.get("source") == "extrapolated" for r in mine) else "o-"
        ax.plot([p[0] for p in pts], [p[1] for p in pts], style, label=label)
        for m, g in pts:
            ax.annotate(f"{g:.2f}", (m, g), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.axhline(4.0, color="grey", ls="--", lw=0.8)
    ax.plot([60], [4.0], "kx")
    ax.annotate("goal: < 4 GB at 60 min", (60, 4.0), textcoords="offset points", xytext=(-120, 6), fontsize=8)
    longer = [r for r in rows if r["minutes"] > 60]
    if longer:  # the growth goal from the 60-minute point of the latest revision measured beyond it
        label = longer[-1]["label"]
        at60 = [r["peak_gb"] for r in rows if r["label"] == label and r["minutes"] == 60]
        if at60:
            ax.plot([60, x_max], [at60[0], at60[0] + 0.5 * (x_max - 60) / 60], color="grey", ls=":", lw=1.0)
            ax.annotate("goal: < +0.5 GB per further hour", (x_max, at60[0] + 0.5 * (x_max - 60) / 60),
                        textcoords="offset points", xytext=(-170, -16), fontsize=8)
    _style(ax, "peak memory (GB)", 8, "upper left", x_max)
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    return 0


if __name__ == "__main__":
    sys.exit(main())
