"""Segmentation on real scanners: noise-derived ("auto") parameters against the fixed defaults.

Per real log (``--real``: the Radish CARMEN logs ACES, Intel and Freiburg 079,
and both topics of the ROS1 obstacle-detector bag) ``--scans`` scans spread
evenly over the log are read; the scanner's noise model is estimated from them
(``segmentation.noise.estimate``), and every method segments them twice: at its
fixed defaults (``segmentation.get(name)``) and with the defaults derived from
the model (``segmentation.get(name, noise=model)``). Measured:

- coverage: the share of valid points that lie in a segment;
- segments per scan (mean);
- straightness: the median over all segments of the segment's fit residual
  (rms of the orthogonal distances to its line) over the model's noise at the
  segment's centroid range. Orthogonal residuals of range noise are at most the
  range noise (times cos of the incidence), so a value near or below 1 means
  the segments are straight to the noise; a bent or two-faced segment shows
  up as a larger value.

Writes a markdown table (``--out``; printed too) and a figure (``--figure``) of
``--panels`` scans per log segmented by RoR with auto parameters, each
segment's fitted line drawn over its points. The C++ ``laser_line_extraction``
peer is not installed here, so its column is left out (the issue's reference:
about 2.5 lines per ACES scan).

Usage: ``python scripts/bench_segmentation_real.py [--out docs/bench_segmentation_real.md]
[--figure docs/figures/segmentation_real.png] [--scans 60]``.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import segmentation as sg
from segmentation.noise import NoiseModel
from slam.io import open_scans

# ../shared/data/real beside the checkout (or beside the folder of worktrees holding it)
DEFAULT_REAL = next((p / "shared" / "data" / "real" for p in Path(__file__).resolve().parents[2:4]
                     if (p / "shared" / "data" / "real").is_dir()), Path("../shared/data/real"))
DEFAULT_METHODS = ("ror", "line_tracking", "split_and_merge", "iepf", "sef", "ransac", "hough")
BAG = "obstacle_detector_scans_demo.bag"


@dataclass(frozen=True)
class Log:
    """One real scanner stream: a file and, for a bag, one topic."""

    name: str
    file: str
    topic: str | None = None
    beams: str = ""


LOGS = (
    Log("aces", "aces-corrected.log.gz", beams="180, 1 deg"),
    Log("intel", "intel-corrected.log.gz", beams="180, 1 deg"),
    Log("freiburg 079", "freiburg-079-corrected.log.gz", beams="360, 0.5 deg"),
    Log("bag /front_scan", BAG, "/front_scan", "726, 0.35 deg"),
    Log("bag /rear_scan", BAG, "/rear_scan", "726, 0.35 deg"),
)


@dataclass
class Score:
    """Counts of one method on one log's scans."""

    valid: int = 0
    in_segments: int = 0
    segments: int = 0
    scans: int = 0
    skipped: int = 0
    ratios: list[float] | None = None

    @property
    def coverage(self) -> float:
        return self.in_segments / max(self.valid, 1)

    @property
    def per_scan(self) -> float:
        return self.segments / max(self.scans, 1)

    @property
    def residual(self) -> float:
        return float(np.median(self.ratios)) if self.ratios else float("nan")


def read_spread(path: Path, topic: str | None, n: int) -> list[sg.Scanline]:
    """``n`` scans spread evenly over the stream (all of them if it has fewer)."""
    scans = list(open_scans(path, topics=[topic] if topic else None))
    if len(scans) <= n:
        return scans
    idx = np.unique(np.linspace(0, len(scans) - 1, n).round().astype(int))
    return [scans[i] for i in idx]


def score(segmenter: sg.Segmenter, scans: Sequence[sg.Scanline], model: NoiseModel) -> Score:
    """Coverage, segments and residual ratios of ``segmenter`` on ``scans``."""
    s = Score(ratios=[])
    assert s.ratios is not None
    for line in scans:
        try:
            seg = segmenter.segment(line)
        except ValueError:
            s.skipped += 1
            continue
        s.scans += 1
        s.valid += line.n_valid
        s.in_segments += int(np.count_nonzero(seg.labels[line.valid_index] >= 0))
        s.segments += seg.n_segments
        r = np.hypot(seg.centroid[:, 0], seg.centroid[:, 1])
        s.ratios.extend((seg.rms / np.asarray(model.sigma(r))).tolist())
    return s


