"""Dead reckoning of a simulated bag's IMU from the true state: how well the IMU model fits.

Starts at the ground truth's pose and velocity every ``--every`` seconds, integrates the bag's
``/imu`` for ``--length`` seconds with the bias at zero (right for a noise-free IMU: simulate with
``imu_noise`` all 0), and prints the position error at the end for both sample models of
``slam.imu_feed`` (``instantaneous``: midpoint rule; ``held``: each reading held to the next stamp),
then a summary row. The start velocity is the central difference of the sampled truth, whose own
error is a few mm/s.

Usage:
    .venv/bin/python scripts/imu_dead_reckoning.py BAG [--gt BAG.gt] [--length 8] [--every 6]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from slam.config import SlamConfig
from slam.export import read_trajectory_tum
from slam.imu_feed import ImuSamples, predict_navstate
from slam.io.bag import InputError, read_imu
from slam.motion import ImuConfig
from slam.trajectory.interpolation import interpolate_trajectory


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("--gt", type=Path, default=None, help="ground-truth folder (default: BAG with .gt)")
    ap.add_argument("--length", type=float, default=8.0, help="seconds integrated per start (default 8)")
    ap.add_argument("--every", type=float, default=6.0, help="seconds between starts (default 6)")
    ap.add_argument("--skip", type=float, default=12.0, help="seconds skipped at the start (default 12)")
    args = ap.parse_args(argv)
    gt = args.gt or args.bag.with_suffix(".gt")
    if not (gt / "trajectory.tum").is_file():
        print(f"error: {gt / 'trajectory.tum'}: no ground-truth trajectory", file=sys.stderr)
        return 2
    try:
        series = read_imu(args.bag, "/imu")
        t_gt, T_gt = read_trajectory_tum(gt / "trajectory.tum")
        models = {name: ImuSamples(series.times, series.linear_acceleration, series.angular_velocity,
                                   instantaneous=name == "instantaneous") for name in ("instantaneous", "held")}
    except InputError as e:  # names the bag already
        print(f"error: {e}", file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"error: {args.bag}: {e}", file=sys.stderr)
        return 2
    ic = SlamConfig().imu  # the SLAM configuration's IMU model (the prediction uses its gravity)
    cfg = ImuConfig(accel_noise_density=ic.accel_noise, gyro_noise_density=ic.gyro_noise,
                    accel_bias_rw=ic.accel_bias_walk, gyro_bias_rw=ic.gyro_bias_walk,
                    integration_sigma=ic.integration_sigma, bias_prior_sigmas=(ic.accel_bias_prior, ic.gyro_bias_prior),
                    velocity_prior_sigma=1.0, gravity=ic.gravity, T_body_imu=None)
    h = 1e-3
    end = min(t_gt[-1], series.times[-1]) - args.length
    starts = np.arange(t_gt[0] + args.skip, end, args.every)
    if starts.size == 0:
        print(f"error: {args.bag}: shorter than --skip + --length", file=sys.stderr)
        return 2
    errs: dict[str, list[float]] = {k: [] for k in models}
    print("| start (s) | instantaneous, midpoint (mm) | held (mm) |\n|---:|---:|---:|")
    for t0 in starts:
        T0 = interpolate_trajectory(t_gt, T_gt, np.array([t0]))[0]
        p = interpolate_trajectory(t_gt, T_gt, np.array([t0 - h, t0 + h]))[:, :3, 3]
        v0 = (p[1] - p[0]) / (2 * h)
        T_true = interpolate_trajectory(t_gt, T_gt, np.array([t0 + args.length]))[0]
        row = []
        for name, samples in models.items():
            T1, _ = predict_navstate(cfg, T0, v0, np.zeros(6), samples, t0, t0 + args.length)
            e = float(np.linalg.norm(T1[:3, 3] - T_true[:3, 3])) * 1e3
            errs[name].append(e)
            row.append(f"{e:.1f}")
        print(f"| {t0 - t_gt[0]:.0f} | " + " | ".join(row) + " |")
    med = {k: float(np.median(v)) for k, v in errs.items()}
    print(f"| **median** | {med['instantaneous']:.1f} | {med['held']:.1f} |")
    print(f"held / midpoint: {med['held'] / max(med['instantaneous'], 1e-9):.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
