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
from typing import Any

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
    out = ["| log (beams) | scans | range noise at median range | growth | beam to beam | quantisation | "
           "angular step |",
           "|---|---|---|---|---|---|---|"]
    for log, model, scans in logs:
        growth = f"{1e3 * model.sigma0:.1f} mm + {1e3 * model.slope:.2f} mm/m r" if model.slope else "constant"
        quant = f"{1e3 * model.quantum:g} mm" if model.quantum else "none"
        out.append(f"| {log.name} ({log.beams}) | {len(scans)} | {1e3 * model.sigma_ref:.1f} mm at "
                   f"{model.range_ref:.1f} m | {growth} | {1e3 * model.beam_sigma:.1f} mm | {quant} | "
                   f"{math.degrees(model.angle_step):.4g} deg |")
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


def _picks(scans: Sequence[sg.Scanline], n: int) -> list[int]:
    """``n`` scan indices spread over the list (not its first and last scan)."""
    return [int(k) for k in np.linspace(0, len(scans) - 1, n + 2)[1:-1].round()]


def _panel(ax: Any, line: sg.Scanline, seg: sg.Segmentation, title: str) -> None:
    """One segmented scan, zoomed to the points within the 95 % quantile of the ranges."""
    from backpack_slam.commands._segplot import draw_segmentation

    draw_segmentation(ax, line, seg, title)
    pts = line.points_xy
    r = np.hypot(pts[:, 0], pts[:, 1])
    near = pts[r <= np.quantile(r, 0.95)]
    lo, hi = np.minimum(near.min(axis=0), 0.0) - 0.5, np.maximum(near.max(axis=0), 0.0) + 0.5
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.tick_params(labelsize=7)
    ax.xaxis.label.set_size(7)
    ax.yaxis.label.set_size(7)


def goals(logs: Sequence[tuple[Log, NoiseModel, list[sg.Scanline]]],
          results: dict[tuple[str, str], tuple[Score, Score]]) -> str:
    """Issue 25's goals for RoR with auto parameters, checked per log (markdown)."""
    out = ["| log | coverage (goal) | segments per scan | median residual / noise (goal <= 1.5) |",
           "|---|---|---|---|"]
    for i, (log, _, _) in enumerate(logs):
        d, a = results[(log.name, "ror")]
        if i == 0:
            cov = f"{_pct(a.coverage)} (>= 40 %: {'met' if a.coverage >= 0.4 else 'NOT met'})"
            per = f"{a.per_scan:.1f} (>= 2: {'met' if a.per_scan >= 2 else 'NOT met'})"
        else:
            cov = (f"{_pct(a.coverage)} (>= today's {_pct(d.coverage)}: "
                   f"{'met' if a.coverage >= d.coverage else 'NOT met'})")
            per = f"{a.per_scan:.1f}"
        res = f"{a.residual:.2f} ({'met' if a.residual <= 1.5 else 'NOT met'})"
        out.append(f"| {log.name} | {cov} | {per} | {res} |")
    return "\n".join(out) + "\n"


def document(logs: Sequence[tuple[Log, NoiseModel, list[sg.Scanline]]], methods: Sequence[str],
             results: dict[tuple[str, str], tuple[Score, Score]], out: Path, figures: Sequence[Path]) -> str:
    """The whole markdown report: method, the measured tables, the goals and the figures."""
    n = max(len(scans) for _, _, scans in logs)
    links = "\n\n".join(f"![{f.stem}]({_relative(f, out.parent)})" for f in figures)
    return f"""# Segmentation on real scanners: noise-derived parameters (issue 25)

Every segmenter's fixed defaults are stated for a UTM-30LX indoors: about 3 mm range noise at
0.25 deg steps. `segmentation.noise.estimate(scans)` measures a scanner's noise model from its
own scans (range noise and its growth with range, range quantisation, angular step; see the
module docstring), and `segmentation.get(name, noise=model)` derives every parameter not given
explicitly from it: thresholds scale with the noise (RoR's sigma is 9.5 mm / 3 mm = 3.17 times
the noise, times the noise's independent share when the range errors are correlated along the
scan: `segmentation.base.independent_share`, the beam-to-beam over the lagged noise, counted as
white above 0.8; the URG bag's topics: about 0.8 and 0.55), segment sizes with the angular step (the same metric length at 5 m: RoR's 15 points
at 0.25 deg are 8 at 1 deg, never fewer than 8), `max_gap` with the beam spacing. With the
reference model (3 mm, 0.25 deg) the derived parameters are the fixed defaults exactly, and
without a model nothing changes (the SLAM configuration passes explicit parameters).

Measured with `python scripts/bench_segmentation_real.py --out {out} --figure {figures[0] if figures else 'FIG.png'}`
on up to {n} scans spread evenly over each log; the noise model of each log is estimated from the
same scans. Per method: **coverage** (share of valid points in a segment), **segments per scan**
and the **median residual over the noise** (per segment: the rms of its points' orthogonal
distances to its fitted line over the model's noise at the segment's range; the median over all
segments; near or below 1: straight to the noise, a segment bent round a corner or an arc shows a
larger value). Each cell: fixed defaults -> **auto** (noise-derived).

The C++ `laser_line_extraction` peer is not installed on this machine, so it has no column here;
the issue's reference for it is about 2.5 lines per ACES scan (its default range noise is 2 cm).

## Noise models

{table(logs, methods, results)}
## Goals (RoR, auto parameters)

{goals(logs, results)}
## Figures

{links}

## Notes

- *Range noise* is the effective noise a line fit sees: quantisation included (`q^2 / 12`), and
  measured over 9-beam stretches (triples 4 beams apart) because real scanners' range errors are
  correlated along the scan. The *beam to beam* column is the same estimate from consecutive
  beams at the same range: on the SICK logs the 9-beam value is about a fifth higher, on the bag's
  Hokuyo-class scanners one and a half to two times higher (the long wall of the front scanner,
  its quadratic trend removed, scatters about 9 mm about its line with a lag-1 autocorrelation of
  the range errors of about 0.9, in line with the URG-04LX's +-10 mm accuracy). On simulated white
  noise both agree within a few per cent (`tests/test_noise.py`).
- The bag's front scanner sees one long wall, partly at grazing incidence, whose points bend by
  up to about 10 cm along its 5 m. RoR follows it with a few segments whose rms is about 1.7 times the estimated
  noise (RoR tolerates a single point up to 9.5 noise widths and runs of points up to about 2.5
  noise widths; split-and-merge cuts the same wall into shorter pieces and stays near 1). A
  noise estimate from consecutive beams (lag 1) gives the same ratio: the wall's bends are larger
  than the scanner's noise at any scale a local estimate can see.
- Far ranges: the model's growth with range is fitted where the data are (the bins' median
  ranges), and extrapolates linearly beyond: on ACES the noise at 9 m is taken as about 6 cm, and
  RoR's few-point segments there are lenient (a curved far wall can become one line, see the
  ACES panels).
"""


