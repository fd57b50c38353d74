"""Calibration experiment: perturb the true extrinsics, calibrate from a simulated recording, report
the recovered error per parameter (goal: < 0.05 deg and < 2 mm from a 2-minute recording).

    python scripts/calibration_recovery.py --out results/calibration_recovery [--duration 120]

Simulates ``configs/simulation/calibration.yaml`` (or reuses ``OUT/run.bag``), perturbs the tilted
scanners' true ``T_body_scanner`` by uniform draws within +-``--max-deg`` and +-``--max-mm`` per
parameter (seeded), runs :func:`calibration.calibrate.calibrate_bag` coarse to fine (the first
round's SLAM gates opened for an extrinsic error of ``--coarse-deg`` / ``--coarse-mm``, by
default the perturbation bounds; 0 0 = the plain schedule) and writes ``OUT/recovery.csv`` (per
scanner and parameter: perturbation, recovered error, 1-sigma marginal (``sigma``) and
cluster-robust (``sigma_cluster``)), ``OUT/rounds.json`` (per round: planes, points, change, gates,
SLAM and batch seconds; the wall time), ``OUT/recovery.png`` (results written atomically), the
calibrated rig and the report folder; prints one line per round as it ends, the wall time and
the error / sigma statistics.

    python scripts/calibration_recovery.py --out docs/figures/calibration_recovery.csv --summarize RUN...

collects several runs (seeds) into one CSV (``seed`` column) and figure (``.png`` next to it).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from calibration.calibrate import CalibrationOptions, RoundInfo, calibrate_bag
from calibration.estimator import EstimatorConfig
from calibration.observability import PARAMETERS, parameter_covariance
from calibration.report import write_report
from calibration.rig_io import updated_rig
from common.config import configs_dir
from common.rig import Rig, write_rig
from common.rotations import matrix_to_rpy
from slam.config import SlamConfig


def perturbed_rig(true: Rig, rng: np.random.Generator, max_deg: float, max_m: float) -> Rig:
    """The true rig with every non-reference scanner's rpy and xyz moved by uniform draws."""
    ext = {}
    for s in true.scanners:
        if s.name == true.reference:
            continue
        e = s.T_body_scanner
        rpy = np.array(e.rpy) + np.radians(rng.uniform(-max_deg, max_deg, 3))
        xyz = np.array(e.translation) + rng.uniform(-max_m, max_m, 3)
        T = np.eye(4)
        T[:3, :3] = e.model_copy(update={"rpy": rpy.tolist()}).matrix()[:3, :3]
        T[:3, 3] = xyz
        ext[s.name] = (T, None)
    return updated_rig(true, ext, name=f"{true.name}-perturbed")


def parameters(T: np.ndarray) -> np.ndarray:
    return np.array([*matrix_to_rpy(T[:3, :3]), *T[:3, 3]])


def _atomic(path: Path, write: Callable[[Path], object]) -> None:
    """``write(tmp)`` then rename ``tmp`` to ``path``: an interrupted run leaves no half file."""
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    write(tmp)
    os.replace(tmp, path)


