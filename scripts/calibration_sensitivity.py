"""How much a calibration error raises SLAM drift and map error.

    python scripts/calibration_sensitivity.py --out results/calibration_sensitivity [--world demo --duration 60]

Simulates a walk (or reuses ``OUT/run.bag``), then for each level of calibration error
(rotation 0, 0.25, 0.5, 1, 2 deg paired with translation 0, 5, 10, 20 mm: every combination)
perturbs the tilted scanners' true extrinsics by that amount in a seeded random direction, runs
SLAM with the wrong rig and evaluates it against the ground truth (:func:`slam.evaluate.evaluate`).
Writes ``OUT/sensitivity.csv`` and ``OUT/sensitivity.png`` (ATE RMSE SE(3)- and start-aligned,
median plane angle error and median cloud-to-mesh distance against the rotation error, one line
per translation error). ``--rot-deg`` / ``--trans-mm`` choose the levels (a shorter study).
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from calibration.rig_io import updated_rig
from common.rig import Rig, load_rig
from slam.config import SlamConfig
from slam.trajectory.interpolation import se3_exp

ROT_DEG = (0.0, 0.25, 0.5, 1.0, 2.0)
TRANS_MM = (0.0, 5.0, 10.0, 20.0)


def perturb(true: Rig, rng: np.random.Generator, deg: float, mm: float) -> Rig:
    """Every non-reference extrinsic moved by exactly ``deg`` and ``mm`` in random directions."""
    ext = {}
    for s in true.scanners:
        if s.name == true.reference:
            continue
        u, v = rng.normal(size=3), rng.normal(size=3)
        d = np.concatenate([math.radians(deg) * u / np.linalg.norm(u), mm * 1e-3 * v / np.linalg.norm(v)])
        T = s.T_body_scanner.matrix()
        T_new = T @ se3_exp(np.concatenate([d[:3], np.zeros(3)]))
        T_new[:3, 3] = T[:3, 3] + d[3:]
        ext[s.name] = (T_new, None)
    return updated_rig(true, ext)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--world", default="demo")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--rot-deg", type=float, nargs="+", default=list(ROT_DEG), help="rotation errors (deg)")
    ap.add_argument("--trans-mm", type=float, nargs="+", default=list(TRANS_MM), help="translation errors (mm)")
    ap.add_argument("--one-at-a-time", action="store_true",
                    help="vary rotation (translation 0) and translation (rotation 0) separately, not the grid")
    args = ap.parse_args()
    from simulation.run import simulate
    from slam.evaluate import evaluate
    from slam.run import run_slam

    args.out.mkdir(parents=True, exist_ok=True)
    bag = args.out / "run.bag"
    if not bag.exists():
        simulate(args.world, "itc_backpack", duration=args.duration, seed=args.seed, out=bag)
    gt = args.out / "run.gt"
    true = load_rig(gt / "rig.yaml")
    cfg = SlamConfig()
    cfg = cfg.model_copy(update={"output": cfg.output.model_copy(update={"rerun": False, "voxel": 0.02})})
    rows = []
    t0 = time.perf_counter()
    levels = [(deg, mm) for deg in args.rot_deg for mm in args.trans_mm
              if not args.one_at_a_time or deg == 0.0 or mm == 0.0]
    for deg, mm in tqdm(levels, desc="calibration errors"):
        rig = perturb(true, np.random.default_rng(args.seed), deg, mm)
        run_dir = args.out / f"run_{deg:g}deg_{mm:g}mm"
        nan = float("nan")
        row = {"rot_deg": deg, "trans_mm": mm, "ate_rmse_mm": nan, "ate_start_rmse_mm": nan,
               "plane_angle_median_deg": nan, "cloud_median_mm": nan, "slam_failed": 0.0}
        try:
            run_slam(bag, rig, cfg, run_dir, progress=False)
        except ValueError as err:  # a rig this wrong can break SLAM itself: record it, go on
            print(f"{deg:g} deg, {mm:g} mm: SLAM failed: {err}", flush=True)
            row["slam_failed"] = 1.0
        else:
            ev = evaluate(run_dir, gt)
            row.update({"ate_rmse_mm": ev.trajectory.ate["se3_aligned"].rmse * 1e3,
                        "ate_start_rmse_mm": ev.trajectory.ate["start_aligned"].rmse * 1e3,
                        "plane_angle_median_deg": ev.planes.angle.median if ev.planes else nan,
                        "cloud_median_mm": float(np.median(ev.cloud.distances)) * 1e3 if ev.cloud else nan})
        rows.append(row)
        print(", ".join(f"{k} {v:.4g}" for k, v in row.items()) + f", {time.perf_counter() - t0:.0f} s",
              flush=True)
    with open(args.out / "sensitivity.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    _plot(rows, args.out / "sensitivity.png")
    print(f"wrote {args.out / 'sensitivity.csv'} and {args.out / 'sensitivity.png'}")


def _plot(rows: list[dict[str, float]], path: Path) -> None:
    """Each metric against the rotation error (one line per translation error, top row) and against
    the translation error (one line per rotation error, bottom row)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = (("ate_rmse_mm", "ATE RMSE, SE(3)-aligned (mm)"), ("ate_start_rmse_mm", "ATE RMSE, start-aligned (mm)"),
            ("plane_angle_median_deg", "plane angle error, median (deg)"),
            ("cloud_median_mm", "cloud-to-mesh median (mm)"))
    fig, axes = plt.subplots(2, 4, figsize=(17, 7.5))
    for row, (x, other, xlabel, unit) in enumerate((("rot_deg", "trans_mm", "rotation error (deg)", "mm"),
                                                    ("trans_mm", "rot_deg", "translation error (mm)", "deg"))):
        for ax, (key, label) in zip(axes[row], keys, strict=True):
            for lev in sorted({r[other] for r in rows}):
                sel = sorted((r for r in rows if r[other] == lev), key=lambda r: r[x])
                if len(sel) >= 2:
                    ax.plot([r[x] for r in sel], [r[key] for r in sel], "o-", label=f"{lev:g} {unit}")
            ax.set_xlabel(f"{xlabel} of the tilted scanners")
            ax.set_ylabel(label)
            ax.set_yscale("log")  # a diverged run is 1000x the others
            ax.legend(title="other error", fontsize=8)
    fig.suptitle("SLAM error versus calibration error")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
