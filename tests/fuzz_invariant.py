"""The invariant every command keeps over any input (issue 24), and the runners that check it.

For every command over a case's inputs (``tests/fuzz_inputs.py``), one of:

- ``ok``: exit 0, its outputs complete (a run's ``summary.json`` verdict ``ok`` or ``degraded``),
  and the input held usable data;
- ``refused``: exit 2 with one line ``backpack-slam: error: ...`` on stderr naming the input
  (besides the run's ``note:`` lines), nothing written;
- ``failed``: exit 3 from ``run``, its outputs complete and marked ``failed`` in ``summary.json``;
- ``interrupted``: exit 130 (SIGINT) or 143 (SIGTERM) after the case's signal (or an exit by
  that signal, before the CLI's handlers are in place), the outputs complete or absent;

and never a traceback, another exit code, stray lines on stderr, a temporary file left behind
(``.tmp-``, ``.old-``, ``.partN.rows``), or a hang (the command's time limit). Anything else is
a violation, named in one line each.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fuzz_inputs import Command, Output

ROOT = Path(__file__).resolve().parents[1]
OUTCOMES = ("ok", "refused", "failed", "interrupted", "violation")
EXIT_SIGNAL = {"INT": 130, "TERM": 143}
SIGNUM = {"INT": int(signal.SIGINT), "TERM": int(signal.SIGTERM)}
_PROGRESS = re.compile(r"\d+%\||\[\d+:\d+(:\d+)?[<,]")
_ALLOWED = {
    0: ("note: ", "warning: ", "backpack-slam: warning: "),
    3: ("note: ", "warning: ", "backpack-slam: warning: ", "backpack-slam: failure: ",
        "backpack-slam: the run's estimate cannot be trusted"),
    2: ("note: ", "warning: "),
}
_TEMPORARY = re.compile(r"(\.tmp-|\.old-|\.part\d+\.rows$)")


@dataclass
class Result:
    """One command's run and its judgement."""

    command: Command
    rc: int | None
    stdout: str
    stderr: str
    seconds: float
    outcome: str = "violation"
    violations: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        lines = stderr_lines(self.stderr)
        return {"command": self.command.name, "argv": self.command.argv, "rc": self.rc, "seconds": round(self.seconds, 2),
                "outcome": self.outcome, "violations": self.violations, "signal": self.command.signal,
                "stderr_last": lines[-1][:300] if lines else ""}


def stderr_lines(text: str) -> list[str]:
    """The lines of stderr without progress bars (tqdm redraws with carriage returns)."""
    out = []
    for part in re.split(r"[\r\n]", text):
        s = part.strip()
        if s and not _PROGRESS.search(s):
            out.append(s)
    return out


def _strict_json(path: Path) -> Any:
    def no_constant(c: str) -> Any:
        raise ValueError(f"non-finite number {c}")

    return json.loads(path.read_text(), parse_constant=no_constant)


def check_complete(out: Output) -> str | None:
    """Why an existing output is not complete, or None."""
    p = out.path
    try:
        if out.folder:
            if not p.is_dir():
                return f"{p} is not a folder"
            missing = [f for f in out.required if not (p / f).is_file()]
            if missing:
                return f"{p} lacks {', '.join(missing)}"
            if out.check == "run":
                _strict_json(p / "summary.json")
            return None
        if not p.is_file() or p.stat().st_size == 0:
            return f"{p} is empty or not a file"
        if out.check == "json":
            _strict_json(p)
        elif out.check == "rig":
            from common.rig import load_rig

            load_rig(p)
    except Exception as e:
        return f"{p}: {type(e).__name__}: {' '.join(str(e).split())[:200]}"
    return None


def run_verdict(out: Output) -> str | None:
    """A run folder's health verdict (summary.json), or None."""
    try:
        return str(_strict_json(out.path / "summary.json")["health"]["verdict"])
    except Exception:
        return None


def temporaries(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if _TEMPORARY.search(p.name))


