"""The forked helper processes' lifecycle (the scan reader, the back-end worker, the cloud pass's
parts): whether one can be forked here, waiting for their results, making a helper die with its
parent, and stopping them within a bounded time.
"""

from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import queue as queue_mod
import signal
import sys
import time
from collections.abc import Sequence
from typing import Any

_POLL_S = 1.0  # s between checks that the helpers are still alive while waiting for a result
_PR_SET_PDEATHSIG = 1  # prctl(2): the signal a process gets when its parent ends
_STOP_GRACE_S = 2.0  # s a stopped helper process has to exit on SIGTERM before it is killed


def get_from_children(q: Any, procs: Sequence[Any], what: str) -> Any:
    """The next item that the forked processes ``procs`` put on ``q``, waiting while any of them
    lives; a RuntimeError naming ``what`` when they have all stopped without one."""
    while True:
        try:
            return q.get(timeout=_POLL_S)
        except queue_mod.Empty:
            if not any(p.is_alive() for p in procs):
                codes = ", ".join(str(p.exitcode) for p in procs)
                raise RuntimeError(f"{what}: stopped without a result (exit code {codes})") from None


def stop_children(procs: Sequence[Any], grace_s: float = _STOP_GRACE_S) -> None:
    """Stop the forked processes ``procs`` that still live: SIGTERM, then SIGKILL for those still
    alive ``grace_s`` later, and reap them. Bounded: a helper whose main thread waits on a lock
    (its queue's feeder thread, say, blocked on a pipe nobody reads) may never run its SIGTERM
    handler when the signal lands in another of its threads."""
    alive = [p for p in procs if p.is_alive()]
    for p in alive:
        p.terminate()
    deadline = time.monotonic() + grace_s
    for p in alive:
        p.join(timeout=max(0.0, deadline - time.monotonic()))
    for p in alive:
        if p.is_alive():
            p.kill()
        p.join()


def die_with_parent(parent: int) -> None:
    """Called first in a forked helper: the kernel kills it (SIGKILL) when its parent ``parent``
    ends (Linux; elsewhere nothing), and it ends at once if the parent already has. A helper
    forked while its parent was being interrupted may be unknown to the parent's clean-up (the
    interrupt landed between the fork and the parent's record of it), and its exit would wait
    forever on a queue the parent no longer reads."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (AttributeError, OSError):
            pass
    if os.getppid() != parent:
        os._exit(1)


def can_fork_reader() -> bool:
    """Whether a reader process can be started here (fork available, not a daemon process)."""
    return "fork" in mp.get_all_start_methods() and not mp.current_process().daemon
