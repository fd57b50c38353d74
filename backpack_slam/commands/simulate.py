"""``backpack-slam simulate``: walk a simulated building with the backpack rig and write a ROS bag
(ROS1 or ROS2) plus its ground-truth folder ``<out>.gt/``."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from backpack_slam.commands import output_path

DESCRIPTION = """Simulate an operator walking WORLD with the rig's 2D scanners (per-beam timing,
range noise, dropouts, mixed pixels) and write a real ROS bag (LaserScan per scanner, /tf_static,
/ground_truth, optional /imu) and beside it OUT.gt/ (trajectory.tum, mesh.ply, planes.json,
beams.npz, rig.yaml, meta.json). Command-line values override those of --config. A ROS2 bag is
a directory; OUT=run.bag then writes the directory run/ (rosbags reads *.bag as ROS1)."""


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser("simulate", help="simulate a backpack recording as a ROS bag", description=DESCRIPTION)
    p.add_argument("--world", default=None, help="world name (configs/worlds/<name>.yaml) or YAML path (default: demo)")
    p.add_argument("--rig", default=None, help="rig name (configs/rig/<name>.yaml) or YAML path (default: itc_backpack)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="seconds to simulate (default: 60)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: 0)")
    p.add_argument("--out", type=output_path, required=True, metavar="OUT", help="the bag to write, e.g. run.bag")
    p.add_argument("--format", choices=("ros1", "ros2"), default=None, help="bag format (default: ros1)")
    p.add_argument("--imu", action="store_true", default=None, help="also write /imu (200 Hz)")
    p.add_argument("--noise", type=float, default=None, metavar="SIGMA", help="range noise std in m (default: the scanner's, 0.003)")
    p.add_argument("--config", type=Path, default=None, metavar="YAML", help="a SimulationConfig (configs/simulation/*.yaml)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def run(args: argparse.Namespace) -> int:
    from simulation.run import SimulationConfig, load_simulation_config, simulate

    cfg = load_simulation_config(args.config) if args.config is not None else SimulationConfig()
    upd: dict[str, Any] = {}
    if args.world is not None:
        upd["world"] = args.world
    if args.rig is not None:
        upd["rig"] = args.rig
    if args.noise is not None:
        if args.noise < 0:
            raise ValueError(f"--noise must be >= 0 m, got {args.noise}")
        upd["noise"] = cfg.noise.model_copy(update={"range_sigma": args.noise})
    if args.duration is not None and not args.duration > 0:
        raise ValueError(f"--duration must be > 0 s, got {args.duration}")
    cfg = cfg.model_copy(update=upd)
    res = simulate(
        cfg.world,
        cfg.rig,
        duration=args.duration,
        seed=args.seed,
        out=args.out,
        fmt=args.format,
        imu=args.imu,
        config=cfg,
        progress=not args.quiet,
    )
    dur = res.meta["duration"]
    scans = sum(res.meta["counts"]["scans"].values())
    print(f"wrote {res.bag} ({res.meta['format']}) and {res.gt}/")
    print(f"  {dur:g} s walked in {res.meta['world']}: {scans} scans, {res.n_rays} rays, seed {res.meta['seed']}")
    print(f"  {res.wall_time:.1f} s wall time ({dur / max(res.wall_time, 1e-9):.1f}x real time)")
    return 0
