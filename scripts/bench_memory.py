"""Peak memory (RSS) of ``run_slam`` and ``evaluate`` per stage, on the simulated office bags.

Each bag is run in fresh child processes (so that every ``ru_maxrss`` is that process's own):

- ``run`` child: ``run_slam`` then ``evaluate`` in one process (what ``bench_slam.py`` and a
  user's script do); the peak is read after the estimation (``SlamRunner.result``, hooked by
  this script so that any revision can be measured), after the export and after the evaluation;
- ``eval`` child: ``evaluate`` alone on the run folder (the ``backpack-slam evaluate`` command).

``ru_maxrss`` never decreases, so a stage's figure is the peak of that stage and every one
before it. With ``--baseline REV`` the same children also run on the code of git revision REV
(exported with ``git archive`` into a temporary folder and put first on ``PYTHONPATH``) in the
same invocation, and the table gives both and their ratio; the baseline's and the current
``cloud.ply`` (their points, after the header) and cloud figures are compared. ``--current REV``
measures revision REV instead of the working tree (e.g. to leave out uncommitted changes).

With ``--profile`` each bag is instead run once in a ``profile`` child that finds what holds
the memory: at ``--points`` evenly spaced data times of the walk, after the estimation (the
final batch included) and after the export it records the process's RSS and peak, the
Python heap traced by ``tracemalloc`` (current, and the peak since the previous point: so the
peak of each stage) grouped by the file and line that allocated it, the gc-tracked objects by
type, the gtsam objects ``tracemalloc`` cannot see (the graph's factor records and built
factors, the variables of the estimate) and the size of each holder (:data:`HOLDERS`, deep
sizes with shared objects counted once, in that order). The report gives each holder's bytes
at every point and its growth per data minute (least-squares slope over the walk's points).
``tracemalloc`` slows the run about 1.5-2x; the figures are for finding holders, not timing.
With ``--no-trace`` there is no ``tracemalloc``: the points add the PSS of all the run's processes,
glibc's malloc figures and each stage's peak RSS and PSS, sampled every 0.25 s by a separate
process (the final batch's own peak, the covariances', the export's steps'), and the report
extrapolates every holder and stage to 60 data minutes.

Usage (2 cores: the children run one at a time; use ``nice``):
    nice .venv/bin/python scripts/bench_memory.py [BAG ...] [--baseline REV] [--current REV]
        [--out DIR] [--markdown FILE]
    nice .venv/bin/python scripts/bench_memory.py --profile [BAG ...] [--points 6] [--no-trace]
        [--json FILE] [--markdown FILE]
BAG defaults to the 60 s and 120 s office walks in /tmp/bench_slam_cache (``bench_slam.py``
simulates them); each needs its ``<stem>.gt`` folder beside it.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
CACHE = Path("/tmp/bench_slam_cache")
DEFAULT_BAGS = (CACHE / "office_adis_rest10_60s_seed1.bag", CACHE / "office_adis_rest10_120s_seed1.bag")
STAGES = (  # (key, label)
    ("estimation", "estimation (after runner.result)"),
    ("export", "export (after run_slam)"),
    ("run_and_evaluate", "run + evaluate, one process"),
    ("evaluate_alone", "evaluate alone"),
)
_ROW = "MEMORY_ROW "


def _peak_gb() -> float:
    """This process's peak RSS so far (GB; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9


