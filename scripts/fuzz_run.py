"""Fuzz campaign over the command line (issue 24): hostile bags, logs, scanlines, rigs, configs,
option values and run folders through ``segment``, ``run``, ``calibrate``, ``evaluate``, ``export``
and ``rig``, each command in a subprocess as a user runs it, some interrupted by SIGINT or SIGTERM.

Every case is drawn from a seeded RNG (``tests/fuzz_inputs.py``, case ``i`` of seed ``S`` is
``RandomChooser(S * 1_000_003 + i)``) and judged by the invariant of ``tests/fuzz_invariant.py``.
Prints the count per outcome (per command and per input kind) and keeps every violation as a
reproducible case folder ``OUT/violations/case-<i>/`` (the generated inputs, ``spec.json``, the
command lines, stdout, stderr and the reasons); ``--replay DIR`` runs such a folder's spec again.

Usage:
    .venv/bin/python scripts/fuzz_run.py --cases 1000 --seed 1 [--out out/fuzz] [--timeout-scale 1.0]
        [--kinds bag,rig,...] [--jobs 1] [--duration 3.0]
    .venv/bin/python scripts/fuzz_run.py --replay out/fuzz/violations/case-17
    .venv/bin/python scripts/fuzz_run.py --report-only out/fuzz/summary-seed1-0.json --docs docs

``--docs DIR`` writes the campaign's figures there: ``fuzz_campaign.json`` (the summary),
``fuzz_campaign.md`` (count per outcome, per command and per input kind, the wall time) and
``figures/fuzz_outcomes.png`` (outcomes per input kind).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):  # before numpy: the forked commands inherit it
    os.environ.setdefault(_var, "1")
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

from fuzz_inputs import (  # noqa: E402
    KINDS,
    Materials,
    RandomChooser,
    build_case,
    build_materials,
    calibrate_command,
    draw_spec,
    run_command,
)
from fuzz_invariant import OUTCOMES, Result, preload, run_subprocess  # noqa: E402


def case_seed(seed: int, i: int) -> int:
    return seed * 1_000_003 + i


def run_case(i: int, spec: dict[str, Any], materials: Materials, work: Path, violations: Path,
             timeout_scale: float, fork: bool = False) -> list[Result]:
    folder = work / f"case-{i}"
    if folder.exists():
        shutil.rmtree(folder)
    try:
        case = build_case(spec, materials, folder)
    except Exception as e:  # the generator's own failure: reported, not counted as the CLI's
        print(f"case {i}: generator error {type(e).__name__}: {e} (spec {json.dumps(spec)[:300]})", file=sys.stderr)
        shutil.rmtree(folder, ignore_errors=True)
        return []
    results = [run_subprocess(cmd, folder, timeout_scale, fork=fork) for cmd in case.commands]
    if any(r.outcome == "violation" for r in results):
        keep = violations / folder.name
        if keep.exists():
            shutil.rmtree(keep)
        shutil.copytree(folder, keep, symlinks=True)
        for k, r in enumerate(results):
            (keep / f"cmd{k}.txt").write_text(" ".join(["backpack-slam", *r.command.argv]) + "\n")
            (keep / f"cmd{k}.stdout").write_text(r.stdout)
            (keep / f"cmd{k}.stderr").write_text(r.stderr)
        (keep / "results.json").write_text(json.dumps([r.to_dict() for r in results], indent=1))
    shutil.rmtree(folder, ignore_errors=True)
    return results


OUTCOME_MEANING = {
    "ok": "exit 0, outputs complete, verdict ok/degraded",
    "refused": "exit 2, one line naming the input",
    "failed": "exit 3, outputs complete, verdict failed",
    "interrupted": "exit 130/143 after SIGINT/SIGTERM, outputs complete or absent",
    "violation": "anything else (traceback, exit 0 over no data, leftovers, hang)",
}


def _table(rows: list[tuple[str, Counter[str] | dict[str, int]]]) -> list[str]:
    lines = ["| commands | " + " | ".join(OUTCOMES) + " | total |", "|---|" + "---:|" * (len(OUTCOMES) + 1)]
    for name, c in rows:
        lines.append(f"| {name} | " + " | ".join(f"{c.get(o, 0):,}" for o in OUTCOMES)
                     + f" | {sum(c.values()):,} |")
    return lines


def write_report(summary: dict[str, Any], docs: Path) -> None:
    """``docs/fuzz_campaign.json``, ``docs/fuzz_campaign.md`` and ``docs/figures/fuzz_outcomes.png``
    of a campaign's summary (module doc)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    docs.mkdir(parents=True, exist_ok=True)
    (docs / "fuzz_campaign.json").write_text(json.dumps(summary, indent=1) + "\n")
    wall = summary["wall_s"]
    md = [
        "# Fuzz campaign (issue 24)",
        "",
        f"`scripts/fuzz_run.py --cases {summary['cases']} --seed {summary['seed']} --jobs {summary.get('jobs', 1)} "
        f"--duration {summary.get('duration', 3.0):g}`: {summary['cases']:,} generated cases, "
        f"{summary['commands']:,} commands, wall time {wall / 60:.1f} min ({wall:.0f} s; the cases "
        f"{summary.get('cases_s', wall) / 60:.1f} min, the warm-up {summary.get('warm_up_s', 0.0):.0f} s) on the "
        "shared 2-core machine (other work on it too). Every command runs in its own process "
        f"({summary.get('runner', 'subprocess')} runner) and is judged by the invariant of "
        "`tests/fuzz_invariant.py`.",
        *([] if not summary.get("rerun_cases") else [
            "",
            f"With the code at the campaign's start, {summary['base_outcomes'].get('violation', 0)} commands broke the "
            "invariant (each fixed and kept as a regression case in `tests/test_fuzz.py`). After "
            f"the fixes, the {len(summary['rerun_cases'])} cases whose inputs reach the changed code (every "
            "violation among them) were run again (`--only`, same seed); the tables count the re-runs in place "
            "of the first runs (`--merge`), the wall time is both together."]),
        "",
        "Outcomes:",
        "",
        *[f"- `{o}`: {OUTCOME_MEANING[o]}" for o in OUTCOMES],
        "",
        "Per command:",
        "",
        *_table([("**all**", summary["outcomes"]), *sorted(summary["by_command"].items())]),
        "",
        "Per input kind:",
        "",
        *_table(sorted(summary["by_kind"].items())),
        "",
        "![outcomes per input kind](figures/fuzz_outcomes.png)",
        "",
    ]
    (docs / "fuzz_campaign.md").write_text("\n".join(md))

    kinds = sorted(summary["by_kind"])
    colours = {"ok": "#4c9a2a", "refused": "#3b75af", "failed": "#e08b28", "interrupted": "#8c6bb1",
               "violation": "#c0392b"}
    fig = Figure(figsize=(8, 3.6))
    ax = fig.add_subplot()
    bottom = [0] * len(kinds)
    for o in OUTCOMES:
        counts = [summary["by_kind"][k].get(o, 0) for k in kinds]
        ax.bar(kinds, counts, bottom=bottom, label=f"{o} ({sum(counts)})", color=colours[o])
        bottom = [b + c for b, c in zip(bottom, counts, strict=True)]
    ax.set_ylabel("commands")
    ax.set_title(f"{summary['cases']:,} fuzz cases, {summary['commands']:,} commands: outcome per input kind")
    ax.legend(fontsize=8)
    ax.tick_params(axis="x", labelsize=8)
    fig.tight_layout()
    (docs / "figures").mkdir(exist_ok=True)
    fig.savefig(docs / "figures" / "fuzz_outcomes.png", dpi=110)


