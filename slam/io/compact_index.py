"""A ROS1 bag's message index in numpy columns instead of Python tuples.

rosbags' ROS1 reader keeps one ``IndexData(time, chunk_pos, offset)`` named tuple per message
(about 170 B with its three ints): 322 MB for an hour of three scanners, an IMU and ground truth,
held by every process that opens the bag, and interleaved in memory with the chunk headers it
keeps, so that even freed it stays resident. :func:`open_compact` opens an ``AnyReader`` so that
each chunk's index entries become arrays as soon as they are read (one chunk's tuples alive at a
time), and each connection's index is a :class:`CompactIndex` (20 B per message) that yields the
same ``IndexData`` a block at a time: ``Reader.messages`` (which merges the connections' indexes
with ``heapq.merge``) reads the same messages in the same order. Readers of other formats
(ROS2) open as usual.
"""

from __future__ import annotations

import types
from collections import defaultdict
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

_BLOCK = 4096  # entries made into tuples at a time while iterating


class _ChunkPiece:
    """One chunk's entries of one connection while the bag opens (ordered by chunk position, as
    rosbags sorts a connection's entries once they are all read)."""

    __slots__ = ("offset", "pos", "time")

    def __init__(self, pos: int, entries: list[Any]) -> None:
        n = len(entries)
        self.pos = pos
        self.time = np.fromiter((e[0] for e in entries), dtype=np.int64, count=n)
        self.offset = np.fromiter((e[2] for e in entries), dtype=np.int64, count=n)

    def __lt__(self, other: _ChunkPiece) -> bool:
        return self.pos < other.pos


class CompactIndex:
    """One connection's index entries as columns sorted by (time, chunk position, offset):
    ``time`` (ns), ``chunk_pos`` (int64) and ``offset`` (uint32, within the decompressed chunk);
    iterating yields ``make(time, chunk_pos, offset)`` (rosbags' ``IndexData``) in that order."""

    __slots__ = ("chunk_pos", "make", "offset", "time")

    def __init__(self, time: NDArray[np.int64], chunk_pos: NDArray[np.int64], offset: NDArray[np.int64],
                 make: Any) -> None:
        if offset.size and (offset.min() < 0 or offset.max() > np.iinfo(np.uint32).max):
            raise ValueError("bag index: a message offset outside 0..2^32-1")
        order = np.lexsort((offset, chunk_pos, time))
        self.time: NDArray[np.int64] = np.ascontiguousarray(time[order])
        self.chunk_pos: NDArray[np.int64] = np.ascontiguousarray(chunk_pos[order])
        self.offset: NDArray[np.uint32] = offset[order].astype(np.uint32)
        self.make = make

    @classmethod
    def of_pieces(cls, pieces: list[_ChunkPiece], make: Any) -> CompactIndex:
        if not pieces:
            empty = np.zeros(0, dtype=np.int64)
            return cls(empty, empty, empty, make)
        pos = np.concatenate([np.full(p.time.size, p.pos, dtype=np.int64) for p in pieces])
        return cls(np.concatenate([p.time for p in pieces]), pos, np.concatenate([p.offset for p in pieces]), make)

    def __len__(self) -> int:
        return int(self.time.size)

    def __iter__(self) -> Iterator[Any]:
        make = self.make
        for lo in range(0, self.time.size, _BLOCK):
            hi = lo + _BLOCK
            yield from map(make, self.time[lo:hi].tolist(), self.chunk_pos[lo:hi].tolist(),
                           self.offset[lo:hi].tolist())

    def __getitem__(self, i: int) -> Any:
        return self.make(int(self.time[i]), int(self.chunk_pos[i]), int(self.offset[i]))

    @property
    def nbytes(self) -> int:
        return int(self.time.nbytes + self.chunk_pos.nbytes + self.offset.nbytes)


def open_compact(reader: Any) -> int:
    """Open ``reader`` (a rosbags ``AnyReader``, not yet open) with the index of each of its ROS1
    bags kept as :class:`CompactIndex` es; returns the number of messages they index (0 for
    other formats)."""
    from rosbags.rosbag1.reader import IndexData
    from rosbags.rosbag1.reader import Reader as Ros1Reader

    ros1 = [r for r in getattr(reader, "readers", ()) if isinstance(r, Ros1Reader)]
    for r in ros1:
        plain = type(r).read_index_data

        def read_index_data(self: Any, pos: int, indexes: dict[int, list[Any]], plain: Any = plain) -> None:
            one: dict[int, list[Any]] = defaultdict(list)
            plain(self, pos, one)  # rosbags parses the record; its tuples live until the next chunk
            for conn, entries in one.items():
                indexes[conn].append(_ChunkPiece(pos, entries))

        r.read_index_data = types.MethodType(read_index_data, r)  # type: ignore[method-assign]
    try:
        reader.open()
    finally:
        for r in ros1:
            r.__dict__.pop("read_index_data", None)
    n = 0
    for r in ros1:
        indexes: dict[int, Any] = r.indexes  # our pieces in rosbags' lists, then our index
        for cid, pieces in list(indexes.items()):
            index = CompactIndex.of_pieces(list(pieces), IndexData)
            indexes[cid] = index
            n += len(index)
        # rosbags counted a connection's messages as the length of its index list (here: chunks)
        r.connections = [c._replace(msgcount=len(r.indexes[c.id])) for c in r.connections]
    if ros1:
        reader.connections = [c for r in reader.readers for c in r.connections]
    return n