def _child_run(bag: str, gt: str, out: str) -> dict[str, Any]:
    """``run_slam`` + ``evaluate`` in this process; the peak after each stage (GB)."""
    import slam.run
    from common.rig import resolve_rig
    from slam.config import SlamConfig
    from slam.evaluate import evaluate

    peaks: dict[str, float] = {}
    result = slam.run.SlamRunner.result

    def hooked(self: Any, *args: Any, **kwargs: Any) -> Any:
        res = result(self, *args, **kwargs)
        peaks["estimation"] = _peak_gb()
        return res

    slam.run.SlamRunner.result = hooked  # type: ignore[method-assign]
    # the back end in this process: a forked one's memory would be missing from this process's peak
    cfg = SlamConfig.model_validate({"backend": {"pipelined": False}})
    summary = slam.run.run_slam(bag, resolve_rig("itc_backpack"), cfg, out, progress=False)
    peaks["export"] = _peak_gb()
    ev = evaluate(out, gt)
    peaks["run_and_evaluate"] = _peak_gb()
    cloud = ev.cloud.to_json()["distance_m"] if ev.cloud is not None else {}
    return {"peaks": peaks, "cloud_points": summary["counts"]["cloud_points"], "cloud_distance_m": cloud,
            "wall": summary["timings"]["wall"], "export_s": summary["timings"].get("export")}


def _child_eval(out: str, gt: str) -> dict[str, Any]:
    """``evaluate`` alone in this process; its peak (GB)."""
    from slam.evaluate import evaluate

    evaluate(out, gt)
    return {"peaks": {"evaluate_alone": _peak_gb()}}