def merged_summary(base: Path, rerun: Path) -> dict[str, Any]:
    """The summary of ``base``'s results (a campaign's ``results.jsonl``) where the cases in
    ``rerun`` (the same seed's cases run again, ``--only``) take their re-run's rows; the
    times are the base campaign's (``BASE/summary-*.json``) plus the re-run's."""
    rows = [json.loads(ln) for ln in base.read_text().splitlines() if ln.strip()]
    again = [json.loads(ln) for ln in rerun.read_text().splitlines() if ln.strip()]
    redone = {r["case"] for r in again}
    rows = [r for r in rows if r["case"] not in redone] + again
    by_outcome: Counter[str] = Counter(r["outcome"] for r in rows)
    by_command: dict[str, Counter[str]] = {}
    by_kind: dict[str, Counter[str]] = {}
    for r in rows:
        by_command.setdefault(r["command"], Counter())[r["outcome"]] += 1
        by_kind.setdefault(r["kind"], Counter())[r["outcome"]] += 1
    summaries = [json.loads(p.read_text()) for p in (*base.parent.glob("summary-*.json"), *rerun.parent.glob("summary-*.json"))]
    first = json.loads(next(base.parent.glob("summary-*.json")).read_text())
    return {**first, "cases": len({r["case"] for r in rows}), "commands": len(rows),
            "wall_s": sum(x["wall_s"] for x in summaries), "cases_s": sum(x.get("cases_s", x["wall_s"]) for x in summaries),
            "warm_up_s": sum(x.get("warm_up_s", 0.0) for x in summaries), "outcomes": dict(by_outcome),
            "by_command": {k: dict(v) for k, v in by_command.items()}, "by_kind": {k: dict(v) for k, v in by_kind.items()},
            "rerun_cases": sorted(redone),
            "base_outcomes": dict(Counter(json.loads(ln)["outcome"] for ln in base.read_text().splitlines() if ln.strip()))}


