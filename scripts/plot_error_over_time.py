"""Position error over time of several SLAM runs of one bag against its ground truth.

Each run's ``trajectory.tum`` is aligned to the ground truth at its first pose (as the
start-aligned ATE is) and the norm of the position error is plotted over time, one line per run,
with the along-x component dashed (the walking direction of the office corridors). ``--heading``
adds a panel with the heading (yaw) error of the body attitude over time, in mdeg.

Usage:
    .venv/bin/python scripts/plot_error_over_time.py GT_DIR OUT.png LABEL=RUN_DIR [LABEL=RUN_DIR ...]
        [--title TEXT] [--log] [--heading]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from common.atomic import OutputFileError
from slam.export import read_trajectory_tum
from slam.trajectory.interpolation import interpolate_trajectory


def _start_aligned(gt_dir: Path, run_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (s from the run's start), the run's poses aligned to the ground truth at its first
    pose and the true poses at those times (n, 4, 4); poses after the ground truth's end are dropped."""
    t_gt, T_gt = read_trajectory_tum(gt_dir / "trajectory.tum")
    t, T = read_trajectory_tum(run_dir / "trajectory.tum")
    keep = (t >= t_gt[0]) & (t <= t_gt[-1])
    t, T = t[keep], T[keep]
    G = interpolate_trajectory(t_gt, T_gt, t)
    A = G[0] @ np.linalg.inv(T[0])
    return t - t[0], np.einsum("ij,njk->nik", A, T), G


def start_aligned_errors(gt_dir: Path, run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """Times (s from the run's start) and position errors (n, 3) in the world frame [m] of a run
    aligned to the ground truth at its first pose; poses after the ground truth's end are dropped."""
    t, T, G = _start_aligned(gt_dir, run_dir)
    return t, T[:, :3, 3] - G[:, :3, 3]


def start_aligned_heading_errors(gt_dir: Path, run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """Times (s from the run's start) and the heading error (rad, about world z) of the body
    attitude of a run aligned to the ground truth at its first pose."""
    t, T, G = _start_aligned(gt_dir, run_dir)
    dR = np.einsum("nij,nkj->nik", T[:, :3, :3], G[:, :3, :3])  # R_est R_true^T, world frame
    return t, np.arctan2(dR[:, 1, 0] - dR[:, 0, 1], dR[:, 0, 0] + dR[:, 1, 1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("gt", type=Path, help="the bag's ground-truth folder (RUN.gt/)")
    ap.add_argument("out", type=Path, help="PNG to write")
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    ap.add_argument("--title", default="")
    ap.add_argument("--log", action="store_true", help="logarithmic error axis")
    ap.add_argument("--heading", action="store_true", help="add a panel with the heading error (mdeg)")
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2 if a.heading else 1, 1, figsize=(9, 7.5 if a.heading else 4.5), sharex=True,
                             squeeze=False)
    ax = axes[0, 0]
    for item in a.runs:
        label, sep, folder = item.partition("=")
        if not sep:
            print(f"error: run '{item}': expected LABEL=RUN_DIR", file=sys.stderr)
            return 2
        try:
            t, E = start_aligned_errors(a.gt, Path(folder))
        except (OutputFileError, ValueError, OSError) as e:
            print(f"error: run '{label}': {e}", file=sys.stderr)
            return 2
        line, = ax.plot(t, np.linalg.norm(E, axis=1) * 1000, label=f"{label} |error|")
        ax.plot(t, np.abs(E[:, 0]) * 1000, "--", color=line.get_color(), lw=0.8, label=f"{label} |x|")
        if a.heading:
            th, yaw = start_aligned_heading_errors(a.gt, Path(folder))
            rms = float(np.degrees(np.sqrt(np.mean(yaw**2)))) * 1000
            axes[1, 0].plot(th, np.degrees(yaw) * 1000, lw=0.6, color=line.get_color(),
                            label=f"{label} (RMS {rms:.0f} mdeg)")
    axes[-1, 0].set_xlabel("time since start (s)")
    ax.set_ylabel("position error (mm), start-aligned")
    if a.heading:
        axes[1, 0].set_ylabel("heading error (mdeg), start-aligned")
        axes[1, 0].grid(alpha=0.3)
        axes[1, 0].legend(fontsize=7)
    if a.log:
        ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    ax.set_title(a.title)
    fig.tight_layout()
    tmp = a.out.with_name(a.out.name + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    tmp.replace(a.out)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
