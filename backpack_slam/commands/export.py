"""``backpack-slam export``: a run's cloud in a format survey tools open (LAS, LAZ, E57, PCD)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from tqdm import tqdm

from backpack_slam.commands import output_path

DESCRIPTION = """Stream DIR/cloud.ply (world frame) into LAS/LAZ 1.4 (time, scanner as point source
id, plane id as an extra dimension), E57 (scan poses from the trajectory) or PCD. The frame is the
SLAM world frame (metres, z up, origin at the first pose): a local frame without a CRS."""


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "export", help="write a run's cloud as LAS, LAZ, E57 or PCD", description=DESCRIPTION
    )
    p.add_argument("dir", type=Path, metavar="RUN_DIR", help="SLAM output folder (holding cloud.ply)")
    p.add_argument("--format", dest="fmt", default=None, help="las, laz, e57 or pcd (default: from --out, else laz)")
    p.add_argument("--out", type=output_path, default=None, help="output file (default: RUN_DIR/cloud.<format>)")
    return p


def run(args: argparse.Namespace) -> int:
    from slam.export import cloud_ply_layout
    from slam.survey import export_cloud, survey_format

    run_dir: Path = args.dir
    if not run_dir.is_dir():
        raise ValueError(f"{run_dir}: no such run folder")
    fmt = survey_format(args.fmt or (args.out.suffix if args.out is not None and args.out.suffix else "laz"))
    out = args.out if args.out is not None else run_dir / f"cloud.{fmt}"
    n, _ = cloud_ply_layout(run_dir / "cloud.ply")
    traj = run_dir / "trajectory.tum"
    with tqdm(total=n, unit="pt", unit_scale=True, desc=f"export {fmt}", leave=False, disable=None) as bar:
        written = export_cloud(run_dir / "cloud.ply", out, fmt, traj if traj.is_file() else None, bar.update)
    print(f"{written} points -> {out}")
    return 0