def warm_up(materials: Materials, folder: Path) -> float:
    """Run and calibrate the materials' bag once, outside the count: numba compiles the kernels
    into its on-disk cache the first time (a minute of CPU), which every case would otherwise
    pay until one finished. Returns the seconds it took."""
    t0 = time.perf_counter()
    if folder.exists():
        shutil.rmtree(folder)
    (folder / "out").mkdir(parents=True)
    for cmd in (run_command(materials.bags["ros1"], materials.rig, folder, []),
                calibrate_command(materials.bags["ros1"], materials.rig, folder, [])):
        r = run_subprocess(cmd, folder, timeout_scale=10.0)
        if r.outcome != "ok":
            print(f"warm-up {cmd.name}: {r.outcome} rc={r.rc} {'; '.join(r.violations)} "
                  f"{r.stderr.strip()[-300:]}", file=sys.stderr)
    shutil.rmtree(folder, ignore_errors=True)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--start", type=int, default=0, help="first case index (resume a campaign)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "fuzz")
    ap.add_argument("--timeout-scale", type=float, default=1.0, help="multiply every command's time limit")
    ap.add_argument("--kinds", default=",".join(KINDS), help="input kinds to draw from (comma separated)")
    ap.add_argument("--jobs", type=int, default=1, help="cases run at the same time")
    ap.add_argument("--duration", type=float, default=3.0, help="s of the simulated recordings")
    ap.add_argument("--runner", choices=("fork", "subprocess"), default="fork",
                    help="fork: each command a child forked from a worker that imported the package once "
                         "(default, ~1.6 s of CPU less a command); subprocess: python -m backpack_slam.cli")
    ap.add_argument("--replay", type=Path, default=None, help="a violation folder: run its spec.json again")
    ap.add_argument("--only", default=None, help="comma-separated case indices of the seed to run (re-run a campaign's cases)")
    ap.add_argument("--merge", nargs=2, type=Path, default=None, metavar=("BASE_JSONL", "RERUN_JSONL"),
                    help="a campaign's results.jsonl with the rows of the cases re-run (--only) replaced by the "
                         "re-run's: print and report (--docs) the merged counts")
    ap.add_argument("--docs", type=Path, default=None, help="write the campaign's report there (module doc)")
    ap.add_argument("--report-only", type=Path, default=None, help="a summary JSON: write its report to --docs")
    args = ap.parse_args(argv)
    if args.merge is not None:
        summary = merged_summary(*args.merge)
        print(json.dumps({k: summary[k] for k in ("cases", "commands", "outcomes", "rerun_cases")}))
        if args.docs is not None:
            write_report(summary, args.docs)
        return 0
    if args.report_only is not None:
        write_report(json.loads(args.report_only.read_text()), args.docs or ROOT / "docs")
        return 0

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    materials = build_materials(out / "materials", duration=args.duration)
    materials_s = time.perf_counter() - t0
    print(f"materials: {materials.root} ({materials_s:.1f} s)", flush=True)
    work, violations = out / "work", out / "violations"
    work.mkdir(exist_ok=True)
    violations.mkdir(exist_ok=True)
    warm_s = 0.0 if args.replay is not None else warm_up(materials, out / "warmup")
    print(f"warm-up (numba's cache): {warm_s:.1f} s", flush=True)

    if args.replay is not None:
        spec = json.loads((args.replay / "spec.json").read_text())
        for r in run_case(0, spec, materials, work, out / "replayed", args.timeout_scale, args.runner == "fork"):
            print(f"{r.outcome:12s} rc={r.rc} {' '.join(r.command.argv)}")
            for v in r.violations:
                print(f"    {v}")
            if r.stderr.strip():
                print("    stderr: " + r.stderr.strip().splitlines()[-1][:300])
        return 0

    kinds = tuple(k for k in args.kinds.split(",") if k)
    unknown = set(kinds) - set(KINDS)
    if unknown:
        ap.error(f"unknown kinds {sorted(unknown)}; known: {', '.join(KINDS)}")
    specs = []
    indices = ([int(k) for k in args.only.split(",") if k.strip()] if args.only
               else range(args.start, args.start + args.cases))
    for i in indices:
        ch = RandomChooser(case_seed(args.seed, i))
        specs.append((i, draw_spec(ch, ch.choice(kinds))))

    by_outcome: Counter[str] = Counter()
    by_command: dict[str, Counter[str]] = {}
    by_kind: dict[str, Counter[str]] = {}
    log = (out / "results.jsonl").open("a")
    n_done = 0
    t_cases = time.perf_counter()

    fork = args.runner == "fork"
    with ProcessPoolExecutor(max_workers=max(1, args.jobs), mp_context=mp.get_context("fork"),
                             initializer=preload if fork else None) as ex:
        futures = [ex.submit(run_case, i, spec, materials, work, violations, args.timeout_scale, fork)
                   for i, spec in specs]
        for (i, spec), future in zip(specs, futures, strict=True):
            results = future.result()
            n_done += 1
            for r in results:
                by_outcome[r.outcome] += 1
                by_command.setdefault(r.command.name, Counter())[r.outcome] += 1
                by_kind.setdefault(spec["kind"], Counter())[r.outcome] += 1
                log.write(json.dumps({"case": i, "seed": args.seed, "kind": spec["kind"], **r.to_dict()}) + "\n")
                if r.outcome == "violation":
                    print(f"case {i} [{spec['kind']}] {r.command.name}: VIOLATION: {'; '.join(r.violations)[:400]}",
                          flush=True)
            log.flush()
            if n_done % 25 == 0:
                el = time.perf_counter() - t_cases
                print(f"{n_done}/{len(specs)} cases, {el / 60:.1f} min: {dict(by_outcome)}", flush=True)
    log.close()
    wall = time.perf_counter() - t0
    cases_s = time.perf_counter() - t_cases
    n_cmd = sum(by_outcome.values())
    print(f"\n{len(specs)} cases, {n_cmd} commands, seed {args.seed}, wall time {wall / 60:.1f} min "
          f"({wall:.0f} s)")
    print("outcome      " + " ".join(f"{o:>11s}" for o in OUTCOMES))
    for name, c in [("all", by_outcome), *sorted(by_command.items()), *sorted((f"[{k}]", v) for k, v in by_kind.items())]:
        print(f"{name:12s} " + " ".join(f"{c.get(o, 0):11d}" for o in OUTCOMES))
    summary = {"cases": len(specs), "commands": n_cmd, "seed": args.seed, "start": args.start, "wall_s": wall,
               "cases_s": cases_s, "warm_up_s": warm_s, "materials_s": materials_s,
               "jobs": args.jobs, "duration": args.duration, "runner": args.runner,
               "outcomes": dict(by_outcome), "by_command": {k: dict(v) for k, v in by_command.items()},
               "by_kind": {k: dict(v) for k, v in by_kind.items()}}
    (out / f"summary-seed{args.seed}-{args.start}.json").write_text(json.dumps(summary, indent=1))
    if args.docs is not None:
        write_report(summary, args.docs)
    if by_outcome.get("violation"):
        print(f"violations kept in {violations}/")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
