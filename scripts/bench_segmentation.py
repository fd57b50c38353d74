"""Scans per second of every registered segmenter, on one core, with ratios to split_and_merge.

Data sets (scanlines built once, outside the timing):
- ``office``: 1081-beam synthetic scanlines, half ``figure1`` noise draws and
  half ``random_room`` offices (boards, doors, 2-5 mm noise);
- ``figure1``: 1081-beam ``figure1`` noise draws only (the paper's scene: long
  walls, RoR's costliest case);
- every CARMEN log in ``--real`` (``slam.io.carmen``; 180 or 360 beams).

Each method runs at its defaults (``segmentation.get(name)``); a warm-up pass
compiles and caches, then ``--repeats`` timed passes over the whole data set;
scans/s = scans / median pass time. Numba and BLAS are limited to one thread
and the process is pinned to one CPU. Goals (reported, not enforced): RoR
combined >= 10,000 scans/s and >= 0.5x split_and_merge on ``office`` and
``figure1``; every method >= 1,000 scans/s.

The caption records the 1-minute load average before and after the run and
the number of CPUs: on a shared, loaded machine absolute scans/s drop (the
ratios, measured in the same run, move less); ``--note`` adds free text.

Usage: ``python scripts/bench_segmentation.py [--out table.md] [--repeats 7] [--note TEXT]``.
"""

from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

import segmentation as sg  # noqa: E402
from simulation.scanline import figure1, random_room  # noqa: E402
from slam.io.carmen import read_carmen_scans  # noqa: E402

REFERENCE = "split_and_merge"
GOAL_ALL = 1_000.0
GOAL_ROR = 10_000.0
GOAL_ROR_RATIO = 0.5
DEFAULT_REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def office_scans(n: int) -> list[sg.Scanline]:
    """``n`` 1081-beam synthetic office scanlines: figure-1 draws and random rooms."""
    out = []
    for k in range(n):
        s = figure1(seed=k) if k % 2 == 0 else random_room(k)
        out.append(sg.Scanline.from_ranges(s.ranges, s.angles, s.times, range_min=s.range_min, range_max=s.range_max))
    return out


def figure1_scans(n: int) -> list[sg.Scanline]:
    """``n`` 1081-beam figure-1 scanlines (3 mm noise, seeds 0 .. n-1)."""
    out = []
    for k in range(n):
        s = figure1(seed=k)
        out.append(sg.Scanline.from_ranges(s.ranges, s.angles, s.times, range_min=s.range_min, range_max=s.range_max))
    return out


def real_scans(folder: Path, max_scans: int) -> dict[str, list[sg.Scanline]]:
    """Up to ``max_scans`` scanlines of every ``*.log`` / ``*.log.gz`` CARMEN log in ``folder``."""
    sets = {}
    for path in sorted(folder.glob("*.log*")):
        scans = []
        for line in read_carmen_scans(path):
            if line.n_valid >= 20:
                scans.append(line)
            if len(scans) >= max_scans:
                break
        name = path.name.removesuffix(".gz").removesuffix(".log")
        sets[name] = scans
    return sets


def time_method(method: str, scans: list[sg.Scanline], repeats: int) -> float:
    """Scans per second: median over ``repeats`` timed passes, after one warm-up pass."""
    seg = sg.get(method)
    for line in scans:
        seg.segment(line)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for line in scans:
            seg.segment(line)
        times.append(time.perf_counter() - t0)
    return len(scans) / float(np.median(times))


def _load_average() -> float:
    """The 1-minute load average (NaN where the OS does not report it)."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return float("nan")


def markdown(results: dict[str, dict[str, float]], sets: dict[str, list[sg.Scanline]]) -> str:
    names = list(sets)
    beams = {k: int(np.median([s.n_beams for s in v])) for k, v in sets.items()}
    head = "| method | " + " | ".join(f"{k} ({len(sets[k])} x {beams[k]} beams) scans/s | ratio" for k in names) + " | goals |"
    sep = "|---|" + "---:|---:|" * len(names) + "---|"
    lines = [head, sep]
    for m, row in results.items():
        cells = []
        for k in names:
            ref = results.get(REFERENCE, {}).get(k, float("nan"))
            cells.append(f"{row[k]:,.0f} | {row[k] / ref:.2f}x")
        notes = []
        if min(row.values()) < GOAL_ALL:
            notes.append(f"below {GOAL_ALL:,.0f}/s")
        if m == "ror":
            synthetic = [k for k in ("office", "figure1") if k in row]
            ok = all(row[k] >= GOAL_ROR and row[k] / results.get(REFERENCE, {}).get(k, float("nan")) >= GOAL_ROR_RATIO
                     for k in synthetic)
            notes.append("RoR goal met" if ok else f"RoR goal missed (>= {GOAL_ROR:,.0f}/s and >= {GOAL_ROR_RATIO}x)")
        lines.append(f"| {m} | " + " | ".join(cells) + f" | {'; '.join(notes) or 'ok'} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, help="also write the markdown table here")
    ap.add_argument("--repeats", type=int, default=7, help="timed passes per method and data set")
    ap.add_argument("--office", type=int, default=200, help="synthetic 1081-beam scanlines")
    ap.add_argument("--real", type=Path, default=DEFAULT_REAL, help="folder of CARMEN logs")
    ap.add_argument("--max-real", type=int, default=400, help="scanlines per real log")
    ap.add_argument("--methods", nargs="*", help="subset of segmenters (default: all registered)")
    ap.add_argument("--note", default="", help="free text appended to the table caption")
    args = ap.parse_args(argv)
    if args.repeats < 1 or args.office < 1 or args.max_real < 1:
        print("error: --repeats, --office and --max-real must be >= 1", file=sys.stderr)
        return 2
    methods = args.methods or sg.available()
    unknown = sorted(set(methods) - set(sg.available()))
    if unknown:
        print(f"error: unknown segmenters {', '.join(unknown)}; available: {', '.join(sg.available())}",
              file=sys.stderr)
        return 2
    if REFERENCE in sg.available() and REFERENCE not in methods:
        methods = [*methods, REFERENCE]
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

    sets: dict[str, list[sg.Scanline]] = {"office": office_scans(args.office), "figure1": figure1_scans(args.office)}
    if args.real.is_dir():
        sets.update(real_scans(args.real, args.max_real))
    else:
        print(f"warning: no real data folder {args.real}; synthetic only", file=sys.stderr)

    load_before = _load_average()
    results: dict[str, dict[str, float]] = {m: {} for m in methods}
    with tqdm(total=len(methods) * len(sets), desc="bench", unit="set") as bar:
        for m in methods:
            for k, scans in sets.items():
                results[m][k] = time_method(m, scans, args.repeats)
                bar.update()

    table = markdown(results, sets)
    load = f"{load_before:.1f} before, {_load_average():.1f} after the run" if np.isfinite(load_before) else "unknown"
    header = (f"Segmentation speed, one core ({platform.processor() or platform.machine()}, "
              f"numba threads 1), defaults, median of {args.repeats} passes; ratio to {REFERENCE}. "
              f"Machine: {os.cpu_count()} CPUs, 1-minute load average {load}."
              + (f" {args.note}" if args.note else "") + "\n\n")
    print("\n" + header + table)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=args.out.parent, prefix=f".{args.out.name}.")
        with os.fdopen(fd, "w") as f:
            f.write(header + table + "\n")
        os.replace(tmp, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
