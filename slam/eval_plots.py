"""Plots of an evaluation (matplotlib, Agg canvas, no display): PNGs written atomically.

- ``trajectory_error_topview.png``: top view (x, y in the ground-truth world) of the ground
  truth and of the start-aligned estimate coloured by its position error.
- ``error_over_distance.png``: position error against distance walked, for the three ATE
  variants.
- ``plane_errors.png``: histograms of plane angle (deg) and offset (mm) errors.
- ``cloud_to_mesh.png``: histogram of the cloud's distances to the true mesh (mm).
- ``plane_extents.png``: each door's and board's estimated extent against its true face, in
  the face's plane.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from common.atomic import atomic_path
from slam.evaluate import CloudEval, EvalResult, PlaneEval, TrajectoryEval
from slam.frontend.planemap import plane_basis


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    return path


def plot_topview(traj: TrajectoryEval, path: Path) -> Path:
    """Ground truth (grey) and start-aligned estimate coloured by its error (mm)."""
    fig = Figure(figsize=(7, 6))
    ax = fig.add_subplot()
    ax.plot(traj.gt_xyz[:, 0], traj.gt_xyz[:, 1], color="0.6", lw=3, label="ground truth")
    xy = traj.est_xyz_start[:, :2]
    segs = np.stack([xy[:-1], xy[1:]], axis=1)
    err_mm = 1000.0 * traj.err_start
    lc = LineCollection(list(segs), cmap="viridis", linewidths=1.5)
    lc.set_array(0.5 * (err_mm[:-1] + err_mm[1:]))
    ax.add_collection(lc)
    fig.colorbar(lc, ax=ax, label="position error, start-aligned (mm)")
    ax.plot(*xy[0], "k^", label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ate = traj.ate
    ax.set_title(
        f"ATE RMSE: start-aligned {1000 * ate['start_aligned'].rmse:.1f} mm, "
        f"SE(3)-aligned {1000 * ate['se3_aligned'].rmse:.1f} mm",
        fontsize=10,
    )
    ax.legend(loc="best", fontsize=8)
    return _save(fig, path)


def plot_error_over_distance(traj: TrajectoryEval, path: Path) -> Path:
    """Position error (mm) of the three ATE variants against distance walked (m)."""
    fig = Figure(figsize=(8, 4))
    ax = fig.add_subplot()
    for err, label, style in (
        (traj.err_start, "start-aligned (datum)", "-"),
        (traj.err_se3, "SE(3)-aligned", "-"),
        (traj.err_unaligned, "unaligned", "--"),  # dashed: often equal to start-aligned
    ):
        ax.plot(traj.distance, 1000.0 * err, lw=1, ls=style, label=label)
    ax.set_xlabel("distance walked (m)")
    ax.set_ylabel("position error (mm)")
    ax.set_title(
        f"drift: {traj.drift_endpoint_per_100m:.3f} % (end point), "
        f"{traj.rot_drift_deg_per_100m:.3f} deg/100 m",
        fontsize=10,
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def plot_plane_errors(planes: PlaneEval, path: Path) -> Path:
    """Histograms of angle (deg) and signed offset (mm) errors of the matched planes, and each
    plane's angle error against its own reported 1-sigma (log-log, by the true plane's kind):
    points near the diagonal are planes as good as their data allow."""
    fig = Figure(figsize=(14.5, 3.8))
    ax1, ax2, ax3 = fig.subplots(1, 3)
    ang = np.array([m.angle_deg for m in planes.matches])
    off = 1000.0 * np.array([m.offset_m for m in planes.matches])
    ax1.hist(ang, bins=30, color="tab:blue")
    ax1.set_xlabel("normal angle error (deg)")
    ax1.set_ylabel("planes")
    ax1.set_title(f"median {np.median(ang):.3f} deg" if ang.size else "no matches", fontsize=10)
    ax2.hist(off, bins=30, color="tab:orange")
    ax2.set_xlabel("offset error (mm)")
    ax2.set_title(
        f"median |offset| {np.median(np.abs(off)):.1f} mm" if off.size else "no matches",
        fontsize=10,
    )
    sig = np.array([m.sigma_angle_deg for m in planes.matches])
    ok = np.isfinite(sig) & (sig > 0)
    if ok.any():
        kinds = np.array([m.kind for m in planes.matches])
        floor = 1e-4
        for kind in sorted(set(kinds[ok].tolist())):
            sel = ok & (kinds == kind)
            ax3.scatter(sig[sel], np.maximum(ang[sel], floor), s=12, label=kind)
        lo, hi = max(min(sig[ok].min(), ang[ok].min()), floor) / 2, max(sig[ok].max(), ang[ok].max()) * 2
        xs = np.array([lo, hi])
        ax3.plot(xs, xs, "k-", lw=0.8, label="error = sigma")
        ax3.plot(xs, 3 * xs, "k--", lw=0.8, label="3 sigma")
        ax3.axhline(0.1, color="tab:red", lw=0.8, label="0.1 deg")
        ax3.set_xscale("log")
        ax3.set_yscale("log")
        ax3.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax3.set_xlabel("reported sigma of the normal (deg)")
    ax3.set_ylabel("angle error (deg)")
    ax3.set_title("error against the plane's own uncertainty", fontsize=10)
    fig.suptitle(
        f"{len(planes.matches)} of {planes.n_estimated} estimated planes matched", fontsize=10
    )
    fig.tight_layout()
    return _save(fig, path)


def plot_plane_extents(planes: PlaneEval, path: Path, max_panels: int = 12) -> Path:
    """One panel per door and board plane (up to ``max_panels``): the estimated extent's outline
    (red) and the true face's (green) in the face's plane (u horizontal, v up; m), titled with the
    extent error (the largest distance between corresponding edges)."""
    by_id = {m.est_id: m for m in planes.matches}
    ids = sorted(planes.outlines)[:max_panels]
    cols = min(4, max(1, len(ids)))
    rows = max(1, -(-len(ids) // cols))
    fig = Figure(figsize=(3.6 * cols, 2.8 * rows))
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    for ax, pid in zip(axes, ids, strict=False):
        est, true, normal = planes.outlines[pid]
        B = np.stack(plane_basis(normal))
        for poly, colour, label in ((true, "tab:green", "true face"), (est, "tab:red", "estimated extent")):
            uv = poly @ B.T
            lo, hi = uv.min(axis=0), uv.max(axis=0)
            ax.plot([lo[0], hi[0], hi[0], lo[0], lo[0]], [lo[1], lo[1], hi[1], hi[1], lo[1]], color=colour, label=label)
        m = by_id[pid]
        ax.set_title(f"plane {pid} ({m.kind}, true {m.true_id}): {100 * m.extent_error_m:.0f} cm", fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=7)
    for ax in axes[len(ids):]:
        ax.axis("off")
    if ids:
        axes[0].legend(fontsize=7)
    else:
        axes[0].text(0.5, 0.5, "no door or board planes matched", ha="center", va="center")
    return _save(fig, path)


def plot_cloud_distances(cloud: CloudEval, path: Path) -> Path:
    """Histogram of point-to-mesh distances (mm) with median and 95th percentile."""
    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    d = 1000.0 * cloud.distances
    hi = float(np.percentile(d, 99.5)) if d.size else 1.0
    ax.hist(np.clip(d, 0, hi), bins=80, color="tab:green")
    for q, style in ((50, "-"), (95, "--")):
        v = float(np.percentile(d, q)) if d.size else 0.0
        ax.axvline(v, color="k", ls=style, lw=1, label=f"{q}th percentile {v:.1f} mm")
    ax.set_xlabel("distance to the true mesh (mm, clipped at the 99.5th percentile)")
    ax.set_ylabel("points")
    ax.legend(fontsize=8)
    return _save(fig, path)


def write_plots(result: EvalResult, out_dir: str | Path) -> list[Path]:
    """Write every plot the result supports into ``out_dir``; return the files written."""
    d = Path(out_dir)
    out = [
        plot_topview(result.trajectory, d / "trajectory_error_topview.png"),
        plot_error_over_distance(result.trajectory, d / "error_over_distance.png"),
    ]
    if result.planes is not None and result.planes.matches:
        out.append(plot_plane_errors(result.planes, d / "plane_errors.png"))
        out.append(plot_plane_extents(result.planes, d / "plane_extents.png"))
    if result.cloud is not None and result.cloud.distances.size:
        out.append(plot_cloud_distances(result.cloud, d / "cloud_to_mesh.png"))
    return out