def _relative(path: Path, start: Path) -> str:
    import os

    return os.path.relpath(path.resolve(), start.resolve())


def figure(path: Path, logs: Sequence[tuple[Log, NoiseModel, list[sg.Scanline]]], n_panels: int) -> None:
    """``n_panels`` scans per log (rows), RoR with auto parameters, fitted lines drawn."""
    from matplotlib.figure import Figure

    from backpack_slam.commands._segplot import save_figure

    fig = Figure(figsize=(4.2 * n_panels, 4.2 * len(logs)), layout="constrained")
    axes = fig.subplots(len(logs), n_panels, squeeze=False)
    for row, (log, model, scans) in zip(axes, logs, strict=True):
        seg = sg.get("ror", noise=model)
        for ax, k in zip(row, _picks(scans, n_panels), strict=True):
            _panel(ax, scans[k], seg.segment(scans[k]), f"{log.name}, scan {k} of {len(scans)}")
    fig.suptitle("RoR with parameters from each scanner's estimated noise model (black: fitted lines; "
                 "grey: unsegmented)", fontsize=11)
    save_figure(fig, path, dpi=90)


def figure_defaults(path: Path, log: Log, model: NoiseModel, scans: Sequence[sg.Scanline], n_panels: int) -> None:
    """One log's scans, RoR at its fixed defaults (top row) and with auto parameters (bottom row)."""
    from matplotlib.figure import Figure

    from backpack_slam.commands._segplot import save_figure

    fig = Figure(figsize=(4.2 * n_panels, 8.4), layout="constrained")
    axes = fig.subplots(2, n_panels, squeeze=False)
    for row, (what, seg) in zip(axes, (("fixed defaults", sg.get("ror")), ("auto", sg.get("ror", noise=model))),
                                strict=True):
        for ax, k in zip(row, _picks(scans, n_panels), strict=True):
            _panel(ax, scans[k], seg.segment(scans[k]), f"{log.name}, scan {k}: {what}")
    fig.suptitle(f"{log.name}: RoR at its fixed defaults (sigma 9.5 mm, min_len 15) and with parameters from "
                 f"the estimated noise ({1e3 * model.sigma_ref:.0f} mm)", fontsize=11)
    save_figure(fig, path, dpi=90)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", type=Path, default=DEFAULT_REAL, help="folder of the real logs")
    ap.add_argument("--scans", type=int, default=60, help="scans per log, spread over it")
    ap.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS))
    ap.add_argument("--out", type=Path, help="write the markdown report here")
    ap.add_argument("--figure", type=Path, help="write the figure (PNG) here")
    ap.add_argument("--panels", type=int, default=3, help="scans per log in the figure")
    args = ap.parse_args(argv)
    logs, results = run(args.real, args.methods, args.scans)
    if not logs:
        print(f"no real logs found in {args.real}", file=sys.stderr)
        return 1
    for _, model, _ in logs:
        print(model)
    print(table(logs, args.methods, results))
    print(goals(logs, results))
    figures: list[Path] = []
    if args.figure is not None:
        figure(args.figure, logs, args.panels)
        first = logs[0]
        second = args.figure.with_name(f"{args.figure.stem}_{first[0].name.split()[0]}_defaults{args.figure.suffix}")
        figure_defaults(second, *first, args.panels)
        figures = [args.figure, second]
        print(f"figures: {args.figure}, {second}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(document(logs, args.methods, results, args.out, figures))
        print(f"report: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