def _write_csv(path: Path, rows: list[dict[str, object]]) -> None:
    def write(tmp: Path) -> None:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(dict.fromkeys(k for r in rows for k in r)), restval="nan")
            w.writeheader()
            w.writerows(rows)

    _atomic(path, write)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--config", type=Path, default=configs_dir() / "simulation" / "calibration.yaml")
    ap.add_argument("--duration", type=float, default=None, help="override the recording's duration (s)")
    ap.add_argument("--seed", type=int, default=7, help="seed of the perturbation")
    ap.add_argument("--max-deg", type=float, default=3.0)
    ap.add_argument("--max-mm", type=float, default=50.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--time-offsets", action="store_true")
    ap.add_argument("--coarse-deg", type=float, default=None,
                    help="rotation uncertainty of the initial rig for the first round's gates (default --max-deg)")
    ap.add_argument("--coarse-mm", type=float, default=None,
                    help="translation uncertainty of the initial rig (default --max-mm)")
    ap.add_argument("--cluster-knots", type=int, nargs="+", default=[20],
                    help="knot intervals per cluster of the cluster-robust covariance; the first is "
                         "sigma_cluster (the reported one), the others extra columns sigma_cluster_<N>k "
                         "(default 20: 1 s)")
    ap.add_argument("--summarize", type=Path, nargs="+", default=None, metavar="RUN",
                    help="no run: collect these runs' results into --out's CSV and figure "
                         "(--out is then the CSV path; the figure gets the .png suffix)")
    ap.add_argument("--coarse-seconds", type=float, default=None,
                    help="loosened (coarse) rounds use only the first this many seconds of the "
                         "recording (default: all); the last round always uses all of it")
    args = ap.parse_args()
    if args.summarize:
        summarize(args.summarize, args.out, args.out.with_suffix(".png"))
        return
    from simulation.run import load_simulation_config, simulate

    args.out.mkdir(parents=True, exist_ok=True)
    bag = args.out / "run.bag"
    if not bag.exists():
        cfg = load_simulation_config(args.config)
        simulate(cfg.world, cfg.rig, duration=args.duration, out=bag, config=cfg)
    from common.rig import load_rig

    true = load_rig(args.out / "run.gt" / "rig.yaml")
    rig0 = perturbed_rig(true, np.random.default_rng(args.seed), args.max_deg, args.max_mm / 1e3)
    write_rig(args.out / "perturbed.yaml", rig0)
    c_deg = args.max_deg if args.coarse_deg is None else args.coarse_deg
    c_mm = args.max_mm if args.coarse_mm is None else args.coarse_mm
    if min(c_deg, c_mm, args.max_deg, args.max_mm) < 0 or args.rounds < 1:
        raise SystemExit("--max-deg/--max-mm/--coarse-deg/--coarse-mm: must be >= 0; --rounds: >= 1")
    unc = (math.radians(c_deg), c_mm / 1e3) if c_deg > 0 or c_mm > 0 else None
    windows = tuple(args.cluster_knots)
    est = EstimatorConfig(time_offsets=args.time_offsets, cluster_knots=windows)
    opts = CalibrationOptions(estimator=est, max_rounds=args.rounds,
                              initial_uncertainty=unc, coarse_duration=args.coarse_seconds)
    t0 = time.perf_counter()
    def on_round(info: RoundInfo, rig: Rig) -> None:  # the error against the truth after each round
        worst = []
        for s in rig.scanners:
            if s.name != true.reference:
                d = parameters(s.T_body_scanner.matrix()) - parameters(true.scanner(s.name).T_body_scanner.matrix())
                worst.append(f"{s.name} {np.degrees(np.abs(d[:3]).max()):.4f} deg / "
                             f"{np.abs(d[3:]).max() * 1e3:.2f} mm (xyz {np.round(d[3:] * 1e3, 2).tolist()})")
        write_rig(args.out / f"round{info.round}.yaml", rig)
        print(f"  after round {info.round}: " + "; ".join(worst), flush=True)

    cal = calibrate_bag(bag, rig0, SlamConfig(), opts, progress=lambda m: print(m, flush=True), on_round=on_round)
    wall = time.perf_counter() - t0
    write_rig(args.out / "calibrated.yaml", cal.rig)
    text = json.dumps({
        "seed": args.seed, "max_deg": args.max_deg, "max_mm": args.max_mm, "coarse_deg": c_deg,
        "coarse_mm": c_mm, "coarse_seconds": args.coarse_seconds, "wall_seconds": wall, "converged": cal.converged,
        "rounds": [asdict(r) for r in cal.rounds],
        "scanners": {s.name: {"scale": s.scale, "sandwich": s.sandwich} for s in cal.batch.scanners}},
        indent=1)
    _atomic(args.out / "rounds.json", lambda tmp: tmp.write_text(text))
    write_report(cal, args.out / "report")
    rows: list[dict[str, Any]] = []
    for s in cal.batch.scanners:
        if s.reference:
            continue
        p_true = parameters(true.scanner(s.name).T_body_scanner.matrix())
        d0 = parameters(rig0.scanner(s.name).T_body_scanner.matrix()) - p_true
        d1 = parameters(s.T_body_scanner) - p_true
        covs = {"sigma": s.covariance, "sigma_cluster": s.covariance_cluster,
                **{f"sigma_cluster_{w}k": c for w, c in s.covariance_clusters.items() if w != windows[0]}}
        sig = {n: np.sqrt(np.diag(parameter_covariance(s.T_body_scanner, c))) if c is not None
               else np.full(6, np.nan) for n, c in covs.items()}
        for k, name in enumerate(PARAMETERS):
            f = math.degrees(1.0) if k < 3 else 1e3
            rows.append({"scanner": s.name, "parameter": name, "unit": "deg" if k < 3 else "mm",
                         "perturbation": d0[k] * f, "error": d1[k] * f,
                         **{n: v[k] * f for n, v in sig.items()}})
    _write_csv(args.out / "recovery.csv", rows)
    print(f"{'scanner':8s} {'param':6s} {'perturb':>10s} {'error':>10s} {'sigma':>9s} {'sig_cl':>9s}")
    for r in rows:
        print(f"{r['scanner']:8s} {r['parameter']:6s} {r['perturbation']:10.4f} {r['error']:10.4f} "
              f"{r['sigma']:9.4f} {r['sigma_cluster']:9.4f} {r['unit']}")
    st = _stats(rows)
    print(f"max error: {st['rot']:.4f} deg (goal < 0.05), {st['trans']:.3f} mm (goal < 2); converged: "
          f"{cal.converged}; max |error| / sigma {st['max_z']:.2f} "
          f"({'covered' if st['max_z'] < 3 else 'NOT covered'} by 3 sigma); {wall:.0f} s")
    print("error / sigma: " + _z_text(rows))
    for s in cal.batch.scanners:
        print(f"{s.name}: residual scale {s.scale:.2f}, sandwich factor {s.sandwich:.2f}, "
              f"RMS after {np.sqrt(np.mean(s.residuals_after**2)) * 1e3:.2f} mm, "
              f"median |r| {np.median(np.abs(s.residuals_after)) * 1e3:.2f} mm")
    _plot(rows, args.out / "recovery.png")


def _stats(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Worst rotation/translation error and the RMS / max of error / sigma (marginal, cluster)."""
    z = np.array([float(r["error"]) / float(r["sigma"]) for r in rows])
    zc = np.array([float(r["error"]) / float(r["sigma_cluster"]) for r in rows])
    return {"rot": max(abs(float(r["error"])) for r in rows if r["unit"] == "deg"),
            "trans": max(abs(float(r["error"])) for r in rows if r["unit"] == "mm"),
            "rms_z": float(np.sqrt(np.mean(z**2))), "max_z": float(np.max(np.abs(z))),
            "rms_zc": float(np.sqrt(np.mean(zc**2))), "max_zc": float(np.max(np.abs(zc))),
            "n": float(z.size)}


def _z_text(rows: list[dict[str, Any]]) -> str:
    """RMS and max of |error| / sigma for every sigma column (marginal, cluster-robust, windows)."""
    out = []
    for col in (k for k in rows[0] if k.startswith("sigma")):
        z = np.array([float(r["error"]) / float(r[col]) for r in rows])
        out.append(f"{col} RMS {np.sqrt(np.mean(z**2)):.2f} max {np.max(np.abs(z)):.2f}")
    return "; ".join(out)


def summarize(runs: list[Path], csv_path: Path, fig_path: Path) -> None:
    """Collect the runs' ``recovery.csv`` (one seed each, from ``rounds.json``) into one CSV with a
    ``seed`` column and one figure; print per seed the worst errors, wall time per round and the
    error / sigma statistics, then the pooled statistics."""
    rows: list[dict[str, Any]] = []
    for run in runs:
        meta = json.loads((run / "rounds.json").read_text())
        with open(run / "recovery.csv", newline="") as fh:
            sel = [{"seed": meta["seed"], **{k: (v if k in ("scanner", "parameter", "unit") else float(v))
                                            for k, v in r.items()}} for r in csv.DictReader(fh)]
        st = _stats(sel)
        per_round = ", ".join(f"{r['slam_seconds'] / 60:.1f}+{r['batch_seconds'] / 60:.1f}"
                              for r in meta["rounds"])
        print(f"seed {meta['seed']}: {st['rot']:.4f} deg, {st['trans']:.3f} mm; wall "
              f"{meta['wall_seconds'] / 60:.1f} min (SLAM+batch per round, min: {per_round}); "
              f"error/sigma: {_z_text(sel)}")
        rows.extend(sel)
    st = _stats(rows)
    common = ["error"] + [k for k in rows[0] if k.startswith("sigma")
                          and all(k in r and np.isfinite(float(r[k])) for r in rows)]
    print(f"pooled ({int(st['n'])} parameters): error/sigma: {_z_text([{k: r[k] for k in common} for r in rows])}")
    _write_csv(csv_path, rows)
    _plot(rows, fig_path)


def _plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Per scanner and parameter (x), per seed (colour): |perturbation| (open), |recovered error|
    (filled) and 3 reported sigmas (marginal: bar, cluster-robust: cross, the 1 s windows where
    the run has them) on a log axis; the goal as a red line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seeds = sorted({r.get("seed", 0) for r in rows})
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, unit, goal in ((axes[0], "deg", 0.05), (axes[1], "mm", 2.0)):
        sel = [r for r in rows if r["unit"] == unit]
        labels = list(dict.fromkeys(f"{r['scanner']}\n{r['parameter']}" for r in sel))
        for i, seed in enumerate(seeds):
            rs = [r for r in sel if r.get("seed", 0) == seed]
            x = np.array([labels.index(f"{r['scanner']}\n{r['parameter']}") for r in rs])
            x = x + (i - (len(seeds) - 1) / 2) * 0.22
            c = f"C{i}"
            f = np.array([[abs(float(r[k])) for k in ("perturbation", "error", "sigma", "sigma_cluster")]
                          for r in rs])
            # the 1 s windows (the reported covariance) where the run computed them as an extra column
            one_s = np.array([abs(float(r.get("sigma_cluster_20k", "nan"))) for r in rs])
            f[:, 3] = np.where(np.isfinite(one_s), one_s, f[:, 3])
            ax.scatter(x, f[:, 0], facecolors="none", edgecolors=c, marker="o",
                       label=f"seed {seed}: perturbation" if len(seeds) > 1 else "perturbation")
            ax.scatter(x, f[:, 1], color=c, marker="o", zorder=3,
                       label=f"seed {seed}: recovered error" if len(seeds) > 1 else "recovered error")
            ax.vlines(x, f[:, 1], f[:, 0], colors=c, lw=0.5, alpha=0.5)
            ax.scatter(x, 3 * f[:, 2], color=c, marker="_", s=120, lw=2,
                       label="3 sigma marginal" if i == 0 else None)
            ax.scatter(x, 3 * f[:, 3], color=c, marker="x", s=25, lw=1,
                       label="3 sigma cluster-robust (1 s where computed)" if i == 0 else None)
        ax.axhline(goal, color="r", ls="--", label="goal (0.05 deg, 2 mm)")
        ax.set_yscale("log")
        ax.set_xticks(range(len(labels)), labels, fontsize=7)
        ax.set_ylabel(f"|value - true| ({unit})")
        ax.grid(axis="y", which="both", alpha=0.3)
    handles, labels = axes[1].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, loc="lower center", ncol=min(len(labels), 4), frameon=False)
    fig.suptitle("calibration recovery: perturbation vs recovered error")
    fig.tight_layout(rect=(0.0, 0.06 * (1 + (len(labels) - 1) // 4), 1.0, 1.0))
    _atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format=path.suffix.lstrip(".") or "png"))
    plt.close(fig)


if __name__ == "__main__":
    main()
