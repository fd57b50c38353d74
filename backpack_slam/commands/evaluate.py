"""``backpack-slam evaluate``: compare a SLAM output folder with the simulator's ground truth."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

DESCRIPTION = """Evaluate the SLAM outputs in DIR (trajectory.tum, planes.json, cloud.ply,
segments.npz) against a ground-truth folder BAG.gt written by the simulator: ATE (unaligned,
start-aligned, SE(3)-aligned) and RPE with evo, drift per 100 m, plane angle and offset errors,
cloud-to-mesh distances and segment association accuracy. Writes DIR/eval.json and PNG plots
and prints a short table."""


class GroundTruthNotFound(ValueError):
    """No ground-truth folder could be found for the run."""


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "evaluate", help="evaluate SLAM outputs against ground truth", description=DESCRIPTION
    )
    p.add_argument("dir", type=Path, metavar="DIR", help="SLAM output folder")
    p.add_argument(
        "--gt",
        type=Path,
        metavar="BAG.gt|BAG",
        help="ground-truth folder, or the bag (its <stem>.gt beside it is used); "
        "default: the bag named in DIR/summary.json",
    )
    p.add_argument(
        "--align",
        choices=("start", "se3", "none"),
        default="start",
        help="transform of planes and cloud into the ground truth's world before comparing: "
        "start = the start pose is the datum (default), se3 = the trajectory's SE(3) alignment",
    )
    p.add_argument(
        "--max-cloud-points",
        type=int,
        default=2_000_000,
        metavar="N",
        help="evaluate at most N cloud points (regular stride; default 2000000)",
    )
    p.add_argument("--no-plots", action="store_true", help="write eval.json only")
    return p


def _gt_for(path: Path) -> Path:
    """The ground-truth folder for ``path``: itself, or ``<stem>.gt`` beside a bag."""
    if path.is_dir() and (path / "trajectory.tum").is_file():
        return path
    beside = path.parent / f"{path.stem}.gt"
    if path.suffix != ".gt" and beside.is_dir():
        return beside
    raise GroundTruthNotFound(f"{path}: not a ground-truth folder and no {beside.name} beside it")


def resolve_ground_truth(run_dir: Path, gt: Path | None) -> Path:
    """``--gt`` as given (folder or bag), else the bag recorded in ``run_dir/summary.json``."""
    if gt is not None:
        return _gt_for(gt)
    summary = run_dir / "summary.json"
    bag: Any = None
    if summary.is_file():
        from slam.export import read_summary_json

        bag = read_summary_json(summary).get("bag")
    if not isinstance(bag, str):
        raise GroundTruthNotFound(f"{run_dir}: no --gt given and {summary.name} names no bag")
    return _gt_for(Path(bag))


def _mm(x: float) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{1000 * x:.1f}"


def format_table(js: dict[str, Any]) -> str:
    """A short text table of the main figures of an ``eval.json``."""
    tr = js["trajectory"]
    ate = tr["ate_m"]
    lines = [
        f"poses {tr['n_poses']}, path {tr['path_length_m']:.1f} m",
        "ATE RMSE (mm)       unaligned {}  start-aligned {}  SE(3)-aligned {}{}".format(
            _mm(ate["unaligned"]["rmse"]),
            _mm(ate["start_aligned"]["rmse"]),
            _mm(ate["se3_aligned"]["rmse"]),
            "" if tr["se3_alignment_ok"] else " (degenerate: = start)",
        ),
    ]
    r1, r10 = tr["rpe_1m"]["translation_m"], tr["rpe_10m"]["translation_m"]
    lines.append(
        "RPE mean (mm)       1 m {}  10 m {}".format(
            _mm(r1["mean"]) if r1 else "-", _mm(r10["mean"]) if r10 else "-"
        )
    )
    dr = tr["drift_per_100m"]

    def num(x: Any, fmt: str) -> str:
        return "-" if x is None or not math.isfinite(x) else format(x, fmt)

    lines.append(
        f"drift per 100 m     end point {num(dr['endpoint_percent'], '.3f')} %  "
        f"RPE {num(dr['rpe_percent'], '.3f')} %  rotation {num(dr['rotation_deg'], '.3f')} deg"
    )
    if js["planes"]:
        pl = js["planes"]
        lines.append(
            f"planes              {pl['n_matched']}/{pl['n_estimated']} matched, "
            f"angle median {num(pl['angle_deg']['median'], '.3f')} deg "
            f"(max {num(pl['angle_deg']['max'], '.3f')}), "
            f"offset median {_mm(pl['offset_m']['median'])} mm (max {_mm(pl['offset_m']['max'])})"
        )
    if js["cloud"]:
        d = js["cloud"]["distance_m"]
        lines.append(
            f"cloud to mesh (mm)  mean {_mm(d['mean'])}  median {_mm(d['median'])}  "
            f"p95 {_mm(d['p95'])}  ({js['cloud']['n_points_evaluated']} points)"
        )
    if js["association"]:
        a = js["association"]
        lines.append(
            f"association         correct {100 * a['fraction_correct']:.1f} % of "
            f"{a['n_segments']} segments, associated {100 * a['fraction_associated']:.1f} %"
        )
    for what, why in js["skipped"].items():
        lines.append(f"skipped {what}: {why}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from slam.eval_plots import write_plots
    from slam.evaluate import EvaluationError, evaluate, write_eval_json

    run_dir: Path = args.dir
    if not run_dir.is_dir():
        raise EvaluationError(f"{run_dir}: SLAM output folder not found")
    if args.max_cloud_points < 1:
        raise EvaluationError(f"--max-cloud-points: must be >= 1, got {args.max_cloud_points}")
    gt = resolve_ground_truth(run_dir, args.gt)
    result = evaluate(run_dir, gt, map_alignment=args.align, max_cloud_points=args.max_cloud_points)
    out = write_eval_json(run_dir / "eval.json", result)
    plots = [] if args.no_plots else write_plots(result, run_dir)
    print(format_table(result.to_json()))
    print(f"wrote {out}" + (f" and {len(plots)} plots in {run_dir}" if plots else ""))
    return 0
