"""``backpack-slam rig``: a rig from a recording (its scan topics and transforms, or a URDF), or
the check of a rig: which degrees of freedom its scanners constrain and which only an IMU holds."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from backpack_slam.commands import output_path

DESCRIPTION = """With BAG: build the rig from the recording itself (scanners from its LaserScan /
MultiEchoLaserScan topics and their messages' geometry, range noise measured from the first scans,
extrinsics from /tf_static and the static part of /tf, or from --urdf), print it and write it to
--out. With --check RIG: print which of the six degrees of freedom the rig's scanners constrain in
a typical room and which are left to an IMU."""


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "rig", help="build a rig from a bag (tf or URDF), or check a rig's observability", description=DESCRIPTION
    )
    p.add_argument("bag", nargs="?", default=None, help="ROS1 .bag or ROS2 bag folder")
    p.add_argument("--out", type=output_path, default=None, help="write the rig YAML here")
    p.add_argument("--urdf", type=Path, default=None, help="take the extrinsics from this URDF instead of the bag's tf")
    p.add_argument("--base", default=None, help="body frame (default: the IMU's frame, else the tf tree's root)")
    p.add_argument("--name", default=None, help="rig name (default: from the bag's name)")
    p.add_argument("--check", metavar="RIG", default=None, help="check a rig (name or YAML) instead")
    p.add_argument("--echo", choices=("first", "last", "strongest"), default=None,
                   help="MultiEchoLaserScan: the echo of each beam the range noise is measured on (default: the "
                   "SLAM config's input.echo default); a run reads the echo its config's input.echo names")
    return p


def describe(rig: Any) -> list[str]:
    """One line per scanner: name, topic, model, mounting."""
    lines = [f"rig '{rig.name}': body frame '{rig.body_frame}', reference scanner '{rig.reference}', "
             f"IMU topic '{rig.imu.topic}' ({rig.imu.frame_id})"]
    for s in rig.scanners:
        m = s.scanner_model
        ext = s.T_body_scanner
        lines.append(
            f"  {s.name}: {s.topic} ({s.message}, frame {s.frame}), {m.n_beams} beams from "
            f"{math.degrees(m.angle_min):.2f} deg at {math.degrees(m.angle_increment):.4f} deg, {1 / m.scan_period:.1f} Hz, "
            f"{m.range_min:g}-{m.range_max:g} m, noise {1000 * m.range_sigma:.1f} mm; at "
            f"[{', '.join(f'{x:.4f}' for x in ext.translation)}] m, rpy [{', '.join(f'{math.degrees(x):.2f}' for x in ext.rpy)}] deg")
    return lines


def run(args: argparse.Namespace) -> int:
    from common.rig import resolve_rig, write_rig
    from slam.rig_check import rig_observability

    if args.check is not None:
        if args.bag is not None:
            raise ValueError("give either BAG or --check RIG, not both")
        rig = resolve_rig(args.check)
    else:
        if args.bag is None:
            raise ValueError("give a BAG to build the rig from, or --check RIG")
        from slam.config import SlamConfig
        from slam.io.source import BagSource
        from slam.rig_builder import rig_from_source

        echo = args.echo or SlamConfig().input.echo
        with BagSource(args.bag) as src:
            rig = rig_from_source(src, urdf=args.urdf, base=args.base, name=args.name, echo=echo)
    print("\n".join(describe(rig)))
    print(rig_observability(rig).summary())
    if args.out is not None:
        source = f"the URDF {args.urdf}" if args.urdf else "its transforms"
        write_rig(args.out, rig, header=f"built by backpack-slam rig from {args.bag} and {source}"
                  if args.bag else f"checked rig {args.check}")
        print(f"rig -> {args.out}")
    return 0
