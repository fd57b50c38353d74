"""``backpack-slam report DIR``: markdown and plots from a sweep's results."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

DESCRIPTION = """Write DIR/report.md and PNG plots from DIR/results.parquet: drift (ATE, RPE per
100 m) and map error (cloud-to-mesh, plane angles) per segmenter and parameter with 95 %
confidence intervals over seeds, the segmenters' scores against the per-beam ground truth,
time per segmenter, and the failed cells."""


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser("report", help="report of a sweep (markdown + PNG)", description=DESCRIPTION)
    p.add_argument("dir", type=Path, metavar="DIR", help="sweep folder holding results.parquet")
    return p


def run(args: argparse.Namespace) -> int:
    from backpack_slam.sweep.report import write_report

    if not args.dir.is_dir():
        raise ValueError(f"{args.dir}: no such sweep folder")
    path = write_report(args.dir)
    print(f"wrote {path} and its plots")
    return 0
