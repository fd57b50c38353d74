"""``backpack-slam run BAG [--rig RIG] --out DIR``: SLAM on a bag, the run folder out.

Exit codes: 0 the run's estimate passed its own health checks (``summary.json`` ``health``); 3
the run finished but its estimate cannot be trusted (outputs written, marked ``failed``, one
line per problem printed); 2 bad input, a rig that does not match the recording, or a rig that
leaves a degree of freedom to an IMU the recording lacks (nothing written)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from backpack_slam.commands import input_file, output_path
from common.rig import resolve_rig
from slam.config import load_slam_config, with_segmenter
from slam.health import EXIT_FAILED
from slam.survey import export_cloud, survey_format

PROG = "backpack-slam"


def parse_params(items: list[str]) -> dict[str, Any]:
    """``key=value`` strings -> dict (values are coerced by the segmenter)."""
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--param {item!r}: expected key=value")
        k, v = item.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser("run", help="run SLAM on a bag and write trajectory, planes, cloud, map")
    p.add_argument("bag", help="ROS1 .bag file or ROS2 bag folder with the rig's LaserScan topics")
    p.add_argument("--rig", default=None, type=input_file,
                   help="rig name (configs/rig/NAME.yaml) or YAML path (default: built from the bag's /tf_static or --urdf)")
    p.add_argument("--urdf", default=None, type=input_file, help="URDF with the rig's extrinsics (without --rig: the rig is built from it)")
    p.add_argument("--config", default=None, type=input_file, help="SLAM config YAML (default: built-in defaults, see configs/slam/default.yaml)")
    p.add_argument("--segmenter", default=None, help="segmenter name (overrides the config)")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="segmenter parameter (repeatable)")
    p.add_argument("--voxel", type=float, default=None, help="thin cloud.ply to one point per voxel of this size (m)")
    p.add_argument("--out", required=True, type=output_path, help="output folder")
    p.add_argument("--cloud-format", default=None, metavar="FMT",
                   help="also write the cloud as FMT for survey tools: laz, las, e57 or pcd (OUT/cloud.FMT)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def run(args: argparse.Namespace) -> int:
    from slam.run import run_slam

    rig = resolve_rig(args.rig) if args.rig is not None else None
    fmt = survey_format(args.cloud_format) if args.cloud_format is not None else None
    cfg = with_segmenter(load_slam_config(args.config), args.segmenter, parse_params(args.param))
    if args.voxel is not None and not (math.isfinite(args.voxel) and args.voxel > 0):
        raise ValueError(f"--voxel {args.voxel}: must be finite and > 0")
    if fmt is not None and not cfg.output.cloud:
        raise ValueError(f"--cloud-format {args.cloud_format}: the configuration turns the cloud off (output.cloud: false)")
    summary = run_slam(args.bag, rig, cfg, args.out, progress=not args.quiet, voxel=args.voxel, urdf=args.urdf,
                       report=lambda line: print(f"note: {line}", file=sys.stderr))
    c = summary["counts"]
    t = summary["timings"]
    print(
        f"{c['knots']} knots, {c['planes']} planes ({c['planes_merged']} merged), "
        f"{c['segments_associated']}/{c['segments']} segments associated, "
        f"{t['wall']:.1f} s ({summary['realtime_factor']:.2f}x real time)"
    )
    names = ("trajectory.tum", "trajectory_online.tum", "planes.json", "segments.npz", "cloud.ply", "map.rrd",
             "summary.json")
    print(f"outputs: {args.out}/ ({', '.join(n for n in names if (Path(args.out) / n).exists())})")
    if fmt is not None:
        out = Path(args.out)
        n = export_cloud(out / "cloud.ply", out / f"cloud.{fmt}", fmt, out / "trajectory.tum")
        print(f"cloud for survey tools: {n} points -> {out / f'cloud.{fmt}'}")
    health = summary["health"]
    for p in sorted(health["problems"], key=lambda p: p["severity"] != "failure"):
        print(f"{PROG}: {p['severity']}: {p['message']}", file=sys.stderr)
    if health["verdict"] == "failed":
        print(f"{PROG}: the run's estimate cannot be trusted (verdict: failed; outputs marked so in summary.json)",
              file=sys.stderr)
        return EXIT_FAILED
    print(f"health: {health['verdict']}")
    return 0
