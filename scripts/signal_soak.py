"""Signal ``backpack-slam run`` many times while it writes its outputs, and count what happens.

The test suite signals one run at one moment (tests/test_fuzz.py); a race between an interrupt and
the forked helpers (the back end, the reader, the cloud pass's parts) shows only now and then on
a loaded machine. This script repeats it: each run is signalled at a random moment, up to
``--spread`` s after its temporary output folder appears (SIGINT to the process group, as a
shell's Ctrl-C, or SIGTERM to the run alone), and judged as the suite does: exit 130/143 with the
last line "interrupted"/"terminated" (or 0 with complete outputs when it finished first), no
traceback, no temporary left, no process left, no hang (``--timeout`` s).

    python scripts/signal_soak.py --runs 40 --signal int --seed 1 --markdown soak.md
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from fuzz_inputs import build_materials  # noqa: E402
from fuzz_invariant import python_env, temporaries  # noqa: E402

LAST_LINE = {130: "backpack-slam: interrupted", 143: "backpack-slam: terminated"}


def _left(out: Path) -> list[str]:
    """Processes whose command line names the run's output folder (helpers left behind)."""
    return subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout.split()


def one_run(bag: Path, rig: Path, folder: Path, group: bool, delay: float, timeout: float) -> str:
    """One signalled run in ``folder``; returns its outcome (``ok``, ``interrupted`` or a
    violation's name)."""
    out = folder / "run"
    proc = subprocess.Popen([sys.executable, "-m", "backpack_slam.cli", "run", str(bag), "--rig", str(rig), "--out",
                             str(out), "--quiet"], cwd=folder, env=python_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    t0 = time.monotonic()
    while proc.poll() is None and time.monotonic() - t0 < 120 and not any(folder.glob(".run.tmp-*")):
        time.sleep(0.02)
    time.sleep(delay)
    try:
        if group:
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGTERM)
    except ProcessLookupError:
        pass
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        return "hang"
    deadline = time.monotonic() + 10
    while _left(out) and time.monotonic() < deadline:
        time.sleep(0.2)
    lines = err.strip().splitlines()
    if "Traceback" in err:
        return "traceback"
    if temporaries(folder):
        return "temporary left"
    if _left(out):
        return "process left"
    if proc.returncode == 0:
        return "ok" if (out / "summary.json").is_file() else "exit 0, incomplete"
    if proc.returncode not in LAST_LINE:
        return f"exit {proc.returncode}"
    if not lines or lines[-1] != LAST_LINE[proc.returncode]:
        return "wrong last line"
    if out.exists() and not (out / "summary.json").is_file():
        return "half-written output"
    return "interrupted"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--signal", choices=("int", "term"), default="int",
                    help="int: SIGINT to the process group (Ctrl-C); term: SIGTERM to the run alone")
    ap.add_argument("--spread", type=float, default=0.3, help="s: the signal lands up to this long after the "
                    "temporary output folder appears")
    ap.add_argument("--timeout", type=float, default=60.0, help="s after the signal that count as a hang")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--markdown", default="", help="write the table here too")
    a = ap.parse_args()
    rng = random.Random(a.seed)
    counts: Counter[str] = Counter()
    with tempfile.TemporaryDirectory(prefix="signal_soak_") as tmp:
        mat = build_materials(Path(tmp) / "materials", duration=1.0)
        for i in range(a.runs):
            folder = Path(tmp) / f"run{i}"
            folder.mkdir()
            outcome = one_run(mat.bags["ros1"], mat.rig, folder, a.signal == "int", rng.uniform(0.0, a.spread),
                              a.timeout)
            counts[outcome] += 1
            print(f"{i + 1}/{a.runs}: {outcome}", flush=True)
    what = "SIGINT to the group" if a.signal == "int" else "SIGTERM to the run"
    table = [f"{a.runs} runs, {what}, up to {a.spread:g} s after the output folder appears (seed {a.seed})", "",
             "| outcome | runs |", "|---|---:|", *(f"| {k} | {v} |" for k, v in sorted(counts.items()))]
    text = "\n".join(table) + "\n"
    print(text)
    if a.markdown:
        Path(a.markdown).write_text(text)
    bad = sum(v for k, v in counts.items() if k not in ("ok", "interrupted"))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