def judge(cmd: Command, rc: int | None, stderr: str, folder: Path, timed_out: bool) -> tuple[str, list[str]]:
    """(outcome, violations) of a command's run (module doc)."""
    bad: list[str] = []
    lines = stderr_lines(stderr)
    if timed_out:
        bad.append(f"hang: no exit within {cmd.timeout:g} s")
    if "Traceback (most recent call last)" in stderr:
        bad.append("traceback: " + (lines[-1] if lines else "")[:300])
    left = temporaries(folder)
    if left:
        bad.append(f"temporary files left: {', '.join(left[:5])}")
    outcome = "violation"
    if timed_out or rc is None:
        return outcome, bad
    if rc == 0:
        outcome = "ok"
        if cmd.no_usable_data:
            bad.append("exit 0 over an input with no usable data")
        for out in cmd.outputs:
            why = check_complete(out) if out.path.exists() else f"{out.path} missing"
            if why:
                bad.append(f"exit 0 with an incomplete output: {why}")
            elif out.check == "run" and run_verdict(out) not in ("ok", "degraded"):
                bad.append(f"exit 0 with health verdict {run_verdict(out)}")
    elif rc == 3 and cmd.name == "run":
        outcome = "failed"
        for out in cmd.outputs:
            why = check_complete(out) if out.path.exists() else f"{out.path} missing"
            if why:
                bad.append(f"exit 3 with an incomplete output: {why}")
            elif out.check == "run" and run_verdict(out) != "failed":
                bad.append(f"exit 3 with health verdict {run_verdict(out)}")
    elif rc == 2:
        outcome = "refused"
        errors = [ln for ln in lines if ln.startswith("backpack-slam: error: ")]
        if len(errors) != 1:
            bad.append(f"exit 2 with {len(errors)} error lines")
        elif cmd.culprits and not any(c and c in errors[0] for c in cmd.culprits):
            bad.append(f"error line names none of {cmd.culprits}: {errors[0][:300]}")
        for out in cmd.outputs:
            if out.path.exists():
                bad.append(f"exit 2 but {out.path} was written")
    elif cmd.signal is not None and rc in (EXIT_SIGNAL[cmd.signal[0]], -SIGNUM[cmd.signal[0]]):
        # exit by the signal itself (a shell's status 128 + n, as the CLI's own exit code) happens when it
        # lands before the CLI's handlers are in place (the interpreter's start-up)
        outcome = "interrupted"
        for out in cmd.outputs:
            why = check_complete(out) if out.path.exists() else None
            if why:
                bad.append(f"interrupted with an incomplete output: {why}")
    else:
        bad.append(f"exit code {rc}" + (f" (signal {-rc})" if rc < 0 else ""))
    if rc in _ALLOWED:
        allowed = _ALLOWED[rc]
        if rc == 2:
            stray = [ln for ln in lines if not ln.startswith(("backpack-slam: error: ", *allowed))]
        else:
            stray = [ln for ln in lines if not ln.startswith(allowed)]
        if stray and "Traceback (most recent call last)" not in stderr:
            bad.append(f"stray stderr: {stray[0][:300]}")
    if outcome == "interrupted":
        stray = [ln for ln in lines if not ln.startswith(("note: ", "warning: ", "backpack-slam: "))]
        if stray and "Traceback (most recent call last)" not in stderr:
            bad.append(f"stray stderr: {stray[0][:300]}")
    return ("violation" if bad else outcome), bad


