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
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

from fuzz_inputs import KINDS, Materials, RandomChooser, build_case, build_materials, draw_spec  # noqa: E402
from fuzz_invariant import OUTCOMES, Result, run_subprocess  # noqa: E402


def case_seed(seed: int, i: int) -> int:
    return seed * 1_000_003 + i


def run_case(i: int, spec: dict[str, Any], materials: Materials, work: Path, violations: Path,
             timeout_scale: float) -> list[Result]:
    folder = work / f"case-{i}"
    if folder.exists():
        shutil.rmtree(folder)
    try:
        case = build_case(spec, materials, folder)
    except Exception as e:  # the generator's own failure: reported, not counted as the CLI's
        print(f"case {i}: generator error {type(e).__name__}: {e} (spec {json.dumps(spec)[:300]})", file=sys.stderr)
        shutil.rmtree(folder, ignore_errors=True)
        return []
    results = [run_subprocess(cmd, folder, timeout_scale) for cmd in case.commands]
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
    ap.add_argument("--replay", type=Path, default=None, help="a violation folder: run its spec.json again")
    args = ap.parse_args(argv)

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    materials = build_materials(out / "materials", duration=args.duration)
    print(f"materials: {materials.root} ({time.perf_counter() - t0:.1f} s)", flush=True)
    work, violations = out / "work", out / "violations"
    work.mkdir(exist_ok=True)
    violations.mkdir(exist_ok=True)

    if args.replay is not None:
        spec = json.loads((args.replay / "spec.json").read_text())
        for r in run_case(0, spec, materials, work, out / "replayed", args.timeout_scale):
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
    for i in range(args.start, args.start + args.cases):
        ch = RandomChooser(case_seed(args.seed, i))
        specs.append((i, draw_spec(ch, ch.choice(kinds))))

    by_outcome: Counter[str] = Counter()
    by_command: dict[str, Counter[str]] = {}
    by_kind: dict[str, Counter[str]] = {}
    log = (out / "results.jsonl").open("a")
    n_done = 0
    t_cases = time.perf_counter()

    def one(item: tuple[int, dict[str, Any]]) -> tuple[int, dict[str, Any], list[Result]]:
        i, spec = item
        return i, spec, run_case(i, spec, materials, work, violations, args.timeout_scale)

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        for i, spec, results in ex.map(one, specs):
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
    n_cmd = sum(by_outcome.values())
    print(f"\n{len(specs)} cases, {n_cmd} commands, seed {args.seed}, wall time {wall / 60:.1f} min "
          f"({wall:.0f} s)")
    print("outcome      " + " ".join(f"{o:>11s}" for o in OUTCOMES))
    for name, c in [("all", by_outcome), *sorted(by_command.items()), *sorted((f"[{k}]", v) for k, v in by_kind.items())]:
        print(f"{name:12s} " + " ".join(f"{c.get(o, 0):11d}" for o in OUTCOMES))
    summary = {"cases": len(specs), "commands": n_cmd, "seed": args.seed, "start": args.start, "wall_s": wall,
               "outcomes": dict(by_outcome), "by_command": {k: dict(v) for k, v in by_command.items()},
               "by_kind": {k: dict(v) for k, v in by_kind.items()}}
    (out / f"summary-seed{args.seed}-{args.start}.json").write_text(json.dumps(summary, indent=1))
    if by_outcome.get("violation"):
        print(f"violations kept in {violations}/")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
