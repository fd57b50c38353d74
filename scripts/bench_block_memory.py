"""Bytes the back end holds per observation block, on a synthetic walk through the ``Backend`` API.

A body walks along x at 1 m/s (20 knots/s) past ``--planes`` walls and floor patches; each knot
interval adds ``--blocks`` two-pose blocks of ``--points`` points on planes seen from there, and
``--coalesce`` of them a second time (the front end adds several scans' segments to one (knot,
plane): with ``coalesce_blocks`` they join, as on the office walk, where about 1.4 block ids are
used per live block). The window solver runs every ``--step-every`` knots (the held blocks'
summaries and the release of their factors happen as in a run). The figures, after the walk
(``gc.collect()`` first):

- ``traced``: the Python heap ``tracemalloc`` traced since the ``Backend`` was made, per live block;
- ``rows``: the bytes of the point rows (points, fractions, sigmas) the columns hold in memory
  (their capacity), per live block; ``traced - rows`` is the per-block bookkeeping this script is for
  (the rows of held blocks go to disk once there are ``--spill-rows`` of them in memory, where the
  code spills: the walk is short, so the default here is the code's, 2^18 rows, and ``--spill-rows
  16384`` shows an hour's steady state, its rows in memory bounded);
- ``marginal``: the traced heap's growth over the walk's second half per block added there (what
  a longer walk adds: the window's fixed costs left out; the arrays' growth steps make it coarse);
- ``rss``: (best with ``--no-trace``: tracemalloc's own records count in it) the process's resident set growth over the walk, per live block (gtsam's factors and
  values too; the allocator's slack makes it coarse);
- the traced heap's twelve largest allocation sites, and the walk's time (``tracemalloc`` on: slow).

With ``--baseline REV`` the same walk also runs on git revision REV (exported with ``git archive``,
first on ``PYTHONPATH``) in its own child process, and both are printed.

Usage: nice .venv/bin/python scripts/bench_block_memory.py [--knots 1500] [--baseline REV]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
_ROW = "BLOCK_MEMORY_ROW "


def _rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def walk(knots: int, planes: int, blocks: int, points: int, coalesce: float, step_every: int,
         spill_rows: int | None = None, seed: int = 0, warm_up: bool = True, trace: bool = True) -> dict[str, Any]:
    """The synthetic walk in this process; its figures (see the module doc)."""
    from slam.backend import Backend
    from slam.config import SlamConfig
    from slam.params import backend_config

    rng = np.random.default_rng(seed)
    rate = 20.0
    length = knots / rate + 10.0
    # walls along the walk (normal +-y) and floor patches (normal +z), anchored where they are seen
    xs = rng.uniform(-5.0, length, planes)
    kind = rng.integers(0, 3, planes)  # 0: wall left, 1: wall right, 2: floor
    normals = np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])[kind]
    anchors = np.stack((xs, np.where(kind == 0, 2.0, np.where(kind == 1, -2.0, 0.0)),
                        np.where(kind == 2, -1.5, 0.5)), axis=1)
    cfg = backend_config(SlamConfig(), False)
    if warm_up:  # imports and compilations out of the figures
        walk(30, 20, blocks, points, coalesce, step_every, spill_rows, seed, warm_up=False, trace=trace)
    gc.collect()
    if trace:
        tracemalloc.start()
    rss0 = _rss()
    t0 = tracemalloc.get_traced_memory()[0]
    t_start = time.perf_counter()
    be = Backend(cfg)
    if spill_rows is not None and hasattr(be.blocks.cols, "spill_rows"):
        be.blocks.cols.spill_rows = spill_rows
    added: set[int] = set()
    for i in range(knots):
        x = i / rate
        T = np.eye(4)
        T[0, 3] = x
        be.add_pose(x, T)
        for j in np.flatnonzero(np.abs(xs - x) < 8.0).tolist():
            if j not in added:
                added.add(j)
                n = normals[j]
                be.add_plane(j, n, -float(n @ anchors[j]), horizontal=bool(kind[j] == 2),
                             vertical=bool(kind[j] != 2), anchor=anchors[j])
        if i == 0:
            continue
        near = [j for j in added if abs(xs[j] - x) < 8.0]
        for j in rng.choice(near, size=min(blocks, len(near)), replace=False).tolist():
            for _ in range(2 if rng.uniform() < coalesce else 1):
                al = np.sort(rng.uniform(0.0, 1.0, points))
                # points on plane j (world), seen from the body at their beam times (x moves with alpha)
                u = rng.uniform(-1.0, 1.0, (points, 2))
                n = normals[j]
                t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
                t1 /= np.linalg.norm(t1)
                t2 = np.cross(n, t1)
                pw = anchors[j] + u[:, :1] * t1 + u[:, 1:] * t2 + rng.normal(0.0, 0.005, (points, 1)) * n
                pb = pw - np.stack(((i - 1 + al) / rate, np.zeros(points), np.zeros(points)), axis=1)
                be.add_observations(i - 1, j, pb, al, 0.01)
        if step_every and i % step_every == 0:
            be.step()
        if i == knots // 2:
            gc.collect()
            mid = (tracemalloc.get_traced_memory()[0], len(be.blocks.blocks), _rss())
    be.step()
    seconds = time.perf_counter() - t_start
    gc.collect()
    traced, _ = tracemalloc.get_traced_memory()
    snap = tracemalloc.take_snapshot() if trace else None
    rss = _rss() - rss0
    tracemalloc.stop()
    cols = be.blocks.cols
    n_blocks = len(be.blocks.blocks)
    rows = sum(getattr(cols, name).nbytes for name in ("points", "alphas", "sigmas"))
    disk = getattr(cols, "disk", None)
    spilled = 0 if disk is None else disk.rows("points")
    top = [{"site": str(s.traceback[0]).replace(str(REPO) + "/", ""), "bytes": s.size}
           for s in (snap.statistics("lineno")[:12] if snap is not None else [])]
    return {"knots": knots, "blocks": n_blocks, "points": int(be.blocks.n_points),
            "block_ids": int(be.graph._next_id), "rows_spilled": int(spilled), "traced_per_block": (traced - t0) / n_blocks,
            "rows_per_block": rows / n_blocks, "bookkeeping_per_block": (traced - t0 - rows) / n_blocks,
            "rss_per_block": rss / n_blocks, "seconds": seconds, "traced": trace,
            "marginal_per_block": (traced - mid[0]) / max(1, n_blocks - mid[1]),
            "marginal_rss_per_block": (rss + rss0 - mid[2]) / max(1, n_blocks - mid[1]),
            "top": top}


def _spawn(tree: Path, args: argparse.Namespace) -> dict[str, Any]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(tree), os.environ.get("PYTHONPATH")) if p))
    cmd = [sys.executable, __file__, "--child", "--knots", str(args.knots), "--planes", str(args.planes),
           "--blocks", str(args.blocks), "--points", str(args.points), "--coalesce", str(args.coalesce),
           "--step-every", str(args.step_every)] + ([] if args.trace else ["--no-trace"]) + ([] if args.spill_rows is None else ["--spill-rows",
                                                                                       str(args.spill_rows)])
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, env=env, cwd=tree, check=False)
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith(_ROW)), None)
    if proc.returncode != 0 or line is None:
        raise RuntimeError(f"child in {tree} failed (exit {proc.returncode})")
    row: dict[str, Any] = json.loads(line[len(_ROW):])
    return row


def _print(name: str, r: dict[str, Any]) -> None:
    print(f"{name}: {r['knots']} knots, {r['blocks']} live blocks ({r['block_ids']} ids used), {r['points']} points"
          f" ({r.get('rows_spilled', 0)} rows spilled to disk)")
    if not r.get("traced", True):
        print(f"  per block: RSS growth {r['rss_per_block']:.0f} B, over the second half "
              f"{r['marginal_rss_per_block']:.0f} B per block added; walk {r['seconds']:.1f} s")
        return
    print(f"  per block: traced {r['traced_per_block']:.0f} B = rows {r['rows_per_block']:.0f} B + "
          f"bookkeeping {r['bookkeeping_per_block']:.0f} B; RSS growth {r['rss_per_block']:.0f} B; "
          f"walk {r['seconds']:.1f} s (tracemalloc on)")
    if "marginal_per_block" in r:
        print(f"  second half of the walk: traced {r['marginal_per_block']:.0f} B, RSS "
              f"{r.get('marginal_rss_per_block', float('nan')):.0f} B per block added")
    for t in r["top"]:
        print(f"    {t['bytes'] / 1e6:8.2f} MB  {t['site']}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--knots", type=int, default=1500)
    ap.add_argument("--planes", type=int, default=400, help="planes along the walk (default %(default)s)")
    ap.add_argument("--blocks", type=int, default=11, help="blocks per knot interval (default %(default)s)")
    ap.add_argument("--points", type=int, default=6, help="points per block (default %(default)s)")
    ap.add_argument("--coalesce", type=float, default=0.4,
                    help="share of blocks added twice (joined by coalescing; default %(default)s)")
    ap.add_argument("--step-every", type=int, default=5, help="window step every N knots (0: none)")
    ap.add_argument("--spill-rows", type=int, default=None,
                    help="held rows kept in memory before spilling (default: the code's)")
    ap.add_argument("--no-trace", dest="trace", action="store_false",
                    help="without tracemalloc (its own records inflate the RSS): RSS figures only")
    ap.add_argument("--baseline", default=None, metavar="REV", help="also run on git revision REV")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        row = walk(args.knots, args.planes, args.blocks, args.points, args.coalesce, args.step_every,
                   args.spill_rows, trace=args.trace)
        print(_ROW + json.dumps(row), flush=True)
        return 0
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_memory import export_revision

    with tempfile.TemporaryDirectory(prefix="bench_block_memory_") as tmp:
        trees = {"current": REPO}
        if args.baseline:
            trees[f"baseline {args.baseline}"] = export_revision(args.baseline, Path(tmp) / "baseline")
        for name, tree in trees.items():
            _print(name, _spawn(tree, args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
