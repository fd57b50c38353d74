"""``backpack-slam``: the command-line interface (wiring only).

Each subcommand lives in ``backpack_slam/commands/<name>.py`` and exposes
``add_parser(subparsers) -> argparse.ArgumentParser`` and ``run(args) -> int``. To add
a command, add its module name to ``COMMANDS``.

Bad input never shows a traceback: input errors (``ValueError`` and its subclasses such
as ``ConfigError`` and the readers' ``InputError``, and ``OSError`` such as a missing
file) print one line ``backpack-slam: error: ...`` to stderr and exit with code 2;
Ctrl-C (SIGINT) exits with 130 and SIGTERM with 143, both after the same clean-up (temporary
outputs removed, helper processes stopped). Set ``BACKPACK_SLAM_DEBUG=1`` to get the traceback
instead.
"""

from __future__ import annotations

import os

# numpy's BLAS threads cost far more than they give on the small dense systems of the front
# end (and the sweep runs cells in parallel processes); must be set before numpy loads
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import ctypes
import gc
import importlib
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from types import FrameType
from typing import Any, NoReturn

PROG = "backpack-slam"

# one entry per module in backpack_slam/commands/
COMMANDS: list[str] = ["segment", "demo", "evaluate", "view", "export", "rig", "run", "simulate", "sweep", "report", "calibrate"]


class UsageError(ValueError):
    """A command line that argparse rejects."""


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are exceptions (printed on one line by ``main``)."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(f"{self.prog}: {message}")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog=PROG, description="Backpack indoor mobile laser scanning: line segmentation and SLAM.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    for name in COMMANDS:
        module = importlib.import_module(f"backpack_slam.commands.{name}")
        p = module.add_parser(sub)
        p.set_defaults(_run=module.run)
    return parser


def one_line(e: BaseException) -> str:
    """The error as one line; an OSError names its file."""
    if isinstance(e, OSError) and e.filename is not None:
        text = f"{e.filename}: {e.strerror or e}"
    else:
        text = str(e) or type(e).__name__
    return " ".join(text.split())


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the command is, like Ctrl-C's KeyboardInterrupt (so that the same
    clean-up runs: temporary outputs removed, helper processes stopped)."""


EXIT_INTERRUPTED = 130  # SIGINT (Ctrl-C)
EXIT_TERMINATED = 143  # SIGTERM


class _Redeliver:
    """An interrupt raised where Python cannot raise: inside an at-fork callback (logging's lock
    release around a fork), a weakref callback (importlib's module locks) or a ``__del__``, the
    handler's exception is "unraisable": printed as "Exception ignored" with a traceback and then
    lost. ``sys.unraisablehook`` catches exactly those, keeps the print quiet and raises the
    signal again 5 ms later (a SIGALRM), where the clean-up sees it.

    Once an interrupt has arrived, any other unraisable error is its consequence and is kept quiet
    too: an object the interrupt stopped inside its ``__init__`` (llvmlite's ``OutputString``
    while numba compiles) fails in its ``__del__`` for want of the attributes it never set."""

    pending: int | None = None

    @classmethod
    def hook(cls, previous: Callable[[Any], object], received: list[int]) -> Callable[[Any], object]:
        def unraisable(info: Any) -> None:
            if isinstance(info.exc_value, (KeyboardInterrupt, Terminated)):
                cls.pending = signal.SIGTERM if isinstance(info.exc_value, Terminated) else signal.SIGINT
                signal.setitimer(signal.ITIMER_REAL, 0.005)
                return
            if received:
                return
            previous(info)
        return unraisable


@contextmanager
def signals_as_interrupt() -> Iterator[list[int]]:
    """While the block runs, SIGINT raises KeyboardInterrupt and SIGTERM :class:`Terminated` in
    this process, and the block's list records which arrived (an exception that an interrupt turns
    into another one on its way out, such as an extension module's ImportError while it loads, is
    then still an interrupt). A process forked meanwhile (a reader, the back end or an export
    helper) exits at once on either instead, its parent cleaning up: raised there, the interrupt
    would end in the helper's queue, whose flush at the helper's exit can wait forever on a parent
    that no longer reads it. The previous handlers come back after the block
    (``main`` may run inside a test)."""
    me = os.getpid()
    received: list[int] = []

    def handler(signum: int, frame: FrameType | None) -> None:
        if signum == signal.SIGALRM:
            if _Redeliver.pending is None:
                return
            signum, _Redeliver.pending = _Redeliver.pending, None
        if os.getpid() != me:  # a forked helper: its parent cleans up
            os._exit(128 + signum)
        received.append(signum)
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    previous = {}
    previous_hook = sys.unraisablehook
    sys.unraisablehook = _Redeliver.hook(previous_hook, received)
    try:
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGALRM):
            previous[sig] = signal.signal(sig, handler)
    except ValueError:  # not the main thread: leave the signals as they are
        pass
    try:
        yield received
    finally:
        if received:  # what the interrupt left half-built goes while the quiet hook holds
            gc.collect()
        for sig, old in previous.items():
            signal.signal(sig, old)
        sys.unraisablehook = previous_hook


def _forget_nested_interrupt() -> None:
    """CPython marks an interrupt that escapes code run through ``PyRun_String`` (pybind11's
    ``py::exec`` inside an extension) as unhandled, and at exit kills the process with SIGINT
    itself (exit status -2, not 130 or 143), though the interrupt was caught further out. Here it
    was handled: clear the mark."""
    try:
        ctypes.c_int.in_dll(ctypes.pythonapi, "_Py_UnhandledKeyboardInterrupt").value = 0
    except (AttributeError, ValueError):  # another interpreter, or a CPython without the flag
        pass


def _interrupted(signum: int) -> int:
    _forget_nested_interrupt()
    if signum == signal.SIGTERM:
        print(f"{PROG}: terminated", file=sys.stderr)
        return EXIT_TERMINATED
    print(f"{PROG}: interrupted", file=sys.stderr)
    return EXIT_INTERRUPTED


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv`` (default: ``sys.argv[1:]``); returns the exit code."""
    debug = os.environ.get("BACKPACK_SLAM_DEBUG", "") not in ("", "0")
    # the interrupt is handled inside the block: its traceback's frames (and what an interrupted
    # constructor left half-built in them) are freed while the quiet unraisable hook still holds
    with signals_as_interrupt() as received:
        try:
            parser = build_parser()
            args = parser.parse_args(argv)
            run: Any = getattr(args, "_run", None)
            if run is None:
                parser.print_usage(sys.stderr)
                print(f"{PROG}: error: a command is required (one of: {', '.join(COMMANDS)})", file=sys.stderr)
                return 2
            return int(run(args))
        except Terminated:
            return _interrupted(signal.SIGTERM)
        except KeyboardInterrupt:
            return _interrupted(signal.SIGINT)
        except SystemExit as e:  # --help, --version
            return e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
        except Exception as e:
            if received:
                return _interrupted(received[-1])
            if debug or not isinstance(e, ValueError | OSError):
                raise
            print(f"{PROG}: error: {one_line(e)}", file=sys.stderr)
            return 2


if __name__ == "__main__":
    sys.exit(main())
