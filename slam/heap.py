"""The C heap's free pages handed back to the system (glibc), between the stages of a run and
during a long pass over the bag (:class:`HeapKeeper`)."""

from __future__ import annotations

import ctypes
import gc
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["HeapKeeper", "fewer_collections", "resident_bytes", "trim_heap"]

# the cyclic collector's thresholds during a run: the walk allocates millions of short-lived
# containers (records, tuples, lists) whose memory reference counting frees; at Python's default
# (700, 10, 10) the collector ran ~1,100 times a minute and traversed the whole heap every ~9 s
# (1.7 s of 80 s of the office walk; 0.2 s with these)
RUN_GC_THRESHOLDS = (20_000, 20, 20)


@contextmanager
def fewer_collections(thresholds: tuple[int, int, int] = RUN_GC_THRESHOLDS) -> Iterator[None]:
    """Python's cyclic garbage collector at ``thresholds`` inside the block (processes forked
    in it inherit them), the caller's thresholds again after it."""
    before = gc.get_threshold()
    gc.set_threshold(*thresholds)
    try:
        yield
    finally:
        gc.set_threshold(*before)


def trim_heap() -> bool:
    """Give the free pages of the C heap back to the system (glibc's ``malloc_trim``); False where
    there is no glibc (nothing done). Objects freed by Python, numpy or gtsam leave their memory in
    malloc's free chunks, resident until malloc reuses it: after the estimation, what the final
    batch and the let-go estimator used; after a sectioned batch's solve, its kept eliminations and
    factors."""
    try:
        trim = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
    return True


def resident_bytes() -> int | None:
    """This process's resident memory (bytes, ``/proc/self/statm``); None where unknown."""
    try:
        with open("/proc/self/statm", "rb") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


class HeapKeeper:
    """Keeps a long pass's resident memory from creeping up through malloc's free chunks.

    After :func:`trim_heap` the free chunks of a large heap (the estimator's, and the same heap
    inherited by a forked process) hold no pages; a pass that allocates and frees the same
    amounts over and over (the cloud pass: every scan's arrays, every batch's) is served from
    those chunks, splitting them at ever new places, so that its resident memory rises with the
    scans read while malloc's memory in use does not (session 22: 5 kB per scan in the
    estimator, 1.6 kB in a forked part, on the 120 s walk), up to the heap's whole free size (GB
    after an hour's final batch). :meth:`check`, called now and then (after a cloud batch),
    trims the heap once the resident memory is ``slack`` bytes above what it was after the last
    trim: the rise stays under ``slack``, at a trim per ``slack`` of it."""

    def __init__(self, slack: int = 32 << 20, rss: Callable[[], int | None] = resident_bytes,
                 trim: Callable[[], bool] = trim_heap) -> None:
        self._slack, self._rss, self._trim = slack, rss, trim
        self._base = rss()
        self.trims = 0

    def check(self) -> None:
        if self._base is None:  # resident memory unknown here: never trimmed
            return
        now = self._rss()
        if now is not None and now > self._base + self._slack:
            self._trim()
            self.trims += 1
            self._base = self._rss() or now
