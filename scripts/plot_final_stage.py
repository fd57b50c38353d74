"""The final batch's variants and its Gauss-Newton iterations, from a JSON of forked final stages
(``docs/figures/final_stage_s30.json``: one walk run once, its final stage run once per variant).

Left: the final batch's stage time per variant, for the hour and the 10-minute walk, each bar
labelled with the start-aligned ATE (a variant that changes the estimate is marked by it).
Right: per iteration of the solves, the error's actual relative decrease against what the linear
model predicted (``slam.backend.solver.predicted_end``), with the stopping rule's tolerance and
the margin under which a step is taken as the last one (not linearised again).

Usage:
    .venv/bin/python scripts/plot_final_stage.py docs/figures/final_stage_s30.json \\
        --out docs/figures/final_stage_s30.png [--tolerance 1e-3 --margin 0.5]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def load(path: Path) -> dict[str, Any]:
    """The JSON, checked for the fields the plot reads."""
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable JSON file ({e})") from None
    for key in ("hour", "ten_minutes", "hour_iterations", "ten_minute_iterations"):
        if key not in data:
            raise ValueError(f"{path}: no '{key}' field")
    return data


def plot(data: dict[str, Any], out: Path, tolerance: float, margin: float) -> None:
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 5))
    labels: list[str] = []
    times: list[float] = []
    colours: list[str] = []
    notes: list[str] = []
    for walk, colour in (("hour", "tab:blue"), ("ten_minutes", "tab:orange")):
        for name, v in data[walk].items():
            labels.append(f"{'60 min' if walk == 'hour' else '10 min'}: {name}")
            times.append(float(v["batch"]))
            colours.append(colour)
            notes.append(f"ATE {v['ate_start_mm']:.2f} / {v['ate_se3_mm']:.2f} mm")
    y = range(len(labels))
    ax.barh(list(y), times, color=colours)
    for i, (t, n) in enumerate(zip(times, notes, strict=True)):
        ax.text(t, i, f" {t:.0f} s, {n}", va="center", fontsize=8)
    ax.set_yticks(list(y), labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("final batch (s, stage timer)")
    ax.set_xlim(0, max(times) * 1.6)
    ax.set_title("final stage forked per variant (same walk)")
    for key, marker, name in (("hour_iterations", "o", "60 min"), ("ten_minute_iterations", "s", "10 min")):
        rows = data[key]
        actual = [(before - after) / before for before, after, _ in rows]
        predicted = [p for _, _, p in rows]
        bx.loglog(predicted, actual, marker, label=name, alpha=0.8)
    lo = min(min(p for *_, p in data[k]) for k in ("hour_iterations", "ten_minute_iterations")) / 2
    bx.plot([lo, 1], [lo, 1], "k:", lw=1, label="actual = predicted")
    bx.axhline(tolerance, color="tab:red", lw=1, label=f"stopping rule ({tolerance:g})")
    bx.axvline(margin * tolerance, color="tab:green", lw=1, label=f"taken as the last step (< {margin:g} x rule)")
    bx.set_xlabel("predicted relative decrease (linear model)")
    bx.set_ylabel("actual relative decrease")
    bx.set_title("Gauss-Newton iterations of the final batch's solves")
    bx.legend(fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.stem + ".tmp" + out.suffix)
    fig.savefig(tmp, dpi=110)
    tmp.replace(out)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("json", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--tolerance", type=float, default=1e-3)
    ap.add_argument("--margin", type=float, default=0.5)
    args = ap.parse_args(argv)
    try:
        plot(load(args.json), args.out, args.tolerance, args.margin)
    except ValueError as e:
        print(f"plot_final_stage.py: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
