"""SLAM benchmark on a simulated walk through the ``office`` world (issue 4's goals), or another
world (``--world``: ``small_room``, issue 26's doors and boards next to their walls).

Simulates the walk once (or reuses the bag in ``--cache``), runs SLAM with each segmenter of
``--segmenters`` (RoR first by default) on that same bag, each in a fresh child process so that
its peak memory (``ru_maxrss``) is its own, evaluates every run against the ground truth and
prints one markdown table: time per stage (``summary.json`` timings), total, ratio to real time,
CPU seconds per data second (every process of the run: estimator, reader, export), peak memory,
and the accuracy figures, with the goals marked reached or not. Before and after the runs it
times this machine's RoR segmentation on a fixed set of scanlines (``bench_segmentation.py``'s
synthetic office set, one thread) and prints it beside the speed, so that the figures can be
scaled to another machine.

Usage:
    .venv/bin/python scripts/bench_slam.py [--duration 600] [--cache DIR] [--out DIR]
        [--segmenters ror,split_and_merge,...] [--seed 1] [--markdown FILE] [--world office]
        [--start-rest 10]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

STAGES = ("segmentation", "frontend", "tracking", "association", "plane_creation", "backend", "batch", "export")
GOALS = {  # issue 4, office 10 min walk
    "ate": ("ATE RMSE (start-aligned)", 0.01, "m"),
    "ate_se3": ("ATE RMSE (SE(3)-aligned, the usual ATE)", 0.01, "m"),
    "cloud_median": ("cloud-to-mesh median", 0.005, "m"),
    "cloud_p95": ("cloud-to-mesh p95", 0.02, "m"),
    "cloud_median_se3": ("cloud-to-mesh median, SE(3)-aligned map", 0.005, "m"),
    "cloud_p95_se3": ("cloud-to-mesh p95, SE(3)-aligned map", 0.02, "m"),
    "plane_angle_max": ("plane angle error (max)", 0.1, "deg"),
    "plane_angle_max_wd": ("plane angle error (max), well-determined planes (reported sigma <= 0.05 deg)", 0.1, "deg"),
    "speed": (">= 2x real time", 2.0, "x"),
    "memory": ("peak memory < 4 GB", 4.0, "GB"),
}


def _cpu_seconds() -> float:
    """User + system CPU seconds of this process and of its children that have ended."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def machine_throughput(n_scans: int = 200, repeats: int = 5) -> float:
    """This machine's RoR (the default, combined) segmentation speed [scans/s] on ``n_scans`` of
    ``bench_segmentation.py``'s synthetic 1081-beam office scanlines (median of ``repeats``
    passes after a warm-up), measured in a child process with one numba/BLAS thread."""
    code = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import bench_segmentation as b; "
            f"print(b.time_method('ror', b.office_scans({n_scans}), {repeats}))")
    env = {**os.environ, **{v: "1" for v in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                              "MKL_NUM_THREADS")}}
    out = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True).stdout
    return float(out.strip().splitlines()[-1])


def _cli_env() -> dict[str, str]:
    """The environment a run gets from the command line (``backpack_slam``): numpy's BLAS and
    OpenMP with one thread unless the caller chose otherwise, so that the benchmark measures
    the run users get (BLAS threads spinning beside the reader and export processes on a
    2-core machine)."""
    return {**os.environ, **{v: os.environ.get(v, "1") for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}}


