"""``backpack-slam calibrate BAG --rig initial.yaml --out calibrated.yaml``: estimate the tilted
scanners' extrinsics (and time offsets) from a recording; write the calibrated rig and a report."""

from __future__ import annotations

import argparse
import math
import warnings
from pathlib import Path
from typing import Any

from backpack_slam.commands import input_file, output_path

DESCRIPTION = """Run SLAM on BAG with the initial rig, then refine the non-reference scanners'
T_body_scanner (and with --time-offsets their clock offsets) in one factor graph with poses and
planes; repeat with the updated rig until the extrinsics settle. Writes OUT (a rig YAML with the
estimates and their 6x6 covariances) and, with --report, a folder with residuals before/after,
per-scanner plots and report.md. Warns, naming scanner and parameter, when the recording does not
constrain a parameter."""


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = sub.add_parser("calibrate", help="calibrate the scanners' extrinsics from a recording",
                                                description=DESCRIPTION)
    p.add_argument("bag", help="ROS1 .bag file or ROS2 bag folder with the rig's LaserScan topics")
    p.add_argument("--rig", required=True, type=input_file, help="initial rig: name (configs/rig/NAME.yaml) or YAML path")
    p.add_argument("--out", required=True, type=output_path, help="calibrated rig YAML to write")
    p.add_argument("--config", default=None, type=input_file, help="SLAM config YAML (default: built-in defaults)")
    p.add_argument("--time-offsets", action="store_true", help="also estimate a clock offset per scanner")
    p.add_argument("--report", type=Path, default=None, metavar="DIR", help="write the report folder DIR")
    p.add_argument("--rounds", type=int, default=3, help="maximum SLAM + batch rounds (default 3)")
    p.add_argument("--sigma-rot", type=float, default=5.0, metavar="DEG", help="prior sigma of the rotations (deg)")
    p.add_argument("--sigma-trans", type=float, default=0.10, metavar="M", help="prior sigma of the translations (m)")
    p.add_argument("--coarse", nargs=2, type=float, default=None, metavar=("DEG", "MM"),
                   help="the initial rig may be off by up to DEG degrees and MM millimetres: start with "
                        "association gates that wide and tighten them round by round (coarse to fine)")
    p.add_argument("--coarse-seconds", type=float, default=None, metavar="S",
                   help="with --coarse: run the coarse rounds on the first S seconds of the recording only "
                        "(faster; the last round always uses all of it)")
    p.add_argument("--quiet", action="store_true", help="no progress messages")
    return p


def run(args: argparse.Namespace) -> int:
    from calibration.calibrate import CalibrationOptions, calibrate_bag
    from calibration.estimator import EstimatorConfig
    from calibration.observability import UnobservableWarning
    from calibration.report import write_report
    from common.rig import resolve_rig, write_rig
    from slam.config import load_slam_config

    rig = resolve_rig(args.rig)
    cfg = load_slam_config(args.config)
    if args.rounds < 1:
        raise ValueError(f"--rounds {args.rounds}: must be >= 1")
    if not all(math.isfinite(x) and x > 0 for x in (args.sigma_rot, args.sigma_trans)):
        raise ValueError("--sigma-rot/--sigma-trans: must be finite and > 0")
    if not args.out.parent.is_dir():
        raise ValueError(f"--out {args.out}: the folder {args.out.parent} does not exist")
    est = EstimatorConfig(sigma_rot=math.radians(args.sigma_rot), sigma_trans=args.sigma_trans,
                          time_offsets=args.time_offsets)
    coarse = None
    if args.coarse is not None:
        if not all(math.isfinite(x) and x >= 0 for x in args.coarse):
            raise ValueError(f"--coarse {args.coarse[0]:g} {args.coarse[1]:g}: must be finite and >= 0")
        coarse = (math.radians(args.coarse[0]), args.coarse[1] / 1000.0)
    if args.coarse_seconds is not None and not (math.isfinite(args.coarse_seconds) and args.coarse_seconds > 0):
        raise ValueError(f"--coarse-seconds {args.coarse_seconds:g}: must be > 0")
    say = None if args.quiet else print
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnobservableWarning)  # printed below, once
        try:
            cal = calibrate_bag(args.bag, rig, cfg, CalibrationOptions(
                estimator=est, max_rounds=args.rounds, initial_uncertainty=coarse,
                coarse_duration=args.coarse_seconds), say)
        except ValueError as e:  # the estimator's own errors (a singular graph) name no recording
            if str(Path(args.bag)) in str(e):
                raise
            raise ValueError(f"calibration from {args.bag} with rig {args.rig}: {e}") from None
    write_rig(args.out, cal.rig, header=f"calibrated by backpack-slam calibrate from {args.bag}\n"
                                         f"initial rig: {args.rig}")
    for w in cal.warnings:
        print(f"warning: {w}")
    for s in cal.batch.scanners:
        if s.reference:
            continue
        p = next(q for q in cal.sigmas if q.scanner == s.name)
        deg = ", ".join(f"{math.degrees(v):.4f}" for v in p.sigmas[:3])
        mm = ", ".join(f"{v * 1e3:.3f}" for v in p.sigmas[3:])
        print(f"{s.name}: sigma rpy ({deg}) deg, xyz ({mm}) mm")
    print(f"wrote {args.out}" + ("" if cal.converged else f" (not converged after {len(cal.rounds)} rounds)"))
    if args.report is not None:
        write_report(cal, args.report)
        print(f"report: {args.report}/report.md")
    return 0
