"""Door and board outlines of runs against their true faces: one panel per true door or board,
each run's outline of the plane matched to it (planes.json, brought into the ground truth's
frame by the run's SE(3) alignment), the face in green, the extent errors in the legend.

Usage:
    .venv/bin/python scripts/plot_outlines.py --gt RUN.gt --runs label=DIR[,label=DIR] --out FILE.png
        [--title TEXT]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gt", type=Path, required=True, help="the walk's ground-truth folder")
    ap.add_argument("--runs", required=True, help="comma-separated label=run folder")
    ap.add_argument("--out", type=Path, required=True, help="PNG to write")
    ap.add_argument("--title", default="", help="figure title")
    args = ap.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common.atomic import atomic_path
    from slam.evaluate import evaluate
    from slam.frontend.planemap import plane_basis

    runs = [spec.split("=", 1) for spec in args.runs.split(",")]
    results = [(label, evaluate(Path(folder), args.gt, map_alignment="se3")) for label, folder in runs]
    faces: dict[int, tuple[np.ndarray, np.ndarray, str]] = {}
    for _, res in results:
        assert res.planes is not None
        for m in res.planes.matches:
            if m.est_id in res.planes.outlines:
                _, true, normal = res.planes.outlines[m.est_id]
                faces.setdefault(m.true_id, (true, normal, m.kind))
    ids = sorted(faces)
    cols = min(4, max(1, len(ids)))
    rows = max(1, -(-len(ids) // cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.8 * cols, 3.0 * rows), squeeze=False)
    styles = ["tab:orange", "tab:red", "tab:blue", "tab:purple"]
    for ax, tid in zip(axes.ravel(), ids, strict=False):
        true, normal, kind = faces[tid]
        B = np.stack(plane_basis(normal))
        t = true @ B.T
        lo, hi = t.min(axis=0), t.max(axis=0)
        ax.fill([lo[0], hi[0], hi[0], lo[0]], [lo[1], lo[1], hi[1], hi[1]], color="tab:green", alpha=0.25,
                label="true face")
        for (label, res), colour in zip(results, styles, strict=False):
            assert res.planes is not None
            for m in res.planes.matches:
                if m.true_id != tid or m.est_id not in res.planes.outlines:
                    continue
                e = res.planes.outlines[m.est_id][0] @ B.T
                a, b = e.min(axis=0), e.max(axis=0)
                ax.plot([a[0], b[0], b[0], a[0], a[0]], [a[1], a[1], b[1], b[1], a[1]], color=colour,
                        label=f"{label}: {100 * m.extent_error_m:.0f} cm")
        ax.set_title(f"true {kind} {tid}", fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6)
    for ax in axes.ravel()[len(ids):]:
        ax.axis("off")
    if args.title:
        fig.suptitle(args.title, fontsize=10)
    fig.tight_layout()
    with atomic_path(args.out) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
