"""Where a SLAM run's wall time goes, stage by stage, for several runs side by side: one stacked bar
per ``scripts/bench_slam.py`` table (its first method's column).

The estimator's stages (tracking, association, plane creation, back end, final batch, export) run
one after another in its process; the rest of the wall time (reading the IMU, the noise estimate,
taking the reader's scans off its queue, the planes' covariances and the residual statistics
after the batch) is shown as "other". The reader process's segmentation and lifting run beside them and are not part
of the bar.

Usage:
    .venv/bin/python scripts/plot_stages.py --out docs/figures/stages.png \\
        "seed 1, before=docs/figures/a.md" "seed 1, after=docs/figures/b.md" [--goal 150]
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

STAGES = ("tracking", "association", "plane_creation", "backend", "batch", "export")


def read_table(path: Path) -> dict[str, float]:
    """The stage times (s) and total wall (s) of a bench_slam.py markdown table."""
    out: dict[str, float] = {}
    for line in path.read_text().splitlines():
        m = re.match(r"\|\s*(?:\*\*)?time: ([a-z_ ]+?) \(s\)(?:\*\*)?(?: \(reader process\))?\s*\|\s*([0-9.]+)", line)
        if m:
            out[m.group(1).replace("total wall", "wall").strip()] = float(m.group(2))
    missing = [s for s in (*STAGES, "wall") if s not in out]
    if missing:
        raise ValueError(f"{path}: no row for {', '.join(missing)} (not a bench_slam.py table?)")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="LABEL=TABLE.md, in the order to draw")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--goal", type=float, default=None, help="a wall-time goal (s) drawn as a line")
    ap.add_argument("--title", default="10-minute office walk: wall time by stage")
    args = ap.parse_args(argv)
    rows = []
    for item in args.runs:
        label, sep, path = item.partition("=")
        if not sep:
            print(f"error: {item!r}: expected LABEL=TABLE.md", file=sys.stderr)
            return 2
        try:
            rows.append((label, read_table(Path(path))))
        except (OSError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    fig, ax = plt.subplots(figsize=(9, 0.55 * len(rows) + 1.6))
    colors = plt.get_cmap("tab10").colors
    for i, (_, t) in enumerate(rows):
        left = 0.0
        parts = [(s, t[s]) for s in STAGES] + [("other", max(0.0, t["wall"] - sum(t[s] for s in STAGES)))]
        for j, (stage, v) in enumerate(parts):
            ax.barh(i, v, left=left, color=colors[j % len(colors)], label=stage if i == 0 else None)
            if v >= 8:
                ax.text(left + v / 2, i, f"{v:.0f}", ha="center", va="center", fontsize=7, color="white")
            left += v
        ax.text(left + 1, i, f"{t['wall']:.1f} s", va="center", fontsize=8)
    if args.goal is not None:
        ax.axvline(args.goal, color="k", ls="--", lw=1)
        ax.text(args.goal, len(rows) - 0.4, f" goal {args.goal:.0f} s", fontsize=8)
    ax.set_yticks(range(len(rows)), [r[0] for r in rows])
    ax.invert_yaxis()
    ax.set_xlabel("wall time (s)")
    ax.set_title(args.title, fontsize=10)
    fig.legend(ncol=7, fontsize=7, loc="lower center")
    fig.tight_layout(rect=(0.0, 0.07, 1.0, 1.0))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(f".{args.out.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    tmp.replace(args.out)
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
