"""Back-end benchmarks, measured in one run.

1. Linearisation cost per point of the batched point-on-plane factor against one CustomFactor
   per point (same points, same values), for several block sizes: table and ratio.
2. iSAM2 update time against the number of knots on the synthetic box room (tests/box_scene.py),
   reading scan by scan as the pipeline will.
3. Whitened constant-velocity residuals of the walking-tuned motion prior on the box-room walk.
4. With ``--log``: a SLAM run's back-end calls (recorded by ``--record BAG``, see
   ``scripts/backend_log.py``) replayed on this tree's back end and, with ``--baseline REV``, on
   git revision REV's, each in a fresh process: CPU seconds per stage and per data second,
   before/after ratios, and how far the two estimates are apart.

Usage: .venv/bin/python scripts/bench_backend.py [--repeat N] [--duration S]
       .venv/bin/python scripts/bench_backend.py --record BAG --log FILE   # once per bag
       .venv/bin/python scripts/bench_backend.py --log FILE [--baseline REV] [--profile FILE] [--only-replay]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import P, X

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from backend_defaults import backend_defaults
from box_scene import make_scene, walking_knots

from slam.backend import Backend
from slam.backend.factors import point_plane_factor
from slam.motion import constant_velocity_terms

ROOT = Path(__file__).resolve().parents[1]


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


def _export_tree(rev: str) -> Path:
    """Git revision ``rev`` of this repository as a folder (kept between runs, so that its numba
    cache is too)."""
    sha = subprocess.run(["git", "rev-parse", "--short", rev], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout.strip()
    out = Path(tempfile.gettempdir()) / f"bench_backend_tree_{sha}"
    if not (out / "slam").is_dir():
        out.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "archive", sha], cwd=ROOT, check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(out)], input=archive, check=True)
    return out


def _replay_child(tree: str, log: str, npz: str, profile: str, overrides: str) -> None:
    """One replay with the back end of ``tree`` (first on sys.path) and the recorded configuration
    with ``overrides`` (a JSON object of ``BackendConfig`` fields) applied; prints one JSON line."""
    sys.path.insert(0, tree)
    sys.path.insert(0, str(ROOT / "scripts"))
    import backend_log

    data = backend_log.load(Path(log))
    if overrides:
        data["config"] = replace(data["config"], **json.loads(overrides))
    backend_log.warm_up(data)
    r = backend_log.replay(data, Path(profile) if profile else None)
    np.savez(npz, poses=r["poses"], plane_ids=r["plane_ids"], normals=r["normals"], offsets=r["offsets"])
    print("REPLAY " + json.dumps({k: r[k] for k in ("seconds", "counts", "mismatches", "data_duration")}))


def _run_replay(tree: Path, log: Path, npz: Path, profile: Path | None, overrides: dict[str, Any] | None = None) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, __file__, "--replay-child", str(tree), str(log), str(npz), str(profile or ""),
           json.dumps(overrides) if overrides else ""]
    out = subprocess.run(cmd, cwd=tree, env=env, check=True, capture_output=True, text=True).stdout
    line = next(ln for ln in out.splitlines() if ln.startswith("REPLAY "))
    return dict(json.loads(line[len("REPLAY "):]))


def _estimate_difference(a: Path, b: Path) -> str:
    """Largest pose and plane differences between two replays' estimates."""
    A, B = np.load(a), np.load(b)
    if A["poses"].shape != B["poses"].shape or not np.array_equal(A["plane_ids"], B["plane_ids"]):
        return "estimates: different knots or planes"
    dt = np.linalg.norm(A["poses"][:, :3, 3] - B["poses"][:, :3, 3], axis=1).max()
    R = np.einsum("kji,kjl->kil", A["poses"][:, :3, :3], B["poses"][:, :3, :3])
    ang = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))).max()
    pa = np.degrees(np.arccos(np.clip(np.sum(A["normals"] * B["normals"], axis=1), -1.0, 1.0))).max()
    po = np.abs(A["offsets"] - B["offsets"]).max()
    same = all(np.array_equal(A[k], B[k]) for k in ("poses", "normals", "offsets"))
    return (f"estimates {'bit for bit identical' if same else 'differ'}: poses max {dt * 1e3:.4f} mm, "
            f"{ang:.5f} deg; planes max {pa:.5f} deg, {po * 1e3:.4f} mm")


def _ate(log: Path, gt: Path, npz: Path) -> str:
    """ATE RMSE (start- and SE(3)-aligned) of a replay's knots against the ground truth."""
    from backend_log import load

    from slam.evaluate import load_ground_truth, trajectory_errors

    t = np.array([c[1][0] for c in load(log)["calls"] if c[0] == "add_pose"], dtype=float)
    truth = load_ground_truth(gt)
    ev = trajectory_errors(t, np.load(npz)["poses"], truth.times, truth.T_world_body)
    return f"ATE start-aligned {ev.ate['start_aligned'].rmse * 1e3:.4f} mm, SE(3)-aligned {ev.ate['se3_aligned'].rmse * 1e3:.4f} mm"


def parse_variant(text: str) -> tuple[str, dict[str, Any]]:
    """``NAME:key=value;key=value`` (values as JSON, else strings) -> (NAME, overrides)."""
    name, _, body = text.partition(":")
    if not name or not body:
        raise ValueError(f"--variant {text!r}: expected NAME:key=value[;key=value...]")
    out: dict[str, Any] = {}
    for item in body.split(";"):
        key, eq, value = item.partition("=")
        if not eq or not key:
            raise ValueError(f"--variant {text!r}: {item!r} is not key=value")
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[key.strip()] = value
    return name, out


