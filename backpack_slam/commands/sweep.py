"""``backpack-slam sweep CONFIG --out DIR``: the segmentation-vs-drift grid, resumable."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

DESCRIPTION = """Run every cell of an experiment (configs/experiments/*.yaml): segmenter
variants x worlds x noise levels x calibration errors x seeds. Each cell simulates its walk
(cached in DIR/cache/, one bag per world, noise and seed), runs SLAM with the cell's segmenter
on the rig perturbed by the calibration error, evaluates against the ground truth and scores
the segmenter on a sample of the scans. Rows go to DIR/results.parquet as cells finish; a
rerun skips finished cells; a failed cell is recorded with its error. Then: backpack-slam report DIR."""


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser("sweep", help="run a segmentation-vs-drift experiment grid", description=DESCRIPTION)
    p.add_argument("config", type=Path, metavar="CONFIG", help="experiment YAML (configs/experiments/*.yaml)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="sweep folder (results, cache, per-cell outputs)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=None, metavar="N", help="local worker processes (default 1; 0 = in this process)")
    where.add_argument("--dask", default=None, metavar="tcp://HOST:8786", help="run the cells on this Dask scheduler (workers need DIR shared)")
    p.add_argument("--retry-failed", action="store_true", help="run failed cells again")
    p.add_argument("--dry-run", action="store_true", help="print the grid's size and exit")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def run(args: argparse.Namespace) -> int:
    from backpack_slam.sweep.config import load_experiment
    from backpack_slam.sweep.engine import run_sweep
    from backpack_slam.sweep.plan import plan_cells

    cfg = load_experiment(args.config)
    try:
        cells = plan_cells(cfg)
    except ValueError as e:
        raise ValueError(f"{args.config}: {e}") from None
    n_sims = len({c.sim_key for c in cells})
    print(f"{cfg.name}: {len(cells)} cells, {n_sims} simulated walks of {cfg.duration:g} s")
    if args.dry_run:
        return 0
    if args.workers is not None and args.workers < 0:
        raise ValueError(f"--workers {args.workers}: must be >= 0")
    s = run_sweep(cells, args.out, workers=1 if args.workers is None else args.workers, dask=args.dask,
                  retry_failed=args.retry_failed, progress=not args.quiet)
    print(f"{s.n_ok} ok, {s.n_failed} failed, {s.n_skipped} already done; {s.wall_time:.1f} s")
    for variant, err in s.failed[:10]:
        print(f"  failed: {variant}: {err}")
    print(f"results: {args.out}/results.parquet; report: backpack-slam report {args.out}")
    return 0
