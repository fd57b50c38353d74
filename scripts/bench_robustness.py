"""Robustness benchmark (issue 21): SLAM on recordings as they come, one table.

Each condition is a simulated walk through ``--world`` (``demo`` by default) that breaks one of the
simulator's defaults: a walk that starts in motion, range noise from 1 to 30 mm, no IMU, people
walking by, a scanner silent for 5 s, a 5 ms clock offset on one scanner, a rig 1 deg / 2 cm off
the recording's, the wrong rig. Every run goes through the command line as a user runs it
(``backpack-slam run``), so the exit code and the printed problems are what a user sees; runs with
outputs are evaluated against the ground truth.

A cell meets its goal when the ATE is within the condition's goal (1 cm; 2 cm at 20-30 mm noise) and
the run exits 0, or when the goal is missed and the run says so (the failure verdict, exit 3), or,
for the wrong rig, when the run is refused before processing (exit 2). Exit 0 over a missed goal is
the one outcome that must never happen.

Usage:
    .venv/bin/python scripts/bench_robustness.py [--world demo] [--duration 60] [--seed 1]
        [--out out/robustness] [--cases walking,noise_10mm,...] [--reuse] [--markdown docs/robustness.md]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
EXE = [sys.executable, "-m", "backpack_slam.cli"]


@dataclass(frozen=True)
class Condition:
    """One cell: simulation overrides, how the rig differs, and the ATE goal (m)."""

    name: str
    what: str
    sim: dict[str, Any] = field(default_factory=dict)
    sim_rig: str = "itc_backpack"  # the rig the recording is made with (its /tf_static)
    run_rig: str | None = "itc_backpack"  # the rig the run is given (a name, 'perturbed', or None)
    rig_change: dict[str, Any] = field(default_factory=dict)  # scanner -> (dtranslation, drpy) for 'perturbed'
    goal: float = 0.01
    refused: bool = False  # the goal is a refusal before processing


def conditions(imu: bool) -> list[Condition]:
    out = [
        Condition("standing", "start standing, 3 mm noise (reference)"),
        Condition("walking", "start while walking at ~1 m/s", {"gait": {"start_speed": 1.0}}),
    ]
    for mm in (1, 3, 10, 20, 30):
        out.append(Condition(f"noise_{mm}mm", f"range noise {mm} mm", {"noise": {"range_sigma": mm / 1000}},
                             goal=0.02 if mm >= 20 else 0.01))
    out += [
        Condition("people", "6 walkers and 2 standing groups", {"people": {"walkers": 6, "groups": 2}}),
        Condition("silent_5s", "scanner 'left' silent for 5 s", {"silences": [{"scanner": "left", "start": 20.0, "duration": 5.0}]}),
        Condition("offset_5ms", "5 ms clock offset on scanner 'right'", sim_rig="offset"),
        Condition("rig_off", "rig 1 deg / 2 cm off the recording's", run_rig="perturbed",
                  rig_change={"left": ([0.02, 0.0, 0.0], [math.radians(1.0), 0.0, 0.0])}),
        Condition("wrong_rig", "the default rig on a recording of another rig", sim_rig="other", refused=True),
    ]
    if imu:
        out = [Condition(c.name + "_imu", c.what + ", with IMU", {**c.sim, "imu": True}, c.sim_rig, c.run_rig,
                         c.rig_change, c.goal, c.refused) for c in out]
    return out


def _rig_variant(kind: str, out: Path, change: dict[str, Any]) -> Path:
    """A rig YAML beside the outputs: the default rig with a clock offset, another rig, or the
    default rig perturbed."""
    from common.rig import resolve_rig, write_rig

    rig = resolve_rig("itc_backpack")
    scanners = []
    for s in rig.scanners:
        ext = s.T_body_scanner
        upd: dict[str, Any] = {}
        if kind == "offset" and s.name == "right":
            upd["time_offset"] = 0.005
        if kind == "other" and s.name != "top":  # pushbroom: side scanners across the walking direction
            upd["T_body_scanner"] = ext.model_copy(update={"rpy": [ext.rpy[0] + 0.5, ext.rpy[1], 0.0],
                                                           "translation": [0.1, ext.translation[1], -0.4]})
        if kind == "perturbed" and s.name in change:
            dt, dr = change[s.name]
            upd["T_body_scanner"] = ext.model_copy(update={
                "translation": [a + b for a, b in zip(ext.translation, dt, strict=True)],
                "rpy": [a + b for a, b in zip(ext.rpy, dr, strict=True)]})
        scanners.append(s.model_copy(update=upd))
    path = out / f"rig_{kind}.yaml"
    write_rig(path, rig.model_copy(update={"scanners": scanners, "name": f"itc_backpack_{kind}"}))
    return path


def run_condition(c: Condition, world: str, duration: float, seed: int, out: Path, cloud: bool = False,
                  slam_config: Path | None = None) -> dict[str, Any]:
    from simulation.run import SimulationConfig, simulate
    from slam.evaluate import Stats, evaluate

    out.mkdir(parents=True, exist_ok=True)
    sim_rig: str | Path = c.sim_rig if c.sim_rig == "itc_backpack" else _rig_variant(c.sim_rig, out, {})
    bag = out / f"{c.name}.bag"
    cfg = SimulationConfig.model_validate({"duration": duration, "seed": seed, **c.sim})
    sim = simulate(world, sim_rig, out=bag, config=cfg, progress=False)
    run_rig = str(_rig_variant("perturbed", out, c.rig_change)) if c.run_rig == "perturbed" else c.run_rig
    run_dir = out / f"{c.name}.out"
    cmd = [*EXE, "run", str(sim.bag), "--out", str(run_dir), "--quiet"] + (["--rig", run_rig] if run_rig else [])
    if not cloud or slam_config is not None:  # the SLAM alone: no cloud pass, no rerun map
        import yaml

        base = yaml.safe_load(slam_config.read_text()) if slam_config is not None else None
        doc: dict[str, Any] = dict(base or {})
        if not cloud:
            doc["output"] = {**(doc.get("output") or {}), "cloud": False, "rerun": False}
        config = out / "slam.yaml"
        config.write_text(yaml.safe_dump(doc))
        cmd += ["--config", str(config)]
    t0 = time.perf_counter()
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run(cmd, capture_output=True, text=True, env=os.environ | {"PYTHONPATH": str(ROOT)})
    wall = time.perf_counter() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    # the run's CPU seconds (user + system): on a loaded machine the wall clock measures the other load too
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    row: dict[str, Any] = {"name": c.name, "what": c.what, "exit": proc.returncode, "wall": wall, "cpu": cpu,
                           "realtime_cpu": duration / max(cpu, 1e-9),
                           "stderr": " | ".join(ln for ln in proc.stderr.splitlines() if "error" in ln or "failure" in ln
                                                or "warning" in ln)[:300]}
    summary_path = run_dir / "summary.json"
    if summary_path.is_file():
        summary = json.loads(summary_path.read_text())
        row["realtime"] = summary.get("realtime_factor")
        row["verdict"] = summary.get("health", {}).get("verdict", "?")
        row["problems"] = [p["code"] for p in summary.get("health", {}).get("problems", [])]
        counts = summary.get("counts", {})
        row["associated"] = counts.get("segments_associated", 0) / max(counts.get("segments", 0), 1)
        row["start_moving"] = summary.get("start", {}).get("moving")
        row["noise_mm"] = {k: round(1000 * v["range_sigma"], 1) for k, v in summary.get("noise", {}).get("scanners", {}).items()
                           if isinstance(v, dict) and v.get("range_sigma") is not None}
        res = evaluate(run_dir, sim.gt, max_cloud_points=500_000)
        row["ate"] = res.trajectory.ate["start_aligned"].rmse
        row["ate_se3"] = res.trajectory.ate["se3_aligned"].rmse
        if res.cloud is not None:
            row["cloud_median"] = Stats.of(res.cloud.distances).median
    else:
        row["verdict"] = "refused" if proc.returncode == 2 else "crashed"
    reached = row.get("ate", math.inf) < c.goal
    if c.refused:
        row["goal_met"] = proc.returncode == 2
    else:
        # the goal, or an honest failure: the one outcome that must never happen is exit 0 over a missed goal
        row["goal_met"] = reached and proc.returncode == 0
        row["honest"] = reached or proc.returncode != 0
    row["goal"] = "refused" if c.refused else f"ATE < {c.goal * 100:g} cm"
    return row


EXPLAIN = """Made by `scripts/bench_robustness.py` (issue 21): each row is one simulated walk that breaks
one of the simulator's defaults, run through the command line as a user runs it (`backpack-slam
run BAG --rig itc_backpack`, no cloud pass), then evaluated against the ground truth. ATE is the
RMSE of the positions after aligning the first pose (start-aligned) or the best rigid motion
(SE(3)); *segments associated* is the fraction of line segments on planes of the map; *x real
time* is the walk's duration over the run's wall-clock time and over its CPU time (both
processes; on a shared machine the wall clock measures the other load too); the verdict is the
run's own (`summary.json` `health`, problems in brackets) and the exit code what the command
returned: 0 ok or degraded, 2 refused before processing (bad input, a rig that does not match the
recording's `/tf_static`), 3 finished but failed (outputs written, marked failed). A cell meets
its goal when the ATE is below it and the run exits 0, or, for the wrong rig, when the run is
refused; *never a silent wrong map* is no only when a run missed its goal and exited 0.

Re-run (one case at a time; `--reuse` keeps the cases already in OUT):

    nice .venv/bin/python scripts/bench_robustness.py --duration 30 --out out/robustness \\
        --markdown docs/robustness.md [--cases walking,noise_20mm] [--reuse] [--imu] [--cloud]
"""


def _mm(row: dict[str, Any], key: str) -> str:
    return f"{1000 * row[key]:.1f} mm" if key in row and math.isfinite(row[key]) else "-"


def table(rows: list[dict[str, Any]]) -> str:
    head = ("| condition | goal | ATE start-aligned | ATE SE(3) | cloud median | segments associated | "
            "x real time (wall / CPU) | verdict | exit | goal met | never a silent wrong map |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        rt = f"{r['realtime']:.2f}x / {r['realtime_cpu']:.2f}x" if r.get("realtime") else "-"
        assoc = f"{100 * r['associated']:.1f} %" if "associated" in r else "-"
        honest = "yes" if r.get("honest", r["goal_met"]) else "**NO**"
        verdict = r["verdict"] + (f" ({', '.join(r['problems'])})" if r.get("problems") else "")
        lines.append(f"| {r['what']} | {r['goal']} | {_mm(r, 'ate')} | {_mm(r, 'ate_se3')} | {_mm(r, 'cloud_median')} | "
                     f"{assoc} | {rt} | {verdict} | {r['exit']} | {'yes' if r['goal_met'] else 'no'} | {honest} |")
    return head + "\n".join(lines) + "\n"


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common.atomic import atomic_path

    names = [r["name"] for r in rows]
    ate = [1000 * r.get("ate", float("nan")) for r in rows]
    colour = {"ok": "tab:green", "degraded": "tab:orange", "failed": "tab:red", "refused": "tab:gray"}
    fig, ax = plt.subplots(figsize=(max(6.0, 0.7 * len(rows)), 4.0))
    ax.bar(names, [a if math.isfinite(a) else 0.0 for a in ate],
           color=[colour.get(r["verdict"], "black") for r in rows])
    goals = [float(r["goal"].split("<")[1].split()[0]) * 10.0 if "<" in r["goal"] else math.nan for r in rows]
    ax.scatter(names, goals, marker="_", s=500, color="k", label="the row's ATE goal", zorder=3)
    for i, r in enumerate(rows):
        if r["verdict"] in ("refused", "crashed"):
            ax.text(i, 0.5, r["verdict"], rotation=90, ha="center", va="bottom", fontsize=7)
    ax.set_yscale("symlog", linthresh=10.0)
    ax.set_ylabel("ATE RMSE, start-aligned (mm)")
    ax.set_title("robustness: bar colour = the run's own verdict (green ok, orange degraded, red failed, grey refused)",
                 fontsize=8)
    ax.tick_params(axis="x", rotation=60, labelsize=7)
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--world", default="demo")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--imu", action="store_true", help="every condition with the simulated IMU")
    ap.add_argument("--cases", default=None, help="comma-separated condition names (default: all)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "robustness")
    ap.add_argument("--markdown", type=Path, default=None, help="write the table (and the plot beside it)")
    ap.add_argument("--cloud", action="store_true", help="write and evaluate the cloud too (slower)")
    ap.add_argument("--config", type=Path, default=None, help="a SLAM configuration (YAML) for every run")
    ap.add_argument("--reuse", action="store_true",
                    help="take a case's row from an earlier run's OUT/CASE/row.json when there is one")
    args = ap.parse_args()
    todo = conditions(args.imu)
    if args.cases:
        want = set(args.cases.split(","))
        unknown = want - {c.name for c in todo}
        if unknown:
            print(f"unknown cases: {', '.join(sorted(unknown))} (known: {', '.join(c.name for c in todo)})", file=sys.stderr)
            return 2
        todo = [c for c in todo if c.name in want]
    rows = []
    for i, c in enumerate(todo):
        saved = args.out / c.name / "row.json"
        if args.reuse and saved.is_file():
            rows.append(json.loads(saved.read_text()))
            print(f"[{i + 1}/{len(todo)}] {c.name}: reused {saved}", file=sys.stderr, flush=True)
            continue
        print(f"[{i + 1}/{len(todo)}] {c.name}: {c.what} ...", file=sys.stderr, flush=True)
        rows.append(run_condition(c, args.world, args.duration, args.seed, args.out / c.name, args.cloud, args.config))
        r = rows[-1]
        saved.write_text(json.dumps(r, indent=1, default=str))
        print(f"    exit {r['exit']}, verdict {r['verdict']}, ATE {1000 * r.get('ate', float('nan')):.1f} mm, "
              f"goal met: {r['goal_met']}", file=sys.stderr, flush=True)
    text = table(rows)
    print(text)
    (args.out / "rows.json").write_text(json.dumps(rows, indent=1, default=str))
    if args.markdown is not None:
        from common.atomic import write_text

        png = args.markdown.parent / "figures" / f"robustness_{args.world}{'_imu' if args.imu else ''}.png"
        png.parent.mkdir(parents=True, exist_ok=True)
        plot(rows, png)
        write_text(args.markdown, f"# Robustness ({args.world}, {args.duration:g} s, seed {args.seed}"
                   f"{', IMU' if args.imu else ''})\n\n{EXPLAIN}\n{text}\n"
                   f"![robustness]({png.relative_to(args.markdown.parent)})\n")
    return 0 if all(r.get("honest", r["goal_met"]) for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
