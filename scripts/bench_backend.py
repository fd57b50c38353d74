"""Back-end benchmarks, measured in one run.

1. Linearisation cost per point of the batched point-on-plane factor against one CustomFactor
   per point (same points, same values), for several block sizes: table and ratio.
2. iSAM2 update time against the number of knots on the synthetic box room (tests/box_scene.py),
   reading scan by scan as the pipeline will.
3. Whitened constant-velocity residuals of the walking-tuned motion prior on the box-room walk.

Usage: .venv/bin/python scripts/bench_backend.py [--repeat N] [--duration S]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import gtsam
import numpy as np
from gtsam.symbol_shorthand import P, X

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from backend_defaults import backend_defaults
from box_scene import make_scene, walking_knots

from slam.backend import Backend
from slam.backend.factors import point_plane_factor
from slam.motion import constant_velocity_terms


def _linearize_seconds(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, repeat: int) -> float:
    graph.linearize(values)  # warm-up
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        graph.linearize(values)
        best = min(best, time.perf_counter() - t0)
    return float(best)


def bench_factor(repeat: int) -> None:
    rng = np.random.default_rng(0)
    kernel = backend_defaults().kernel  # the SLAM configuration's
    Ta = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3))
    values = gtsam.Values()
    values.insert(X(0), Ta)
    values.insert(X(1), Ta.compose(gtsam.Pose3.Expmap(rng.normal(size=6) * 0.02)))
    values.insert(P(0), gtsam.OrientedPlane3(gtsam.Unit3(rng.normal(size=3)), 1.0))
    print("1. linearisation cost per point (best of", repeat, "runs)")
    print(f"{'points/block':>12} {'batched us/pt':>14} {'per-point us/pt':>16} {'ratio':>7} "
          f"{'batched us/block':>17}")
    total = 4000
    for n in (10, 30, 100, 300, 1000):
        blocks = total // n
        pts = rng.normal(size=(blocks * n, 3)) * 3.0
        al = rng.uniform(0.0, 1.0, blocks * n)
        batched = gtsam.NonlinearFactorGraph()
        for b in range(blocks):
            s = slice(b * n, (b + 1) * n)
            batched.add(point_plane_factor(X(0), X(1), P(0), pts[s], al[s], 0.003, kernel))
        single = gtsam.NonlinearFactorGraph()
        for k in range(min(blocks * n, 1000)):
            single.add(point_plane_factor(X(0), X(1), P(0), pts[k:k + 1], al[k:k + 1], 0.003, kernel))
        tb = _linearize_seconds(batched, values, repeat) / (blocks * n) * 1e6
        ts = _linearize_seconds(single, values, repeat) / single.size() * 1e6
        print(f"{n:>12d} {tb:>14.3f} {ts:>16.2f} {ts / tb:>7.1f} {tb * n:>17.1f}")


def bench_isam(duration: float) -> None:
    scene = make_scene(duration=duration, beams=181, sigma_range=0.003, seed=1)
    by_knot: dict[int, list[dict]] = {}
    for b in scene.blocks:
        by_knot.setdefault(b["knot"], []).append(b)
    rng = np.random.default_rng(2)
    be = Backend(replace(backend_defaults(), solver="isam2"))
    for j, p in enumerate(scene.planes):
        be.add_plane(j, p[:3] + rng.normal(0, 0.01, 3), p[3] + rng.normal(0, 0.02))
    print(f"\n2. iSAM2 update per knot (box room, 3 scanners x 181 beams, "
          f"{scene.n_points / (scene.knot_times.size - 1):.0f} points per knot)")
    print(f"{'knots':>6} {'update ms':>10} {'blocks':>7}")
    report = {10, 20, 40, 80, 120, 160, 200, 240}
    times = []
    for i, t in enumerate(scene.knot_times):
        be.add_pose(t, scene.knot_poses[0] if i == 0 else be.predict_pose(t))
        for b in by_knot.get(i - 1, []):
            be.add_observations(b["knot"], b["plane"], b["points_body"], b["alphas"], b["sigmas"])
        if i >= 8:
            t0 = time.perf_counter()
            be.step()
            times.append(time.perf_counter() - t0)
            if i in report:
                print(f"{i:>6d} {1e3 * np.mean(times[-5:]):>10.1f} {len(be.blocks.blocks):>7d}")
    t0 = time.perf_counter()
    s = be.batch_optimize(graduated=False)
    print(f"final LM over {be.num_knots} knots: {s.iterations} iterations, "
          f"{time.perf_counter() - t0:.2f} s; real time {duration:.1f} s")


def bench_motion_prior(duration: float) -> None:
    kt, poses = walking_knots(duration)
    cfg = backend_defaults().motion  # the SLAM configuration's
    r = []
    for i in range(1, kt.size - 1):
        res, *_ = constant_velocity_terms(*(gtsam.Pose3(poses[k]) for k in (i - 1, i, i + 1)),
                                          kt[i] - kt[i - 1], kt[i + 1] - kt[i])
        r.append(res / cfg.sigmas(kt[i] - kt[i - 1], kt[i + 1] - kt[i]))
    rr = np.abs(np.array(r))
    print("\n3. constant-velocity prior on the walk: whitened |residual| rotation / translation")
    print(f"   RMS {np.sqrt(np.mean(rr[:, :3] ** 2)):.3f} / {np.sqrt(np.mean(rr[:, 3:] ** 2)):.3f}, "
          f"max {rr[:, :3].max():.3f} / {rr[:, 3:].max():.3f} (a loose prior: < 1)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--duration", type=float, default=4.0, help="box-room walk [s] (<= 4)")
    args = ap.parse_args()
    if not 0.5 <= args.duration <= 4.0:
        ap.error("--duration: must be in [0.5, 4] s (the walk leaves the box room after that)")
    bench_factor(args.repeat)
    bench_isam(args.duration)
    bench_motion_prior(args.duration)


if __name__ == "__main__":
    main()