def _child(bag: str, gt: str, method: str, out: str, config: str = "") -> None:
    """One SLAM run + evaluation in this process; prints one JSON line with the figures."""
    from common.rig import resolve_rig
    from slam.config import SlamConfig, load_slam_config
    from slam.evaluate import Stats, evaluate
    from slam.run import peak_rss_gb, run_slam

    base = load_slam_config(config) if config else SlamConfig()
    cfg = base if base.segmenter.method == method else base.model_copy(
        update={"segmenter": SlamConfig.model_validate({"segmenter": {"method": method}}).segmenter})
    cpu0 = _cpu_seconds()
    summary = run_slam(bag, resolve_rig("itc_backpack"), cfg, out, progress=True)
    cpu = _cpu_seconds() - cpu0  # the run's reader and export processes have been waited for
    peak_run = peak_rss_gb() * 1e9  # before the evaluation
    res = evaluate(out, gt)
    peak = peak_rss_gb() * 1e9  # SLAM and evaluation in this one process
    tr = res.trajectory
    row: dict[str, Any] = {
        "method": method,
        "timings": summary["timings"],
        "data_duration": summary["data_duration"],
        "realtime_factor": summary["realtime_factor"],
        "cpu_seconds": cpu,
        "peak_bytes": peak,
        "peak_run_bytes": peak_run,
        **pace_figures(summary.get("pace") or []),
        "counts": summary["counts"],
        "path_length": tr.path_length,
        "ate": tr.ate["start_aligned"].rmse,
        "ate_se3": tr.ate["se3_aligned"].rmse,
        "rpe_1m": tr.rpe_1m.mean if tr.rpe_1m else float("nan"),
        "rpe_10m": tr.rpe_10m.mean if tr.rpe_10m else float("nan"),
        "drift_endpoint": tr.drift_endpoint_per_100m,
        "drift_rpe": tr.drift_rpe_per_100m,
        "drift_rot": tr.rot_drift_deg_per_100m,
    }
    if res.cloud is not None:
        d = Stats.of(res.cloud.distances)
        row |= {"cloud_median": d.median, "cloud_p95": d.p95}
    if res.planes is not None:
        a = res.planes.angle
        wd = res.planes.well_determined()
        row |= {"plane_angle_max_wd": max((m.angle_deg for m in wd), default=float("nan")), "planes_wd": len(wd),
                "plane_angle_over_sigma_median": res.planes.normalized_angle.median}
        row |= {"plane_angle_median": a.median, "plane_angle_p95": a.p95, "plane_angle_max": a.max,
                "plane_offset_median": res.planes.offset.median, "planes_matched": len(res.planes.matches)}
    # the map again after the trajectory's SE(3) alignment (the usual registration before comparing a
    # mobile-mapping cloud with a reference): the start alignment also carries the first pose's
    # attitude error, 0.02-0.03 deg, over the building's 60 m
    reg = evaluate(out, gt, map_alignment="se3")
    if reg.cloud is not None:
        d = Stats.of(reg.cloud.distances)
        row |= {"cloud_median_se3": d.median, "cloud_p95_se3": d.p95}
    if reg.planes is not None:
        row |= {"plane_angle_p95_se3": reg.planes.angle.p95, "plane_angle_max_se3": reg.planes.angle.max}
    if res.association is not None:
        a = res.association
        row |= {"assoc_associated": a.fraction_associated,
                "assoc_correct_of_associated": a.fraction_correct_of_associated,
                "assoc_correct_surface": a.fraction_correct_surface_of_associated,
                "assoc_by_kind": {k: (c / n if n else None) for k, (n, c) in a.by_kind.items()},
                "confusions": a.confusions_wall_to_child + a.confusions_child_to_wall,
                "confusion_fraction": a.confusion_fraction if a.n_child_associated else None,
                "confusions_pure": a.confusions_pure,
                "confusion_fraction_pure": a.confusion_fraction_pure if a.n_child_associated_pure else None}
    row |= {"ate_max": tr.ate["start_aligned"].max, "trimmed_points": summary["counts"].get("trimmed_points"),
            "cloud_points": summary["counts"].get("cloud_points")}
    if reg.planes is not None:
        ext = [m.extent_error_m for m in reg.planes.matches if m.extent_error_m == m.extent_error_m]
        excess = [m.extent_excess_m for m in reg.planes.matches if m.extent_excess_m == m.extent_excess_m]
        row |= {"extent_error_max": max(ext, default=None), "extent_excess_max": max(excess, default=None),
                "extent_planes": len(ext)}
    print("BENCH_ROW " + json.dumps(row))