def run(real: Path, methods: Sequence[str], n_scans: int) -> tuple[list[tuple[Log, NoiseModel, list[sg.Scanline]]],
                                                                   dict[tuple[str, str], tuple[Score, Score]]]:
    """Models and (defaults, auto) scores per (log, method)."""
    logs = []
    results: dict[tuple[str, str], tuple[Score, Score]] = {}
    for log in LOGS:
        path = real / log.file
        if not path.is_file():
            print(f"skipping {log.name}: {path} not found", file=sys.stderr)
            continue
        scans = read_spread(path, log.topic, n_scans)
        model = sg.noise.estimate(scans)
        logs.append((log, model, scans))
        for m in methods:
            results[(log.name, m)] = (score(sg.get(m), scans, model), score(sg.get(m, noise=model), scans, model))
    return logs, results


def _pct(x: float) -> str:
    return f"{100 * x:.0f} %"


def table(logs: Sequence[tuple[Log, NoiseModel, list[sg.Scanline]]], methods: Sequence[str],
          results: dict[tuple[str, str], tuple[Score, Score]]) -> str:
    """The markdown tables: the noise models, then per method and log defaults vs auto."""
    out = ["| log (beams) | scans | range noise at median range | growth | quantisation | angular step |",
           "|---|---|---|---|---|---|"]
    for log, model, scans in logs:
        growth = f"{1e3 * model.sigma0:.1f} mm + {1e3 * model.slope:.2f} mm/m r" if model.slope else "constant"
        quant = f"{1e3 * model.quantum:g} mm" if model.quantum else "none"
        out.append(f"| {log.name} ({log.beams}) | {len(scans)} | {1e3 * model.sigma_ref:.1f} mm at "
                   f"{model.range_ref:.1f} m | {growth} | {quant} | {math.degrees(model.angle_step):.4g} deg |")
    out += ["", "Coverage / segments per scan / median residual over the noise, fixed defaults -> auto:", "",
            "| method | " + " | ".join(log.name for log, _, _ in logs) + " |",
            "|---|" + "---|" * len(logs)]
    for m in methods:
        cells = []
        for log, _, _ in logs:
            d, a = results[(log.name, m)]
            cells.append(f"{_pct(d.coverage)} / {d.per_scan:.1f} / {d.residual:.2f} -> "
                         f"**{_pct(a.coverage)} / {a.per_scan:.1f} / {a.residual:.2f}**")
        out.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def figure(path: Path, logs: Sequence[tuple[Log, NoiseModel, list[sg.Scanline]]], n_panels: int) -> None:
    """``n_panels`` scans per log (rows), RoR with auto parameters, fitted lines drawn."""
    from matplotlib.figure import Figure

    from backpack_slam.commands._segplot import draw_segmentation, save_figure

    fig = Figure(figsize=(4.2 * n_panels, 4.2 * len(logs)), layout="constrained")
    axes = fig.subplots(len(logs), n_panels, squeeze=False)
    for row, (log, model, scans) in zip(axes, logs, strict=True):
        seg = sg.get("ror", noise=model)
        picks = np.linspace(0, len(scans) - 1, n_panels + 2)[1:-1].round().astype(int)
        for ax, k in zip(row, picks, strict=True):
            line = scans[int(k)]
            draw_segmentation(ax, line, seg.segment(line), f"{log.name}, scan {int(k)} of {len(scans)}")
            ax.tick_params(labelsize=7)
            ax.xaxis.label.set_size(7)
            ax.yaxis.label.set_size(7)
    fig.suptitle("RoR with parameters from each scanner's estimated noise model (black: fitted lines)", fontsize=11)
    save_figure(fig, path, dpi=90)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", type=Path, default=DEFAULT_REAL, help="folder of the real logs")
    ap.add_argument("--scans", type=int, default=60, help="scans per log, spread over it")
    ap.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS))
    ap.add_argument("--out", type=Path, help="write the markdown tables here")
    ap.add_argument("--figure", type=Path, help="write the figure (PNG) here")
    ap.add_argument("--panels", type=int, default=3, help="scans per log in the figure")
    args = ap.parse_args(argv)
    logs, results = run(args.real, args.methods, args.scans)
    if not logs:
        print(f"no real logs found in {args.real}", file=sys.stderr)
        return 1
    text = table(logs, args.methods, results)
    for _, model, _ in logs:
        print(model)
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    if args.figure is not None:
        figure(args.figure, logs, args.panels)
        print(f"figure: {args.figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
