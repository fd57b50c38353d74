"""Accuracy of several rigs on the same world and walk (issue 22): the three-scanner ITC backpack
beside Cartographer's two-scanner backpack (MultiEchoLaserScan, IMU), each simulated with an IMU
on the same walk and seed, run without a rig file (the rig comes from the recording's transforms)
and evaluated against the ground truth.

Usage:
    .venv/bin/python scripts/compare_rigs.py [--world demo] [--duration 60] [--seed 1] [--out out/rigs]
        [--rigs itc_backpack,cartographer_backpack_2d] [--markdown FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import backpack_slam as bs
from common.rig import resolve_rig
from slam.evaluate import Stats


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--world", default="demo")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--rigs", default="itc_backpack,cartographer_backpack_2d")
    ap.add_argument("--out", type=Path, default=Path("out/rigs"))
    ap.add_argument("--markdown", type=Path, default=None)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = ["| rig | scanners | ATE start-aligned | ATE SE(3) | cloud-to-mesh median / p95 | plane angle median | "
            "x real time | verdict |", "|---|---|---|---|---|---|---|---|"]
    for rig in args.rigs.split(","):
        print(f"{rig}: simulating and running ...", file=sys.stderr, flush=True)
        sim = bs.simulate(args.world, rig, duration=args.duration, seed=args.seed, out=args.out / f"{rig}.bag", imu=True)
        t0 = time.perf_counter()
        res = bs.run(sim.bag, out=args.out / f"{rig}_slam")
        wall = time.perf_counter() - t0
        ev = bs.evaluate(res.run_dir, sim.gt)
        ate = ev.trajectory.ate
        cloud = Stats.of(ev.cloud.distances) if ev.cloud is not None else None
        cells = f"{1000 * cloud.median:.1f} / {1000 * cloud.p95:.1f} mm" if cloud else "-"
        planes = f"{ev.planes.angle.median:.3f} deg" if ev.planes is not None else "-"
        rows.append(f"| {rig} | {len(resolve_rig(rig).scanners)} | {1000 * ate['start_aligned'].rmse:.1f} mm | {1000 * ate['se3_aligned'].rmse:.1f} mm | {cells} | "
                    f"{planes} | {args.duration / wall:.2f}x | {res.health.verdict} |")
    text = "\n".join(rows) + "\n"
    print(text)
    if args.markdown is not None:
        from common.atomic import write_text

        write_text(args.markdown, f"# Rigs on the {args.world} walk ({args.duration:g} s, seed {args.seed}, IMU)\n\n{text}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