def _bag(cache: Path, duration: float, seed: int, world: str = "office", start_rest: float = 10.0) -> tuple[Path, Path]:
    from simulation.run import SimulationConfig, gt_dir_for, simulate

    cache.mkdir(parents=True, exist_ok=True)
    bag = cache / f"{world}_adis_rest{start_rest:g}_{duration:g}s_seed{seed}.bag"
    gt = gt_dir_for(bag)
    if bag.is_file() and (gt / "meta.json").is_file():
        print(f"reusing {bag}", flush=True)
        return bag, gt
    print(f"simulating {duration:g} s in the {world} world -> {bag}", flush=True)
    # the survey starts with the operator standing still for 10 s, as IMU-aided mobile mapping does: the
    # zero-velocity updates then fix the accelerometer bias that carries the estimate along corridors
    # whose ends are out of range (1 s of standing: ATE 429 mm on the first minute; 10 s: 17 mm)
    cfg = SimulationConfig.model_validate({"gait": {"start_rest": start_rest}})
    sim = simulate(world, "itc_backpack", duration=duration, seed=seed, out=bag, fmt="ros1", imu=True,
                   config=cfg, progress=True)
    print(f"  {sim.n_rays / 1e6:.1f} M rays in {sim.wall_time:.1f} s", flush=True)
    return sim.bag, sim.gt


def pace_figures(pace: list[list[float]]) -> dict[str, float]:
    """CPU and wall seconds per data second over the first and the last sixth of the walk's
    estimation (summary.json ``pace``: rows of data s, wall s, CPU s), to show whether the cost
    per data second stays constant as the walk grows."""
    if len(pace) < 12:
        return {}
    arr = np.asarray(pace, dtype=np.float64)
    k = len(arr) // 6

    def rate(a: int, b: int, col: int) -> float:
        return float((arr[b, col] - arr[a, col]) / (arr[b, 0] - arr[a, 0]))

    n = len(arr) - 1
    return {"pace_cpu_first": rate(0, k, 2), "pace_cpu_last": rate(n - k, n, 2),
            "pace_wall_first": rate(0, k, 1), "pace_wall_last": rate(n - k, n, 1)}


