"""Compact lists of ids by key: the back end's observation blocks by plane and by knot.

Each list is an ``array('q')`` (8 bytes an id) instead of a set or list of Python ints (about 40-70
bytes an id). Removal is lazy: a removed id stays in its list, its readers filter it out with the
liveness they are given, and a list is rewritten without its dead ids once they are half of it.
"""

from __future__ import annotations

from array import array
from collections.abc import Callable, Iterator

import numpy as np
from numpy.typing import NDArray

IntArray = NDArray[np.int64]
_MIN_REWRITE = 32  # lists shorter than this are not rewritten


class IdLists:
    """Lists of int ids by int key, each in the order its ids were added; ``alive(ids)`` says
    which of ``ids`` are still live (dead ones are dropped when a list is rewritten)."""

    def __init__(self, alive: Callable[[IntArray], NDArray[np.bool_]]) -> None:
        self._alive = alive
        self._lists: dict[int, array] = {}
        self._dead: dict[int, int] = {}  # key -> dead ids noted in its list

    def __contains__(self, key: object) -> bool:
        return key in self._lists

    def __len__(self) -> int:
        return len(self._lists)

    def __iter__(self) -> Iterator[int]:
        return iter(self._lists)

    def add_key(self, key: int) -> None:
        """An empty list for ``key`` (kept as it is if it exists)."""
        if key not in self._lists:
            self._lists[key] = array("q")

    def append(self, key: int, ident: int) -> None:
        lst = self._lists.get(key)
        if lst is None:
            lst = self._lists[key] = array("q")
        lst.append(ident)

    def pop(self, key: int) -> None:
        """Forget the list of ``key``."""
        self._lists.pop(key, None)
        self._dead.pop(key, None)

    def get(self, key: int) -> IntArray:
        """The ids of ``key`` (a copy, dead ones included) in the order added; empty if none."""
        lst = self._lists.get(key)
        if lst is None or not lst:
            return np.zeros(0, dtype=np.int64)
        return np.frombuffer(lst, dtype=np.int64).copy()

    def live(self, key: int) -> IntArray:
        """The live ids of ``key`` in the order added."""
        ids = self.get(key)
        return ids[self._alive(ids)]

    def note_dead(self, key: int) -> None:
        """One id of ``key``'s list died; the list is rewritten when half of it is dead."""
        lst = self._lists.get(key)
        if lst is None:
            return
        dead = self._dead.get(key, 0) + 1
        if 2 * dead > len(lst) and len(lst) >= _MIN_REWRITE:
            self._lists[key] = array("q", self.live(key).tobytes())
            self._dead.pop(key, None)
        else:
            self._dead[key] = dead

    def nbytes(self) -> int:
        """Bytes of the lists' buffers (their capacity) and objects, the dict's entries left out."""
        return sum(lst.buffer_info()[1] * lst.itemsize + 64 for lst in self._lists.values())