def python_env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("BACKPACK_SLAM_DEBUG", None)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env.setdefault("OMP_NUM_THREADS", "1")
    env["PYTHONPATH"] = str(ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except (ProcessLookupError, PermissionError):
        return False
    return True


class Forked:
    """``backpack_slam.cli.main(argv)`` in a child forked from this process (its own session, cwd
    ``folder``, stdout and stderr to files), as ``python -m backpack_slam.cli`` would run it but
    without the interpreter's start-up and imports (about 1.6 s of CPU a command): the part of
    :class:`subprocess.Popen` that :func:`run_subprocess` uses. An exception ``main`` lets through
    is printed as a traceback with exit 1, as Python does."""

    def __init__(self, argv: list[str], folder: Path, out_path: Path, err_path: Path) -> None:
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # pragma: no cover - the child
            code = 1
            try:
                os.setsid()
                os.chdir(folder)
                for fd, path, flags in ((0, os.devnull, os.O_RDONLY),
                                        (1, str(out_path), os.O_WRONLY | os.O_CREAT | os.O_TRUNC),
                                        (2, str(err_path), os.O_WRONLY | os.O_CREAT | os.O_TRUNC)):
                    f = os.open(path, flags, 0o644)
                    os.dup2(f, fd)
                    os.close(f)
                # whatever stood for them (a test runner's capture) goes; the files take their place
                sys.stdin = sys.__stdin__ = open(0, closefd=False)
                sys.stdout = sys.__stdout__ = open(1, "w", closefd=False)
                sys.stderr = sys.__stderr__ = open(2, "w", closefd=False)
                for sig in (signal.SIGINT, signal.SIGTERM):
                    signal.signal(sig, signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL)
                from backpack_slam.cli import main

                try:
                    code = main(argv)
                except SystemExit as e:
                    code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
                except BaseException:
                    import traceback

                    traceback.print_exc()
                    code = 1
            finally:
                with contextlib.suppress(Exception):
                    sys.stdout.flush()
                    sys.stderr.flush()
                os._exit(code & 0xFF)
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        t0 = time.perf_counter()
        while self.poll() is None:
            if timeout is not None and time.perf_counter() - t0 > timeout:
                raise subprocess.TimeoutExpired("backpack_slam.cli.main", timeout)
            time.sleep(0.02)
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.returncode is None:
            os.kill(self.pid, sig)


# what the commands import lazily, in the fork server: everything but the modules that start threads at
# import (rerun, through slam.run_folder), which a forked child would inherit without their threads
PRELOAD = ("gtsam", "slam.pipeline", "slam.prefetch", "slam.io.source", "slam.io.bag", "slam.io.carmen",
           "slam.io.scanfile", "slam.health", "slam.preflight", "slam.evaluate", "slam.survey",
           "calibration.estimator", "rosbags.highlevel", "evo.core.metrics", "laspy", "pye57", "matplotlib.figure")


def preload() -> None:
    """Import what the commands import, once, before :class:`Forked` children are made (a
    worker's initializer); the process must stay single-threaded for them."""
    import importlib

    for k, v in python_env().items():
        if k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
            os.environ.setdefault(k, v)
    os.environ.pop("BACKPACK_SLAM_DEBUG", None)
    from backpack_slam.cli import build_parser

    build_parser()  # imports every command's module
    for name in PRELOAD:
        with contextlib.suppress(ImportError):
            importlib.import_module(name)
    threads = len(os.listdir("/proc/self/task")) if os.path.isdir("/proc/self/task") else 1
    if threads != 1:
        print(f"warning: the fork server runs {threads} threads after its imports", file=sys.stderr)


def run_subprocess(cmd: Command, folder: Path, timeout_scale: float = 1.0, fork: bool = False) -> Result:
    """``cmd`` as a user runs it (``python -m backpack_slam.cli``, its own session; with ``fork``
    a :class:`Forked` child of this process instead), with its signal; stdout and stderr go to
    files, so that a helper process left behind cannot hold the command open. Processes of its
    session still alive after it exited are a violation."""
    argv = [sys.executable, "-m", "backpack_slam.cli", *cmd.argv]
    timeout = cmd.timeout * timeout_scale
    logs = folder / "logs"
    logs.mkdir(exist_ok=True)
    k = len(list(logs.glob("*.stdout")))
    out_path, err_path = logs / f"{k}-{cmd.name}.stdout", logs / f"{k}-{cmd.name}.stderr"
    t0 = time.perf_counter()
    proc: subprocess.Popen[bytes] | Forked
    if fork:
        proc = Forked(list(cmd.argv), folder, out_path, err_path)
    else:
        with out_path.open("w") as fo, err_path.open("w") as fe:
            proc = subprocess.Popen(argv, cwd=folder, stdout=fo, stderr=fe, env=python_env(), start_new_session=True)
    timed_out = False
    left_behind = False
    try:
        if cmd.signal is not None:
            name, delay, group = cmd.signal
            try:
                proc.wait(timeout=delay)
            except subprocess.TimeoutExpired:
                sig = signal.SIGINT if name == "INT" else signal.SIGTERM
                if group:
                    os.killpg(proc.pid, sig)
                else:
                    proc.send_signal(sig)
        proc.wait(timeout=max(timeout - time.perf_counter() + t0, 30.0))
        deadline = time.perf_counter() + 10.0  # helpers stopped by the command's clean-up may take a moment
        while _group_alive(proc.pid) and time.perf_counter() < deadline:
            time.sleep(0.1)
        left_behind = _group_alive(proc.pid)
    except subprocess.TimeoutExpired:
        timed_out = True
    finally:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    seconds = time.perf_counter() - t0
    out = out_path.read_text(errors="replace")
    err = err_path.read_text(errors="replace")
    res = Result(cmd, None if timed_out else proc.returncode, out, err, seconds)
    cmd_timeout = cmd.timeout
    cmd.timeout = timeout
    res.outcome, res.violations = judge(cmd, res.rc, err, folder, timed_out)
    cmd.timeout = cmd_timeout
    if left_behind:
        res.violations.append("helper processes still running after the command exited")
        res.outcome = "violation"
    return res


def run_inprocess(cmd: Command, folder: Path) -> Result:
    """``cmd`` through ``backpack_slam.cli.main`` in this process (no signal, no time limit)."""
    from backpack_slam.cli import main

    assert cmd.signal is None, "signals need a subprocess"
    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc: int | None = main(cmd.argv)
        except BaseException as e:  # what main lets through is a violation: record it as a traceback
            import traceback

            err.write("Traceback (most recent call last)\n" + "".join(traceback.format_exception_only(type(e), e)))
            rc = None
    res = Result(cmd, rc, out.getvalue(), err.getvalue(), time.perf_counter() - t0)
    res.outcome, res.violations = judge(cmd, rc if rc is not None else -999, res.stderr, folder, False)
    return res
