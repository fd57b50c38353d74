"""Benchmark: simulate and write a walk (default 10 minutes: 3 x 40 Hz x 600 s = 72,000 scans,
78 million rays) and print the time per stage, the ratio to real time and the peak RSS.

Goal: < 120 s for 600 s on the 2-core machine, memory bounded (streamed chunks).

    .venv/bin/python scripts/bench_simulation.py [--duration 600] [--world office] [--format ros1]
"""

from __future__ import annotations

import argparse
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

from simulation.run import STAGES, simulate

GOAL_S_PER_600 = 120.0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=600.0, help="simulated seconds (default 600)")
    ap.add_argument("--world", default="office")
    ap.add_argument("--rig", default="itc_backpack")
    ap.add_argument("--format", choices=("ros1", "ros2"), default="ros1")
    ap.add_argument("--imu", action="store_true")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--keep", type=Path, default=None, help="write here instead of a temporary folder")
    args = ap.parse_args(argv)

    tmp = Path(tempfile.mkdtemp(prefix="bench_sim_")) if args.keep is None else args.keep
    tmp.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        from simulation.world import load_world

        world = load_world(args.world)
        t_world = time.perf_counter() - t0
        res = simulate(world, args.rig, duration=args.duration, seed=args.seed, out=tmp / "bench.bag", fmt=args.format, imu=args.imu)
        wall = res.wall_time
        size = sum(f.stat().st_size for f in ([res.bag] if res.bag.is_file() else res.bag.rglob("*")) if f.is_file())
        gt_size = sum(f.stat().st_size for f in res.gt.rglob("*") if f.is_file())
    finally:
        if args.keep is None:
            shutil.rmtree(tmp, ignore_errors=True)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    scans = sum(res.meta["counts"]["scans"].values())
    print(f"\nsimulation benchmark: world {args.world}, rig {args.rig}, {args.format}, {args.duration:g} s walk")
    print(f"  {scans} scans, {res.n_rays / 1e6:.1f} M rays; bag {size / 1e6:.0f} MB, ground truth {gt_size / 1e6:.0f} MB")
    print(f"  {'stage':<16}{'seconds':>10}{'share':>9}{'x real time':>14}")
    other = wall - sum(res.seconds.values())
    for name in (*STAGES, "other"):
        s = res.seconds.get(name, other)
        print(f"  {name:<16}{s:>10.2f}{100 * s / wall:>8.1f}%{args.duration / max(s, 1e-9):>14.1f}")
    print(f"  {'total':<16}{wall:>10.2f}{100.0:>8.1f}%{args.duration / wall:>14.1f}")
    print(f"  world compile (not in total): {t_world:.2f} s; rays/s overall: {res.n_rays / wall / 1e6:.2f} M")
    print(f"  peak RSS: {peak_mb:.0f} MB")
    goal = GOAL_S_PER_600 * args.duration / 600.0
    ok = wall < goal
    print(f"  goal: < {goal:.0f} s for {args.duration:g} s ({'met' if ok else 'NOT met'}; ratio to goal {wall / goal:.2f})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
