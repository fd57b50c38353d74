"""Plots of segmented scanlines (scanner frame): points coloured by segment, unsegmented
points grey, each segment's fitted line drawn between its projected endpoints."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from numpy.typing import NDArray

from common.atomic import atomic_path
from segmentation import Scanline, Segmentation


@dataclass(frozen=True)
class Panel:
    """One scanline with its segmentation and a title."""

    scanline: Scanline
    segmentation: Segmentation
    title: str


def draw_segmentation(ax: Axes, line: Scanline, seg: Segmentation, title: str = "") -> None:
    """Draw one segmented scanline on ``ax`` in the scanner frame (m), with its fitted lines."""
    draw_labels(ax, line, seg.labels, title, f"{seg.method}: ")
    for k in range(seg.n_segments):
        e = seg.endpoints[k]
        ax.plot(e[:, 0], e[:, 1], "-", color="k", lw=0.8)


def draw_labels(ax: Axes, line: Scanline, labels: NDArray[np.int64], title: str = "", prefix: str = "") -> None:
    """Draw a scanline's valid points coloured by per-beam ``labels`` (-1 grey) on ``ax``."""
    pts = line.points_xy
    lab = np.asarray(labels)[line.valid_index]
    grey = lab < 0
    n_seg = int(lab.max()) + 1 if lab.size and lab.max() >= 0 else 0
    ax.scatter(pts[grey, 0], pts[grey, 1], s=3, c="0.6", linewidths=0)
    if n_seg:
        colours = np.asarray(_palette(n_seg))
        ax.scatter(pts[~grey, 0], pts[~grey, 1], s=4, c=colours[lab[~grey]], linewidths=0)
    ax.plot([0.0], [0.0], marker="^", color="tab:red", ms=6, ls="none")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m, scanner frame)")
    ax.set_ylabel("y (m)")
    sub = f"{prefix}{len(np.unique(lab[~grey]))} segments, {int(np.count_nonzero(~grey))}/{line.n_valid} points"
    ax.set_title(f"{title}\n{sub}" if title else sub, fontsize=9)
    ax.grid(True, lw=0.3, alpha=0.5)


def _palette(n: int) -> list[tuple[float, float, float, float]]:
    from matplotlib import colormaps

    cmap = colormaps["tab20"]
    # alternate the pairs of tab20 so neighbouring segments differ strongly
    order = [0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 1, 3, 5, 7, 9, 11, 13, 15, 17, 19]
    return [cmap(order[k % 20]) for k in range(n)]


def new_figure(n_panels: int, size: float = 5.0) -> tuple[Figure, list[Axes]]:
    """A figure with ``n_panels`` side by side (no pyplot state: Agg canvas)."""
    fig = Figure(figsize=(size * n_panels, size), layout="constrained")
    axes = fig.subplots(1, n_panels, squeeze=False)[0]
    return fig, list(axes)


IMAGE_FORMATS = ("png", "pdf", "svg", "svgz", "jpg", "jpeg", "eps", "ps", "tif", "tiff", "webp", "gif", "avif", "pgf")


def check_image_path(path: str | Path, option: str) -> None:
    """A ValueError naming ``option`` unless ``path`` can take an image: a suffix matplotlib
    writes, and not an existing folder (checked before any work, so that nothing is written
    for an image that cannot be)."""
    p = Path(path)
    fmt = p.suffix.lower().lstrip(".")
    if fmt not in IMAGE_FORMATS:
        raise ValueError(f"{option} {p}: unknown image format '{p.suffix}' (use one of .{', .'.join(IMAGE_FORMATS)})")
    if p.is_dir():
        raise ValueError(f"{option} {p}: is a folder")


def save_figure(fig: Figure, path: str | Path, dpi: int = 150) -> Path:
    """Save ``fig`` to ``path`` atomically (the format from the suffix); creates the folder."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(p) as tmp:
        fig.savefig(tmp, dpi=dpi, format=p.suffix.lower().lstrip(".") or None)
    return p


def plot_panels(path: str | Path, panels: Sequence[Panel], suptitle: str = "") -> Path:
    """One panel per segmented scanline, side by side, saved to ``path``."""
    fig, axes = new_figure(len(panels))
    for ax, p in zip(axes, panels, strict=True):
        draw_segmentation(ax, p.scanline, p.segmentation, p.title)
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    return save_figure(fig, path)
