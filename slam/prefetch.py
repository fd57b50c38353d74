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

import multiprocessing as mp
import os
from collections.abc import Generator
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from common.rig import Rig
from slam.config import SlamConfig
from slam.forked import can_fork_reader, die_with_parent, get_from_children, stop_children
from slam.frontend.scan_prep import PreparedScan, ScanPreparer
from slam.imu_feed import ImuSamples
from slam.io.source import BagSource, StreamIndex

FloatArray = NDArray[np.float64]

_DONE = "done"
_ERROR = "error"


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
    proc = ctx.Process(target=_reader, args=(bag, rig, cfg, imu, chunk, q, os.getpid()), name="backpack-slam-reader",
                       daemon=True)
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
