"""``backpack-slam demo``: the main job on the built-in default.

1. Simulates a walk through the small ``demo`` world (two rooms and a corridor, doors set
   into the walls and boards proud of them) with the ``itc_backpack`` rig: a ROS1 bag and
   its ground truth.
2. Runs SLAM on the bag with the RoR segmenter: trajectory, planes, point cloud, rerun map.
3. Evaluates the run against the ground truth (ATE, RPE, drift, plane and map errors).
4. Segments the synthetic figure-1 scanline (the seed paper's scene: a whiteboard 2 cm proud
   of its wall, a door 1.5 cm recessed, 3 mm range noise) and one scan of a real CARMEN log
   (the Intel lab) with RoR beside split_and_merge and line_tracking.

Everything goes into ``--out``; the last lines printed say where.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import IO, Any

METHODS = ("ror", "split_and_merge", "line_tracking")
REAL_LOG = "intel-corrected.log.gz"
REAL_SCAN = 300  # a corridor scan with several walls


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "demo", help="run the demo and write its plots", description=__doc__
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder for the plots and JSON")
    p.add_argument(
        "--log", type=Path, default=None, metavar="LOG",
        help=f"real CARMEN log to segment (default: {REAL_LOG} in $BACKPACK_SLAM_DATA or ../shared/data/real)",
    )
    p.add_argument("--scan", type=int, default=REAL_SCAN, help=f"scan of the real log (default: {REAL_SCAN})")
    p.add_argument("--seed", type=int, default=0, help="noise seed of the synthetic scanline (default: 0)")
    p.add_argument("--duration", type=float, default=60.0, help="seconds of walking to simulate (default: 60)")
    p.add_argument("--segmentation-only", action="store_true", help="only the segmentation figures (seconds)")
    return p


def default_log() -> Path | None:
    """The Intel lab log in $BACKPACK_SLAM_DATA, or in ../shared/data/real beside the repository."""
    candidates = []
    if os.environ.get("BACKPACK_SLAM_DATA"):
        candidates.append(Path(os.environ["BACKPACK_SLAM_DATA"]) / REAL_LOG)
    repo = Path(__file__).resolve().parents[2]
    candidates += [repo.parent / "shared" / "data" / "real" / REAL_LOG, Path.cwd().parent / "shared" / "data" / "real" / REAL_LOG]
    return next((c for c in candidates if c.is_file()), None)


def run(args: argparse.Namespace) -> int:
    if not args.duration > 0:
        raise ValueError(f"--duration {args.duration}: must be > 0")
    log = args.log if args.log is not None else default_log()
    written = run_demo(args.out, log, args.scan, args.seed, sys.stdout)
    if not args.segmentation_only:
        written += run_slam_demo(args.out, args.duration, sys.stdout)
    print(f"demo written to {args.out}/:")
    for p in written:
        print(f"  {p}")
    return 0


def run_slam_demo(out: Path, duration: float, stream: IO[str]) -> list[Path]:
    """Simulate the demo world, run SLAM with RoR and evaluate; return the paths written."""
    from common.rig import resolve_rig
    from simulation.run import simulate
    from slam.config import SlamConfig
    from slam.eval_plots import write_plots
    from slam.evaluate import Stats, evaluate, write_eval_json
    from slam.run import run_slam
    from slam.survey import export_cloud

    out.mkdir(parents=True, exist_ok=True)
    bag = out / "demo.bag"
    stream.write(f"simulating {duration:.0f} s of walking in the demo world ...\n")
    sim = simulate("demo", "itc_backpack", duration=duration, seed=1, out=bag, fmt="ros1", progress=True)
    stream.write(f"  {sim.n_rays / 1e6:.1f} M rays in {sim.wall_time:.1f} s -> {sim.bag}, ground truth {sim.gt}\n")
    stream.write("running SLAM (segmenter: ror) ...\n")
    run_dir = out / "slam"
    summary = run_slam(sim.bag, resolve_rig("itc_backpack"), SlamConfig(), run_dir, progress=True)
    c = summary["counts"]
    stream.write(
        f"  {c['knots']} poses, {c['planes']} planes, {c['segments_associated']}/{c['segments']} segments associated, "
        f"{summary['timings']['wall']:.1f} s ({summary['realtime_factor']:.2f}x real time)\n"
    )
    laz = run_dir / "cloud.laz"
    n_laz = export_cloud(run_dir / "cloud.ply", laz)
    stream.write(f"  cloud for survey tools: {n_laz} points -> {laz}\n")
    result = evaluate(run_dir, sim.gt)
    eval_json = write_eval_json(run_dir / "eval.json", result)
    plots = write_plots(result, run_dir)
    ate = result.trajectory.ate
    line = f"ATE RMSE {1000 * ate['start_aligned'].rmse:.1f} mm (start-aligned), {1000 * ate['se3_aligned'].rmse:.1f} mm (SE(3)-aligned)"
    if result.cloud is not None:
        d = Stats.of(result.cloud.distances)
        line += f"; map: cloud-to-mesh median {1000 * d.median:.1f} mm, p95 {1000 * d.p95:.1f} mm"
    if result.planes is not None:
        line += f"; plane angle error median {result.planes.angle.median:.3f} deg"
    stream.write(line + "\n")
    return [sim.bag, sim.gt, run_dir, laz, eval_json, *plots]


def run_demo(out: Path, log: Path | None, scan_index: int, seed: int, stream: IO[str]) -> list[Path]:
    """Segment figure 1 and a real scan with every method of ``METHODS``; return the files written."""
    from matplotlib.figure import Figure

    import segmentation
    from backpack_slam.commands._segplot import (
        draw_labels,
        draw_segmentation,
        new_figure,
        save_figure,
    )
    from backpack_slam.commands.segment import json_safe, scan_info, select_scans
    from common.atomic import write_json
    from segmentation import Scanline, metrics
    from simulation.scanline import figure1
    from slam.io.carmen import read_carmen_scans

    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    record: dict[str, Any] = {"methods": {m: segmentation.segmenter_class(m).defaults() for m in METHODS}}

    syn = figure1(noise_sigma=0.003, seed=seed)
    line = Scanline.from_ranges(syn.ranges, syn.angles, syn.times, range_min=syn.range_min, range_max=syn.range_max, scanner_id="figure1")
    names = list(syn.gt_names)
    fig = Figure(figsize=(4.5 * (1 + len(METHODS)), 11.0), layout="constrained")
    grid = fig.subplots(3, 1 + len(METHODS), height_ratios=[2.0, 1.0, 1.0])
    draw_labels(grid[0, 0], line, syn.gt_labels, "figure 1: ground truth (sigma 3 mm)")
    panels: list[tuple[Any, Any, Any, Any, Any]] = [(grid[0, 0], grid[1, 0], grid[2, 0], syn.gt_labels, None)]
    record["figure1"] = {"noise_sigma": 0.003, "seed": seed, "gt_names": names, "results": {}}
    for col, m in enumerate(METHODS, start=1):
        seg = segmentation.segment(line, method=m)
        score = metrics.compare(seg, syn.gt_labels, line, gt_normals=syn.gt_normals)
        sep = {obj: metrics.separates(seg, syn.gt_labels, names.index(obj)) for obj in ("whiteboard", "door")}
        draw_segmentation(grid[0, col], line, seg, "figure 1")
        panels.append((grid[0, col], grid[1, col], grid[2, col], seg.labels, seg))
        record["figure1"]["results"][m] = {"score": score.summary(), "separates": sep, "segmentation": seg.to_dict()}
        stream.write(
            f"figure 1, {m:16s}: {seg.n_segments:2d} segments, overlap1 {score.mean_overlap1:.3f}, median angle "
            f"{score.median_angle_deg:.2f} deg, board {'separated' if sep['whiteboard'] else 'NOT separated'}, "
            f"door {'separated' if sep['door'] else 'NOT separated'}\n"
        )
    # the 1.5-2 cm steps are invisible at full scale: zoom on the board and the door, stretched across the wall
    for _, ax_board, ax_door, labels, seg in panels:
        for ax, obj in ((ax_board, "whiteboard"), (ax_door, "door")):
            if seg is None:
                draw_labels(ax, line, labels, f"{obj} (zoom, stretched)")
            else:
                draw_segmentation(ax, line, seg, f"{obj} (zoom, stretched)")
            _zoom(ax, line.points_xy[syn.gt_labels[line.valid_index] == names.index(obj)])
    written.append(save_figure(fig, out / "figure1_segmentation.png"))

    if log is None:
        stream.write(f"real log {REAL_LOG} not found: set BACKPACK_SLAM_DATA or pass --log; skipping the real scan\n")
    else:
        ((idx, real),) = list(select_scans(read_carmen_scans(log), scan_index, str(log)))
        fig, axes = new_figure(len(METHODS), size=5.0)
        record["real"] = {"log": str(log), **scan_info(idx, real), "results": {}}
        for ax, m in zip(axes, METHODS, strict=True):
            seg = segmentation.segment(real, method=m)
            draw_segmentation(ax, real, seg, f"{log.name} scan {idx}")
            record["real"]["results"][m] = {"segmentation": seg.to_dict()}
            n_in = int((seg.labels[real.valid_index] >= 0).sum())
            stream.write(f"{log.name} scan {idx}, {m:16s}: {seg.n_segments:2d} segments, {n_in}/{real.n_valid} points in segments\n")
        written.append(save_figure(fig, out / "real_scan_segmentation.png"))
    written.append(write_json(out / "segmentation_demo.json", json_safe(record)))
    return written


def _zoom(ax: Any, pts: Any, margin: float = 0.3, across: float = 0.06) -> None:
    """Limit ``ax`` to the box around ``pts`` grown by ``margin`` m along and ``across`` m across
    the points' long axis, with free aspect so that centimetre steps show."""
    import numpy as np

    lo, hi = pts.min(axis=0), pts.max(axis=0)
    along = int(np.argmax(hi - lo))
    grow = np.where(np.arange(2) == along, margin, across)
    ax.set_aspect("auto")
    ax.set_xlim(lo[0] - grow[0], hi[0] + grow[0])
    ax.set_ylim(lo[1] - grow[1], hi[1] + grow[1])
