"""Scans read and prepared ahead of the front end, in a second process.

The front end and the back end run in one process; reading the bag, segmenting every scan and
lifting its segments into the body frame (``slam.frontend.scan_prep``) depend on the scans alone, so a
reader process does them while the estimator works on the scans before, and hands over
``PreparedScan`` records in chunks through a bounded queue (memory stays bounded: the reader is
at most ``max_chunks`` chunks ahead). The records are the same, bit for bit, as those prepared in
the estimator's own process (``prepared_scans(..., process=False)``).

The reader process is forked (Linux; its start costs nothing and it inherits the compiled
kernels); where forking is unavailable, or this process is a daemon (a pool worker, which may not
have children), the scans are prepared in this process instead.
"""

from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import queue as queue_mod
import signal
import sys
import time
from collections.abc import Generator, Sequence
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from common.rig import Rig
from slam.config import SlamConfig
from slam.frontend.scan_prep import PreparedScan, ScanPreparer
from slam.imu_feed import ImuSamples
from slam.io.source import BagSource, StreamIndex

FloatArray = NDArray[np.float64]

_POLL_S = 1.0  # s between checks that the reader is still alive while waiting for a chunk
_PR_SET_PDEATHSIG = 1  # prctl(2): the signal a process gets when its parent ends
_STOP_GRACE_S = 2.0  # s a stopped helper process has to exit on SIGTERM before it is killed
_DONE = "done"
_ERROR = "error"


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


class PreparedScans:
    """The scans of a bag (the rig's topics, stamp order) prepared for the front end, as an
    iterator; ``index`` is their stream's :class:`StreamIndex`, complete once the iterator is."""

    def __init__(self, scans: Generator[PreparedScan, None, None], index: StreamIndex) -> None:
        self._scans = scans
        self.index = index

    def __iter__(self) -> PreparedScans:
        return self

    def __next__(self) -> PreparedScan:
        return next(self._scans)

    def close(self) -> None:
        """Stop early (and the reader process with it)."""
        self._scans.close()


def prepared_scans(
    source: BagSource,
    rig: Rig,
    cfg: SlamConfig,
    imu: ImuSamples | None,
    *,
    process: bool = True,
    chunk: int = 64,
    max_chunks: int = 32,
) -> PreparedScans:
    """The scans of ``source`` (the rig's topics, time order) prepared for the front end.

    With ``process`` (and :func:`can_fork_reader`) a forked reader process, with its own
    ``BagSource``, prepares them and this iterator hands them on, ``chunk`` scans at a time, at
    most ``max_chunks`` chunks ahead; an error in the reader (an ``InputError`` naming the bag,
    say) is raised here. Closing the iterator early stops the reader. The bag and its topics are
    checked before this returns; then ``source`` lets go of its message index
    (:meth:`BagSource.release`) while the reader holds its own, so that the walk's memory holds
    one index, not two (``source`` opens the bag again when next read: the export)."""
    if not (process and can_fork_reader()):
        preparer = ScanPreparer(rig, cfg, imu)
        stream = source.scans(rig=rig, echo=cfg.input.echo)
        return PreparedScans((preparer.prepare(line) for line in stream), stream.index)
    source.scan_plan(rig=rig)  # checks the bag's topics now, in this process
    source.release()
    index = StreamIndex()
    return PreparedScans(_from_reader(source.path, rig, cfg, imu, chunk, max_chunks, index), index)


def _reader(bag: Path, rig: Rig, cfg: SlamConfig, imu: ImuSamples | None, chunk: int, q: Any, parent: int) -> None:
    """The reader process (forked from ``parent``): prepares every scan of its own ``BagSource``
    of ``bag`` and puts them on ``q`` in chunks, then ``(_DONE, the stream's index)``; any
    exception goes on ``q`` as ``(_ERROR, exception)``."""
    die_with_parent(parent)
    try:
        preparer = ScanPreparer(rig, cfg, imu)
        batch: list[PreparedScan] = []
        angles: dict[int, FloatArray] = {}
        with BagSource(bag) as source:
            stream = source.scans(rig=rig, echo=cfg.input.echo)
            for line in stream:
                batch.append(_shared_angles(preparer.prepare(line), angles))
                if len(batch) >= chunk:
                    q.put(batch)
                    batch = []
        if batch:
            q.put(batch)
        q.put((_DONE, stream.index))
    except BaseException as e:  # handed to the estimator's process, which raises it
        q.put((_ERROR, e))


def _shared_angles(scan: PreparedScan, angles: dict[int, FloatArray]) -> PreparedScan:
    """The scan with its beam angles as the same array object as the last scan's of its scanner
    when they are equal (``angles``: the last array of each scanner): a chunk then carries each
    scanner's angles once (pickle keeps one copy of an object), not once per scan (~8 kB of a
    scan's ~53 kB), and this process unpickles and holds less."""
    segs = scan.segs
    if segs is None:
        return scan
    last = angles.get(scan.scanner)
    if last is not None and last.shape == segs.beam_angles.shape and np.array_equal(last, segs.beam_angles):
        return replace(scan, segs=replace(segs, beam_angles=last))
    angles[scan.scanner] = segs.beam_angles
    return scan


def _from_reader(
    bag: Path, rig: Rig, cfg: SlamConfig, imu: ImuSamples | None, chunk: int, max_chunks: int, index: StreamIndex
) -> Generator[PreparedScan, None, None]:
    """The reader process's scans; ``index`` is filled with its stream's index at the end."""
    ctx = mp.get_context("fork")
    q = ctx.Queue(maxsize=max_chunks)
    proc = ctx.Process(target=_reader, args=(bag, rig, cfg, imu, chunk, q, os.getpid()), name="backpack-slam-reader", daemon=True)
    proc.start()
    try:
        while True:
            item = get_from_children(q, [proc], f"{bag}: the scan reader process")
            if isinstance(item, tuple) and len(item) == 2 and item[0] == _DONE:
                done: StreamIndex = item[1]
                for f in fields(StreamIndex):  # every field: the reader's index is the stream's
                    setattr(index, f.name, getattr(done, f.name))
                break
            if isinstance(item, tuple) and len(item) == 2 and item[0] == _ERROR:
                raise item[1]
            yield from item
        proc.join()
    finally:
        stop_children([proc])
        q.close()
        q.cancel_join_thread()
