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
import importlib
import signal
import sys
from collections.abc import Iterator, Sequence
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


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """While the block runs, SIGTERM raises :class:`Terminated` in this process; a process forked
    meanwhile (a reader or export helper) exits at once on it instead, its parent cleaning up.
    The previous handler comes back after the block (``main`` may run inside a test)."""
    me = os.getpid()

    def handler(signum: int, frame: FrameType | None) -> None:
        if os.getpid() != me:
            os._exit(128 + signum)
        raise Terminated()

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave SIGTERM as it is
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv`` (default: ``sys.argv[1:]``); returns the exit code."""
    debug = os.environ.get("BACKPACK_SLAM_DEBUG", "") not in ("", "0")
    try:
        with sigterm_as_interrupt():
            parser = build_parser()
            args = parser.parse_args(argv)
            run: Any = getattr(args, "_run", None)
            if run is None:
                parser.print_usage(sys.stderr)
                print(f"{PROG}: error: a command is required (one of: {', '.join(COMMANDS)})", file=sys.stderr)
                return 2
            return int(run(args))
    except Terminated:
        print(f"{PROG}: terminated", file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ValueError, OSError) as e:
        if debug:
            raise
        print(f"{PROG}: error: {one_line(e)}", file=sys.stderr)
        return 2
    except SystemExit as e:  # --help, --version
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 2)


if __name__ == "__main__":
    sys.exit(main())
