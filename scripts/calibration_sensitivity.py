"""How much a calibration error raises SLAM drift and map error.

    python scripts/calibration_sensitivity.py --out results/calibration_sensitivity [--world demo --duration 60]

Simulates a walk (or reuses ``OUT/run.bag``), then for each level of calibration error
(rotation 0, 0.25, 0.5, 1, 2 deg paired with translation 0, 5, 10, 20 mm: every combination)
perturbs the tilted scanners' true extrinsics by that amount in a seeded random direction, runs
SLAM with the wrong rig and evaluates it against the ground truth (:func:`slam.evaluate.evaluate`).
Writes ``OUT/sensitivity.csv`` and ``OUT/sensitivity.png`` (ATE RMSE, median plane angle error and
median cloud-to-mesh distance against the rotation error, one line per translation error).
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import numpy as np

from backpack_slam.rig import Rig, load_rig
from calibration.rig_io import updated_rig
from slam.config import SlamConfig
from slam.interpolation import se3_exp

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
    for deg in args.rot_deg:
        for mm in args.trans_mm:
            rig = perturb(true, np.random.default_rng(args.seed), deg, mm)
            run_dir = args.out / f"run_{deg:g}deg_{mm:g}mm"
            run_slam(bag, rig, cfg, run_dir, progress=False)
            ev = evaluate(run_dir, gt)
            row = {"rot_deg": deg, "trans_mm": mm,
                   "ate_rmse_mm": ev.trajectory.ate["se3_aligned"].rmse * 1e3,
                   "plane_angle_median_deg": ev.planes.angle.median if ev.planes else float("nan"),
                   "cloud_median_mm": float(np.median(ev.cloud.distances)) * 1e3 if ev.cloud else float("nan")}
            rows.append(row)
            print(", ".join(f"{k} {v:.4g}" for k, v in row.items()) + f", {time.perf_counter() - t0:.0f} s",
                  flush=True)
    with open(args.out / "sensitivity.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    _plot(rows, args.out / "sensitivity.png", args.trans_mm)
    print(f"wrote {args.out / 'sensitivity.csv'} and {args.out / 'sensitivity.png'}")


def _plot(rows: list[dict[str, float]], path: Path, trans_mm: list[float]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = (("ate_rmse_mm", "ATE RMSE (mm)"), ("plane_angle_median_deg", "plane angle error, median (deg)"),
            ("cloud_median_mm", "cloud-to-mesh median (mm)"))
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    for ax, (key, label) in zip(axes, keys, strict=True):
        for mm in trans_mm:
            sel = [r for r in rows if r["trans_mm"] == mm]
            ax.plot([r["rot_deg"] for r in sel], [r[key] for r in sel], "o-", label=f"{mm:g} mm")
        ax.set_xlabel("rotation error of the tilted scanners (deg)")
        ax.set_ylabel(label)
        ax.legend(title="translation error")
    fig.suptitle("SLAM error versus calibration error")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