def bench_replay(log: Path, baseline: str | None, profile: Path | None, isam2: bool, gt: Path | None = None,
                 variants: Sequence[tuple[str, dict[str, Any]]] = ()) -> None:
    from backend_log import ORDER

    tmp = Path(tempfile.mkdtemp(prefix="bench_backend_"))
    runs: list[tuple[str, dict]] = []
    if baseline:
        runs.append((f"baseline {baseline}", _run_replay(_export_tree(baseline), log, tmp / "base.npz", None)))
    runs.append(("this tree", _run_replay(ROOT, log, tmp / "now.npz", None)))
    if isam2:
        runs.append(("this tree, iSAM2", _run_replay(ROOT, log, tmp / "isam2.npz", None, {"solver": "isam2"})))
    for i, (vname, over) in enumerate(variants):
        runs.append((vname, _run_replay(ROOT, log, tmp / f"variant{i}.npz", None, over)))
    dur = runs[-1][1]["data_duration"]
    print(f"\n4. back end replayed from {log.name} ({dur:.1f} s of data): CPU seconds (time.process_time)")
    head = f"{'stage':<26} {'calls':>7}" + "".join(f" {name + ' s':>20} {'s/data s':>9}" for name, _ in runs)
    if baseline:
        head += f" {'ratio':>7}"
    print(head)
    for stage in (*ORDER, "total"):
        def sec(r: dict, stage: str = stage) -> float:
            return float(sum(r["seconds"].values())) if stage == "total" else float(r["seconds"][stage])
        calls = sum(runs[-1][1]["counts"].values()) if stage == "total" else runs[-1][1]["counts"][stage]
        line = f"{stage:<26} {calls:>7d}" + "".join(f" {sec(r):>20.2f} {sec(r) / dur:>9.4f}" for _, r in runs)
        if baseline:
            now = runs[1][1]
            line += f" {sec(runs[0][1]) / max(sec(now), 1e-9):>7.2f}"
        print(line)
    for name, r in runs:
        if r["mismatches"]:
            print(f"{name}: {r['mismatches']} results differ from the recording's (block ids, knots)")
    if baseline:
        print("this tree vs baseline: " + _estimate_difference(tmp / "base.npz", tmp / "now.npz"))
    if isam2:
        print("iSAM2 vs window: " + _estimate_difference(tmp / "now.npz", tmp / "isam2.npz"))
    for i, (vname, over) in enumerate(variants):
        print(f"{vname} {over} vs this tree: " + _estimate_difference(tmp / "now.npz", tmp / f"variant{i}.npz"))
    if gt is not None:
        files = [*(["base.npz"] if baseline else []), "now.npz", *(["isam2.npz"] if isam2 else []),
                 *(f"variant{i}.npz" for i in range(len(variants)))]
        for (name, _), f in zip(runs, files, strict=True):
            print(f"{name}: {_ate(log, gt, tmp / f)} (the knots; the front end's decisions are the recording's)")
    if profile is not None:  # a run of its own: cProfile more than doubles the time it measures
        _run_replay(ROOT, log, tmp / "profiled.npz", profile)
        print(f"cProfile stats of this tree's replay (CPU time): {profile}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--duration", type=float, default=4.0, help="box-room walk [s] (<= 4)")
    ap.add_argument("--record", type=Path, default=None, help="run SLAM on this bag and write its back-end calls to --log")
    ap.add_argument("--log", type=Path, default=None, help="a back-end call log to replay (4.)")
    ap.add_argument("--baseline", default=None, help="git revision whose back end the replay is compared with")
    ap.add_argument("--profile", type=Path, default=None, help="write cProfile stats of this tree's replay here")
    ap.add_argument("--isam2", action="store_true", help="also replay with the iSAM2 incremental solver")
    ap.add_argument("--only-replay", action="store_true", help="skip benchmarks 1-3")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE[;...]",
                    help="also replay this tree with these BackendConfig fields changed (repeatable), "
                         "e.g. 'it3:window_iterations=3'")
    ap.add_argument("--gt", type=Path, default=None, help="the bag's ground-truth folder: ATE of each replay")
    ap.add_argument("--replay-child", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.replay_child:
        _replay_child(*args.replay_child)
        return
    if not 0.5 <= args.duration <= 4.0:
        ap.error("--duration: must be in [0.5, 4] s (the walk leaves the box room after that)")
    if args.record is not None:
        if args.log is None:
            ap.error("--record needs --log")
        sys.path.insert(0, str(ROOT / "scripts"))
        from backend_log import record

        summary = record(args.record, args.log, Path(tempfile.mkdtemp(prefix="bench_backend_run_")) / "slam")
        print(f"recorded {args.log} ({summary['data_duration']:.1f} s of data)")
        return
    if not args.only_replay:
        bench_factor(args.repeat)
        bench_isam(args.duration)
        bench_motion_prior(args.duration)
    if args.log is not None:
        sys.path.insert(0, str(ROOT / "scripts"))
        try:
            variants = [parse_variant(v) for v in args.variant]
        except ValueError as e:
            ap.error(str(e))
        bench_replay(args.log, args.baseline, args.profile, args.isam2, args.gt, variants)


if __name__ == "__main__":
    main()