def plot_pace(pace: list[list[float]], path: Path, title: str) -> None:
    """CPU and wall seconds per data second in 60 s windows of data over the walk."""
    if len(pace) < 7:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arr = np.asarray(pace, dtype=np.float64)
    step = max(1, round(60.0 / max(arr[1, 0] - arr[0, 0], 1e-9)))
    a, b = arr[:-step:step], arr[step::step]
    mid = 0.5 * (a[:, 0] + b[:, 0]) / 60.0
    fig, ax = plt.subplots(figsize=(8, 3.6))
    ax.plot(mid, (b[:, 2] - a[:, 2]) / (b[:, 0] - a[:, 0]), label="CPU s per data s (all processes)")
    ax.plot(mid, (b[:, 1] - a[:, 1]) / (b[:, 0] - a[:, 0]), label="wall s per data s")
    ax.set_xlabel("data time (min)")
    ax.set_ylabel("s per data s (60 s windows)")
    ax.set_ylim(0, None)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    tmp = path.with_name(path.name + ".part.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)


def _fmt(v: Any, scale: float = 1.0, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and v != v):
        return "-"
    return f"{v * scale:.{digits}f}"


def table(rows: list[dict[str, Any]], duration: float) -> str:
    """The markdown table: one column per segmenter."""
    head = "| | " + " | ".join(r["method"] for r in rows) + " |"
    sep = "|---|" + "---:|" * len(rows)
    lines = [head, sep]

    def add(name: str, vals: list[str]) -> None:
        lines.append(f"| {name} | " + " | ".join(vals) + " |")

    for st in STAGES:
        where = " (reader process)" if st in ("segmentation", "frontend") else ""
        add(f"time: {st} (s){where}", [_fmt(r["timings"].get(st), 1, 1) for r in rows])
    add("**time: total wall (s)**", [_fmt(r["timings"]["wall"], 1, 1) for r in rows])
    add("data duration (s)", [_fmt(r["data_duration"], 1, 1) for r in rows])
    add("**speed (x real time)**", [_fmt(r["realtime_factor"]) for r in rows])
    add("CPU seconds per data second (all processes of the run)",
        [_fmt(r["cpu_seconds"] / r["data_duration"], 1, 3) if "cpu_seconds" in r else "-" for r in rows])
    add("**peak memory (GB)**: all processes (summed PSS)", [_fmt(r.get("peak_pss_bytes"), 1e-9) for r in rows])
    add("peak memory (GB): the estimator's process (ru_maxrss)", [_fmt(r["peak_bytes"], 1e-9) for r in rows])
    add("peak memory (GB): the estimator's process before the evaluation (ru_maxrss)",
        [_fmt(r.get("peak_run_bytes"), 1e-9) for r in rows])
    add("CPU s per data s while estimating: first / last sixth of the walk",
        [f"{_fmt(r.get('pace_cpu_first'), 1, 3)} / {_fmt(r.get('pace_cpu_last'), 1, 3)}" for r in rows])
    add("wall s per data s while estimating: first / last sixth of the walk",
        [f"{_fmt(r.get('pace_wall_first'), 1, 3)} / {_fmt(r.get('pace_wall_last'), 1, 3)}" for r in rows])
    add("knots / planes / merged", [f"{r['counts']['knots']} / {r['counts']['planes']} / {r['counts']['planes_merged']}" for r in rows])
    add("path length (m)", [_fmt(r["path_length"], 1, 1) for r in rows])
    add("**ATE RMSE start-aligned (mm)**", [_fmt(r["ate"], 1e3) for r in rows])
    add("ATE RMSE SE(3)-aligned (mm)", [_fmt(r["ate_se3"], 1e3) for r in rows])
    add("RPE 1 m, mean (mm)", [_fmt(r["rpe_1m"], 1e3) for r in rows])
    add("RPE 10 m, mean (mm)", [_fmt(r["rpe_10m"], 1e3) for r in rows])
    add("drift per 100 m: endpoint (%)", [_fmt(r["drift_endpoint"], 1, 4) for r in rows])
    add("drift per 100 m: RPE (%)", [_fmt(r["drift_rpe"], 1, 4) for r in rows])
    add("rotation drift (deg / 100 m)", [_fmt(r["drift_rot"], 1, 4) for r in rows])
    add("**cloud-to-mesh median (mm)**", [_fmt(r.get("cloud_median"), 1e3) for r in rows])
    add("**cloud-to-mesh p95 (mm)**", [_fmt(r.get("cloud_p95"), 1e3) for r in rows])
    add("plane angle median (deg)", [_fmt(r.get("plane_angle_median"), 1, 4) for r in rows])
    add("plane angle p95 (deg)", [_fmt(r.get("plane_angle_p95"), 1, 4) for r in rows])
    add("**plane angle max (deg)**", [_fmt(r.get("plane_angle_max"), 1, 4) for r in rows])
    add("plane angle max, well-determined planes (deg) / their number",
        [f"{_fmt(r.get('plane_angle_max_wd'), 1, 4)} / {r.get('planes_wd', '-')}" for r in rows])
    add("plane angle / reported sigma, median", [_fmt(r.get("plane_angle_over_sigma_median"), 1, 2) for r in rows])
    add("cloud-to-mesh median / p95, SE(3)-aligned map (mm)",
        [f"{_fmt(r.get('cloud_median_se3'), 1e3)} / {_fmt(r.get('cloud_p95_se3'), 1e3)}" for r in rows])
    add("plane angle p95 / max, SE(3)-aligned map (deg)",
        [f"{_fmt(r.get('plane_angle_p95_se3'), 1, 4)} / {_fmt(r.get('plane_angle_max_se3'), 1, 4)}" for r in rows])
    add("plane offset median (mm)", [_fmt(r.get("plane_offset_median"), 1e3) for r in rows])
    add("segments associated (%)", [_fmt(r.get("assoc_associated"), 100, 1) for r in rows])
    add("association correct of associated (%)", [_fmt(r.get("assoc_correct_of_associated"), 100, 2) for r in rows])
    add("association correct of associated, coplanar true planes as one surface (%)",
        [_fmt(r.get("assoc_correct_surface"), 100, 2) for r in rows])
    for kind in ("wall", "floor/ceiling", "door", "board", "other"):
        add(f"association correct, {kind} segments (%)",
            [_fmt((r.get("assoc_by_kind") or {}).get(kind), 100, 2) for r in rows])
    add("wall<->door/board confusions (segments / % of door and board segments)",
        [f"{r.get('confusions', '-')} / {_fmt(r.get('confusion_fraction'), 100, 2)}" for r in rows])
    add("the same among single-surface segments (purity >= 0.9; segments / %)",
        [f"{r.get('confusions_pure', '-')} / {_fmt(r.get('confusion_fraction_pure'), 100, 2)}" for r in rows])
    add("door/board extent error, max (mm) / excess, max (mm) / planes",
        [f"{_fmt(r.get('extent_error_max'), 1e3, 0)} / {_fmt(r.get('extent_excess_max'), 1e3, 0)} / "
         f"{r.get('extent_planes', '-')}" for r in rows])
    add("largest position error, start-aligned (mm)", [_fmt(r.get("ate_max"), 1e3) for r in rows])
    add("points detached by the final trim / cloud points",
        [f"{r.get('trimmed_points', '-')} / {r.get('cloud_points', '-')}" for r in rows])
    return "\n".join(lines)


def goals(rows: list[dict[str, Any]]) -> str:
    """Which of issue 4's goals each run reaches."""
    lines = ["| goal | " + " | ".join(r["method"] for r in rows) + " |", "|---|" + "---|" * len(rows)]
    for key, (name, limit, _unit) in GOALS.items():
        vals = []
        for r in rows:
            if key == "speed":
                v, ok = r["realtime_factor"], r["realtime_factor"] >= limit
                vals.append(f"{'reached' if ok else 'NOT reached'} ({v:.2f}x)")
                continue
            if key == "memory":
                v = max(r["peak_bytes"], r.get("peak_pss_bytes", 0.0)) * 1e-9
                vals.append(f"{'reached' if v < limit else 'NOT reached'} ({v:.2f} GB)")
                continue
            v = r.get(key)
            if v is None:
                vals.append("-")
                continue
            scale = 1e3 if _unit == "m" else 1.0
            shown = f"{v * scale:.2f} {'mm' if _unit == 'm' else _unit}"
            vals.append(f"{'reached' if v < limit else 'NOT reached'} ({shown})")
        lines.append(f"| {name} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


class PssSampler:
    """The peak, over time, of the summed proportional set size (PSS: shared pages split among
    their users, so a forked process's copy-on-write pages are not counted twice) of a process
    and all its descendants (the SLAM's reader and export processes), sampled every ``period`` s
    in a thread."""

    def __init__(self, pid: int, period: float = 0.5) -> None:
        import threading

        self.pid, self.period, self.peak = pid, period, 0.0
        self.series: list[tuple[float, float, float]] = []  # (s since start, PSS of all, PSS of the root process)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        import psutil

        try:
            root = psutil.Process(self.pid)
        except psutil.Error:
            return
        t0 = time.perf_counter()
        while not self._stop.is_set():
            total = own = 0.0
            try:
                procs = [root, *root.children(recursive=True)]
            except psutil.Error:
                break
            for p in procs:
                try:
                    pss = p.memory_full_info().pss
                except psutil.Error:
                    continue
                total += pss
                if p.pid == root.pid:
                    own = pss
            self.peak = max(self.peak, total)
            self.series.append((time.perf_counter() - t0, total, own))
            self._stop.wait(self.period)

    def write(self, run_dir: Path, timings: dict[str, float]) -> None:
        """``memory_series.tsv`` (time, PSS of all processes and of the estimator) and
        ``memory_over_time.png`` in ``run_dir``, the final batch and the export shaded (their
        starts from the run's stage times, counted back from its end)."""
        if not self.series or not run_dir.is_dir():
            return
        import numpy as np

        arr = np.array(self.series)
        tmp = run_dir / "memory_series.tsv.part"
        np.savetxt(tmp, arr * [1.0, 1e-9, 1e-9], fmt="%.3f", delimiter="\t",
                   header="seconds\tpss_all_gb\tpss_estimator_gb")
        tmp.replace(run_dir / "memory_series.tsv")
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(8, 3.8))
        ax.plot(arr[:, 0], arr[:, 1] * 1e-9, label="all processes (PSS)")
        ax.plot(arr[:, 0], arr[:, 2] * 1e-9, label="estimator process (PSS)")
        wall = float(timings.get("wall", arr[-1, 0]))
        t_export = wall - float(timings.get("export", 0.0))
        t_batch = t_export - float(timings.get("batch", 0.0))
        ax.axvspan(t_batch, t_export, color="tab:orange", alpha=0.15, label="final batch and trim")
        ax.axvspan(t_export, wall, color="tab:green", alpha=0.15, label="export (cloud, recording)")
        ax.set_xlabel("wall time of the run (s; evaluation after the last shaded span)")
        ax.set_ylabel("memory (GB)")
        ax.set_ylim(0, None)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
        ax.set_title(f"peak {arr[:, 1].max() * 1e-9:.2f} GB")
        fig.tight_layout()
        fig.savefig(run_dir / "memory_over_time.png.part.png", dpi=110)
        plt.close(fig)
        (run_dir / "memory_over_time.png.part.png").replace(run_dir / "memory_over_time.png")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=600.0, help="seconds of walking (default 600)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--world", default="office", help="world to walk through (default office; small_room: issue 26)")
    ap.add_argument("--start-rest", type=float, default=10.0, help="s standing still before walking (default 10)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/bench_slam_cache"), help="folder of cached bags")
    ap.add_argument("--out", type=Path, default=None, help="run folders (default: <cache>/runs_<duration>s)")
    ap.add_argument("--segmenters", default="ror", help="comma-separated segmenter names (default: ror)")
    ap.add_argument("--markdown", type=Path, default=None, help="also write the tables to this file")
    ap.add_argument("--config", type=Path, default=None,
                    help="SLAM config YAML (default: the built-in defaults); the segmenter is set per run")
    ap.add_argument("--child", nargs=5, metavar=("BAG", "GT", "METHOD", "OUT", "CONFIG"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        _child(*args.child)
        return 0
    if not args.duration > 0:
        ap.error(f"--duration {args.duration}: must be > 0")
    import segmentation

    methods = [m.strip() for m in args.segmenters.split(",") if m.strip()]
    unknown = [m for m in methods if m not in segmentation.available()]
    if unknown:
        ap.error(f"--segmenters: unknown {', '.join(unknown)} (available: {', '.join(segmentation.available())})")
    bag, gt = _bag(args.cache, args.duration, args.seed, args.world, args.start_rest)
    out = args.out or args.cache / f"runs_{args.duration:g}s_seed{args.seed}"
    throughput = [machine_throughput()]
    load = [os.getloadavg()[0]]
    rows = []
    for m in methods:
        print(f"SLAM with {m} ...", flush=True)
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            [sys.executable, __file__, "--child", str(bag), str(gt), m, str(out / m), str(args.config or "")],
            stdout=subprocess.PIPE, text=True, env=_cli_env(),
        )
        sampler = PssSampler(proc.pid)
        sampler.start()
        stdout, _ = proc.communicate()
        sampler.stop()
        line = next((ln for ln in stdout.splitlines() if ln.startswith("BENCH_ROW ")), None)
        if proc.returncode != 0 or line is None:
            print(f"  {m}: failed (exit {proc.returncode})", file=sys.stderr)
            continue
        rows.append(json.loads(line[len("BENCH_ROW "):]) | {"peak_pss_bytes": sampler.peak})
        try:
            summary = json.loads((out / m / "summary.json").read_text())
        except (OSError, ValueError):
            summary = {}
        sampler.write(out / m, summary.get("timings", {}))
        plot_pace(summary.get("pace") or [], out / m / "pace_over_time.png",
                  f"{args.world} {args.duration:g} s walk, seed {args.seed}, {m}")
        print(f"  memory over time: {out / m / 'memory_over_time.png'}; pace: {out / m / 'pace_over_time.png'}",
              flush=True)
        print(f"  done in {time.perf_counter() - t0:.0f} s (incl. evaluation)", flush=True)
    if not rows:
        return 1
    throughput.append(machine_throughput())
    load.append(os.getloadavg()[0])
    text = (
        f"{args.world} world, {args.duration:g} s walk (seed {args.seed}), bag {bag}\n\n"
        f"This machine: RoR segments {throughput[0]:,.0f} / {throughput[1]:,.0f} scans/s before / after "
        f"the runs (scripts/bench_segmentation.py's 200 synthetic 1081-beam office scanlines, one thread; "
        f"1-minute load average {load[0]:.1f} / {load[1]:.1f}, {os.cpu_count()} CPUs)\n\n"
        + table(rows, args.duration) + "\n\nGoals (issue 4):\n\n" + goals(rows) + "\n"
    )
    print(text)
    if args.markdown:
        args.markdown.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