def _spawn(tree: Path, *args: str) -> dict[str, Any]:
    """Run this script's child mode with ``tree``'s packages first on the path; its row."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(tree), os.environ.get("PYTHONPATH")) if p))
    proc = subprocess.run([sys.executable, __file__, "--child", *args], stdout=subprocess.PIPE, text=True,
                          env=env, cwd=tree, check=False)
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith(_ROW)), None)
    if proc.returncode != 0 or line is None:
        raise RuntimeError(f"child {' '.join(args)} in {tree} failed (exit {proc.returncode})")
    row: dict[str, Any] = json.loads(line[len(_ROW):])
    return row


def measure(tree: Path, bag: Path, gt: Path, out: Path) -> dict[str, Any]:
    """All stage peaks of one bag with the code in ``tree``."""
    row = _spawn(tree, "run", str(bag), str(gt), str(out))
    row["peaks"] |= _spawn(tree, "eval", str(out), str(gt))["peaks"]
    return row


def export_revision(rev: str, dest: Path) -> Path:
    """The files of git revision ``rev`` in ``dest`` (``git archive``; the checkout is untouched)."""
    data = subprocess.run(["git", "-C", str(REPO), "archive", "--format=tar", rev], stdout=subprocess.PIPE,
                          check=False)
    if data.returncode != 0:
        raise ValueError(f"--baseline {rev}: not a revision of {REPO}")
    dest.mkdir(parents=True, exist_ok=True)
    tar = dest / "tree.tar"
    tar.write_bytes(data.stdout)
    with tarfile.open(tar) as t:
        t.extractall(dest / "tree", filter="data")
    tar.unlink()
    return dest / "tree"


def same_cloud_body(a: Path, b: Path, chunk: int = 1 << 26) -> bool:
    """Whether two cloud.ply hold the same bytes after their headers (the points)."""
    end = b"end_header\n"
    with a.open("rb") as fa, b.open("rb") as fb:
        for f in (fa, fb):
            head = f.read(4096)
            if end not in head:
                return False
            f.seek(head.index(end) + len(end))
        while True:
            x, y = fa.read(chunk), fb.read(chunk)
            if x != y:
                return False
            if not x:
                return True


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def table(results: dict[str, dict[str, dict[str, Any]]]) -> str:
    """Markdown: one row per stage, per bag the current figure (and baseline, ratio)."""
    with_base = any("baseline" in r for r in results.values())
    head, sep = "| peak RSS (GB) |", "|---|"
    for name in results:
        head += f" {name} |" + (f" {name} baseline | ratio |" if with_base else "")
        sep += "---:|" * (3 if with_base else 1)
    lines = [head, sep]
    for key, label in STAGES:
        cells = []
        for r in results.values():
            cur = r["current"]["peaks"].get(key)
            cells.append(_fmt(cur))
            if with_base:
                base = r.get("baseline", {}).get("peaks", {}).get(key)
                cells += [_fmt(base), "-" if cur is None or not base else f"{cur / base:.2f}"]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def profile(args: argparse.Namespace) -> int:
    """``--profile``: every bag in a ``profile`` child; the holder tables."""
    from memory_profile import report

    if args.points < 2:
        raise SystemExit(f"--points {args.points}: need at least 2")
    runs = []
    tree = export_revision(args.current, Path(tempfile.mkdtemp(prefix="bench_memory_"))) if args.current else REPO
    for bag in args.bags:
        print(f"{bag.name}: profile ...", flush=True)
        runs.append(_spawn(tree, "profile", str(bag), str(args.out / bag.stem / "profile"), str(args.points),
                           "notrace" if args.no_trace else "trace"))
    text = "\n\n".join(report(r) for r in runs) + "\n"
    print(text)
    if args.markdown:
        args.markdown.write_text(text)
    if args.json:
        args.json.write_text(json.dumps(runs))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bags", nargs="*", type=Path, default=list(DEFAULT_BAGS), help="bags (default: 60 s, 120 s)")
    ap.add_argument("--baseline", default=None, metavar="REV", help="also measure git revision REV")
    ap.add_argument("--current", default=None, metavar="REV",
                    help="measure git revision REV as the current code (default: the working tree)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_memory"), help="run folders (default %(default)s)")
    ap.add_argument("--markdown", type=Path, default=None, help="also write the table to this file")
    ap.add_argument("--profile", action="store_true", help="find the holders of the memory (see above)")
    ap.add_argument("--points", type=int, default=6, help="--profile: points over the walk (default %(default)s)")
    ap.add_argument("--no-trace", action="store_true",
                    help="--profile: without tracemalloc (deep sizes, malloc figures and sampled stage peaks only)")
    ap.add_argument("--json", type=Path, default=None, help="--profile: also write the raw points to this file")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        mode, *rest = args.child
        if mode == "profile":
            from memory_profile import profile_run

            row = profile_run(rest[0], rest[1], int(rest[2]), trace=rest[3] != "notrace")
        else:
            row = _child_run(*rest) if mode == "run" else _child_eval(*rest)
        print(_ROW + json.dumps(row), flush=True)
        return 0
    for bag in args.bags:
        if not bag.exists() or not (bag.parent / f"{bag.stem}.gt").is_dir():
            ap.error(f"{bag}: no such bag, or no {bag.stem}.gt beside it")
    if args.profile:
        return profile(args)
    results: dict[str, dict[str, dict[str, Any]]] = {}
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        trees = {"current": export_revision(args.current, Path(tmp) / "current") if args.current else REPO}
        if args.baseline:
            trees["baseline"] = export_revision(args.baseline, Path(tmp) / "baseline")
        for bag in args.bags:
            gt = bag.parent / f"{bag.stem}.gt"
            results[bag.stem] = {}
            for which, tree in trees.items():
                print(f"{bag.name}: {which} ...", flush=True)
                results[bag.stem][which] = measure(tree, bag, gt, args.out / bag.stem / which)
                print(f"  {json.dumps(results[bag.stem][which])}", flush=True)
    text = table(results) + "\n"
    for name, r in results.items():
        if "baseline" in r:
            same = same_cloud_body(args.out / name / "current" / "cloud.ply", args.out / name / "baseline" / "cloud.ply")
            figures = r["current"]["cloud_distance_m"] == r["baseline"]["cloud_distance_m"]
            text += f"\n{name}: cloud.ply points identical to the baseline: {same}; cloud-to-mesh figures identical: {figures}"
            for which in ("current", "baseline"):
                text += f"\n  {which}: export {r[which]['export_s']} s, wall {r[which]['wall']} s"
    print(text)
    if args.markdown:
        args.markdown.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
