"""Observation blocks: the points seen on one plane during one knot interval, their factors and
the exact summaries of the blocks that left the fixed-lag window.

A block's factor is :func:`slam.backend.factors.point_plane_factor` (per-point robust kernel,
points in the body frame at their beam times). The whole-graph and window solves put the blocks
of one knot interval into one :func:`slam.backend.factors.point_planes_factor` (the same rows,
one Python call per linearisation instead of one per block). A block whose poses the window
holds for good is folded into its plane's scatter (:mod:`slam.backend.plane_summary`).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import NamedTuple

import gtsam
import numpy as np
from gtsam.symbol_shorthand import P, X
from numpy.typing import ArrayLike, NDArray

from slam.backend import factor_kernels as _fk
from slam.backend.factors import (
    PlaneTable,
    RobustKernel,
    check_block,
    plane_row,
    point_plane_factor,
    point_plane_terms,
    point_planes_factor,
    robust_weights,
)
from slam.backend.graph import FactorGraph
from slam.backend.id_lists import IdLists
from slam.backend.plane_summary import scatter, shift_anchor
from slam.backend.spill import SpillTables
from slam.trajectory.placement import interval_poses

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
SPILL_ROWS = 1 << 18  # held blocks' rows kept in memory before they go to the spill files (10 MB)


@dataclass(frozen=True)
class ObservationBlock:
    """Points (N, 3) of plane ``plane_id`` seen during knot interval ``knot`` (body frame at their
    beam times), their interval fractions (N,) (None: at the knot itself) and sigmas (N,) [m]."""

    knot: int
    plane_id: int
    points: FloatArray
    alphas: FloatArray | None
    sigmas: FloatArray


class KnotFactors(NamedTuple):
    """Live factors by their highest knot (:meth:`BlockStore.factors_of_knots`): ids, ordered by
    highest knot then id, each one's highest knot, and which are observation blocks."""

    ids: IntArray
    top: IntArray
    is_block: NDArray[np.bool_]


class BlockColumns:
    """The observation blocks' data as columns: per block id (the graph's factor id, so ids of
    other factors are unused slots) its knot, plane, whether it spans two knots, its rows, whether
    it is live and its index in iSAM2 (-1: none); per row its point (3,), fraction and sigma; per
    held block its scatter (:meth:`scatter_of`, in a slot of its own array: most ids are not held
    blocks). Rows of a block are contiguous; a removed block's rows are garbage until
    :meth:`compact` rewrites the live ones (in block order). Arrays grow by half, so an hour's
    million blocks are a few numpy arrays, not a million Python objects.

    Once the held blocks' rows in memory pass ``spill_rows``, :meth:`spill` moves them and their
    scatters to files (:class:`slam.backend.spill.SpillTables`; ``spilled`` blocks' ``start`` and
    scatter slot are then rows of those files): :meth:`block`, :meth:`gather` and
    :meth:`scatter_of` read them back, byte for byte. None: never."""

    def __init__(self, spill_rows: int | None = SPILL_ROWS) -> None:
        self.knot = np.zeros(0, dtype=np.int64)
        self.plane = np.zeros(0, dtype=np.int64)
        self.two = np.zeros(0, dtype=bool)
        self.live = np.zeros(0, dtype=bool)
        self.start = np.zeros(0, dtype=np.int64)
        self.size = np.zeros(0, dtype=np.int32)
        self.held = np.zeros(0, dtype=bool)  # summarised (its scatter is its plane's share)
        # a held block's scatter slot: >= 0 in ``scatters``, <= -2 row -2 - slot of the spilled
        # scatters, -1 none
        self.slot = np.zeros(0, dtype=np.int32)
        self.isam = np.zeros(0, dtype=np.int32)  # the block's factor's index in iSAM2 (-1: none)
        self.spilled = np.zeros(0, dtype=bool)  # its rows are in the spill files
        self.scatters = np.zeros((0, 4, 4))  # held blocks' scatters (their planes' anchors) by slot
        self.n_slots = 0  # slots used (removed held blocks' included)
        self.points = np.zeros((0, 3))
        self.alphas = np.zeros(0)
        self.sigmas = np.zeros(0)
        self.rows = 0  # rows used in memory (live and garbage)
        self.garbage = 0  # rows of removed blocks in memory
        self.count = 0  # live blocks
        self.n_points = 0  # rows of live blocks (in memory or spilled)
        self.held_rows = 0  # rows of held blocks in memory
        self.spill_rows = spill_rows
        self.disk = SpillTables({"points": (3,), "alphas": (), "sigmas": (), "scatters": (4, 4)})

    def _grow_ids(self, bid: int) -> None:
        n = max(1024, self.knot.shape[0] * 3 // 2)
        while n <= bid:
            n = n * 3 // 2
        for name in ("knot", "plane", "two", "live", "start", "size", "held", "slot", "isam", "spilled"):
            old = getattr(self, name)
            new = np.full(n, -1 if name in ("slot", "isam") else 0, dtype=old.dtype)
            new[: old.shape[0]] = old
            setattr(self, name, new)

    def _grow_rows(self, need: int) -> None:
        n = max(4096, self.points.shape[0] * 3 // 2)
        while n < need:
            n = n * 3 // 2
        for name in ("points", "alphas", "sigmas"):
            old = getattr(self, name)
            new = np.zeros((n, *old.shape[1:]), dtype=old.dtype)
            new[: self.rows] = old[: self.rows]
            setattr(self, name, new)

    def put(self, bid: int, blk: ObservationBlock) -> None:
        """Store new block ``bid``."""
        if bid >= self.knot.shape[0]:
            self._grow_ids(bid)
        n = blk.points.shape[0]
        if self.rows + n > self.points.shape[0]:
            self._grow_rows(self.rows + n)
        s = self.rows
        self.points[s:s + n] = blk.points
        self.sigmas[s:s + n] = blk.sigmas
        if blk.alphas is not None:
            self.alphas[s:s + n] = blk.alphas
        self.rows += n
        self.knot[bid], self.plane[bid], self.two[bid] = blk.knot, blk.plane_id, blk.alphas is not None
        self.start[bid], self.size[bid], self.live[bid], self.isam[bid], self.slot[bid] = s, n, True, -1, -1
        self.spilled[bid] = False
        self.count += 1
        self.n_points += n

    def drop(self, bid: int) -> None:
        """Forget live block ``bid`` (its rows in memory become garbage; rewritten once they
        outweigh the rest)."""
        n = int(self.size[bid])
        if self.held[bid] and not self.spilled[bid]:
            self.held_rows -= n
        self.live[bid] = False
        self.held[bid] = False
        self.slot[bid] = -1
        self.count -= 1
        self.n_points -= n
        if not self.spilled[bid]:
            self.garbage += n
        self.spilled[bid] = False
        if self.garbage > max(self.rows - self.garbage, 1 << 16):
            self.compact()

    def compact(self) -> None:
        """Rewrite the rows in memory of the live blocks, in block order, without the garbage."""
        ids = np.flatnonzero(self.live & ~self.spilled)
        starts, sizes = self.start[ids], self.size[ids]
        idx = np.repeat(starts - np.concatenate(([0], np.cumsum(sizes)[:-1])), sizes) + np.arange(int(sizes.sum()))
        self.points = self.points[idx]
        self.alphas = self.alphas[idx]
        self.sigmas = self.sigmas[idx]
        new_start = np.zeros(ids.shape[0], dtype=np.int64)
        np.cumsum(sizes[:-1], out=new_start[1:])
        self.start[ids] = new_start
        self.rows = int(sizes.sum())
        self.garbage = 0

    def hold(self, bid: int, C: FloatArray) -> None:
        """Block ``bid`` is held with scatter ``C`` (4, 4) (replacing its former one if held)."""
        if not self.held[bid] and not self.spilled[bid]:
            self.held_rows += int(self.size[bid])
        k = int(self.slot[bid])
        if k < 0:  # none, or a spilled one (left behind)
            if self.n_slots == self.scatters.shape[0]:
                grown = np.zeros((max(1024, self.n_slots * 3 // 2), 4, 4))
                grown[: self.n_slots] = self.scatters[: self.n_slots]
                self.scatters = grown
            k = self.n_slots
            self.n_slots += 1
            self.slot[bid] = k
        self.scatters[k] = C
        self.held[bid] = True

    def scatter_of(self, bid: int) -> FloatArray:
        """The scatter (4, 4) of held block ``bid`` (a copy)."""
        assert self.held[bid]
        k = int(self.slot[bid])
        if k >= 0:
            return np.array(self.scatters[k])
        return self.disk.read("scatters", np.array([-2 - k], dtype=np.int64))[0]

    def summarized(self) -> dict[int, FloatArray]:
        """Held (summarised) block id -> its scatter about its plane's anchor (copies, to inspect)."""
        return {int(b): self.scatter_of(int(b)) for b in np.flatnonzero(self.held)}

    def release(self) -> None:
        """No block is held any more (spilled rows stay where they are)."""
        self.held[:] = False
        self.slot[:] = -1
        self.scatters, self.n_slots = np.zeros((0, 4, 4)), 0
        self.held_rows = 0
        self.disk.clear("scatters")

    def spill_if_due(self) -> bool:
        """:meth:`spill` if the held blocks' rows in memory passed ``spill_rows``; whether it did."""
        if self.spill_rows is None or self.held_rows <= self.spill_rows:
            return False
        self.spill()
        return True

    def spill(self) -> None:
        """Move the rows and scatters of every held block in memory to the spill files (in block
        order) and rewrite the rows left in memory."""
        ids = np.flatnonzero(self.held & ~self.spilled)
        if ids.shape[0] == 0:
            return
        pts, al, sg, starts = self.gather(ids)
        first = self.disk.append("points", pts)
        self.disk.append("alphas", al)
        self.disk.append("sigmas", sg)
        with_slot = np.flatnonzero(self.slot >= 0)  # these and spilled blocks held again
        if with_slot.shape[0]:
            k0 = self.disk.append("scatters", self.scatters[self.slot[with_slot]])
            self.slot[with_slot] = -2 - (k0 + np.arange(with_slot.shape[0], dtype=np.int32))
        self.scatters, self.n_slots = np.zeros((0, 4, 4)), 0
        self.start[ids] = first + starts[:-1]
        self.spilled[ids] = True
        self.garbage += int(starts[-1])
        self.held_rows = 0
        self.compact()

    def close(self) -> None:
        """Remove the spill files (the spilled blocks' rows with them: for the end of a run)."""
        self.disk.close()

    def ids(self) -> NDArray[np.int64]:
        """The live block ids, increasing."""
        return np.flatnonzero(self.live)

    def has(self, bid: int) -> bool:
        return 0 <= bid < self.live.shape[0] and bool(self.live[bid])

    def block(self, bid: int) -> ObservationBlock:
        """Live block ``bid`` with its own (copied) arrays."""
        if self.spilled[bid]:
            points, alphas, sigmas, _ = self.gather(np.array([bid], dtype=np.int64))
            return ObservationBlock(int(self.knot[bid]), int(self.plane[bid]), points,
                                    alphas if self.two[bid] else None, sigmas)
        s, e = int(self.start[bid]), int(self.start[bid] + self.size[bid])
        al = self.alphas[s:e].copy() if self.two[bid] else None
        return ObservationBlock(int(self.knot[bid]), int(self.plane[bid]), self.points[s:e].copy(), al,
                                self.sigmas[s:e].copy())

    def gather(self, bids: NDArray[np.int64]) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int64]]:
        """The rows of blocks ``bids`` in that order: points (M, 3), alphas (M,), sigmas (M,) and
        each block's first row in them (len(bids) + 1,)."""
        sizes = self.size[bids]
        starts = np.zeros(bids.shape[0] + 1, dtype=np.int64)
        np.cumsum(sizes, out=starts[1:])
        idx = np.repeat(self.start[bids] - starts[:-1], sizes) + np.arange(int(starts[-1]))
        disk = self.spilled[bids]
        if not disk.any():
            return self.points[idx], self.alphas[idx], self.sigmas[idx], starts
        on_disk = np.repeat(disk, sizes)
        out = []
        for name in ("points", "alphas", "sigmas"):
            mem_rows = getattr(self, name)
            rows = np.empty((idx.shape[0], *mem_rows.shape[1:]))
            rows[~on_disk] = mem_rows[idx[~on_disk]]
            rows[on_disk] = self.disk.read(name, idx[on_disk])
            out.append(rows)
        return out[0], out[1], out[2], starts

    def nbytes(self) -> int:
        """Bytes of the columns in memory (their capacity; the spill files left out)."""
        return sum(getattr(self, n).nbytes for n in ("knot", "plane", "two", "live", "start", "size", "held",
                                                      "slot", "isam", "spilled", "scatters", "points", "alphas",
                                                      "sigmas"))


class BlockView(Mapping[int, ObservationBlock]):
    """The live blocks by id, in increasing id order (each looked up builds its record)."""

    def __init__(self, cols: BlockColumns) -> None:
        self._cols = cols

    def __getitem__(self, bid: int) -> ObservationBlock:
        if not self._cols.has(bid):
            raise KeyError(bid)
        return self._cols.block(bid)

    def __contains__(self, bid: object) -> bool:
        return isinstance(bid, (int, np.integer)) and self._cols.has(int(bid))

    def __iter__(self) -> Iterator[int]:
        return iter(self._cols.ids().tolist())

    def __len__(self) -> int:
        return self._cols.count


class BlockStore:
    """The observation blocks of a :class:`FactorGraph` (block id = its factor id), by plane and
    by knot, with their interval groups and the summaries of the held ones. The blocks' data are
    :class:`BlockColumns`; ``blocks`` is their read-only view by id. A block has no factor record:
    the graph's factors are its records and the live blocks (:meth:`factor_ids`,
    :meth:`factors_of_knots`, :meth:`factor_keys`, :meth:`factor`)."""

    def __init__(self, graph: FactorGraph, kernel: RobustKernel, coalesce: bool) -> None:
        self.graph = graph
        self.kernel = kernel
        self.coalesce = coalesce
        self.cols = BlockColumns()
        self.blocks = BlockView(self.cols)
        alive = self._alive
        self.by_plane = IdLists(alive)  # plane id -> its block ids (every plane has a list)
        self.by_knot = IdLists(alive)  # the highest knot a block touches -> its block ids
        self._factors: dict[int, gtsam.NonlinearFactor] = {}  # block id -> its built factor
        self._open: dict[tuple[int, int, bool], int] = {}  # coalescing: (knot, plane, two poses)
        self._groups: dict[int, tuple[tuple[int, ...], gtsam.NonlinearFactor]] = {}  # knot -> group
        self.summary: dict[int, FloatArray] = {}  # plane id -> scatter M of its summarised blocks
        self.summarized_upto = 0  # blocks whose highest knot is below this are summarised
        self.planes = PlaneTable()  # the planes of the point a solve evaluates the interval factors at
        # plane id -> the plane it was merged into while the walk went on (PlaneTies.fold_links): a
        # caller that still holds the old id reaches the surviving plane
        self.folded: dict[int, int] = {}

    def _alive(self, ids: IntArray) -> NDArray[np.bool_]:
        return self.cols.live[ids]

    @property
    def n_points(self) -> int:
        """Points of the live blocks."""
        return self.cols.n_points

    # ----------------------------------------------------------------- planes
    def add_plane(self, plane_id: int) -> None:
        self.by_plane.add_key(plane_id)

    def check_plane(self, plane_id: int) -> int:
        """``plane_id`` as the id of an existing plane (a plane merged into another by
        :meth:`PlaneTies.fold_links` answers as the one it was merged into)."""
        j = int(plane_id)
        while j in self.folded:
            j = self.folded[j]
        if j not in self.by_plane:
            raise ValueError(f"plane_id: no plane {j}")
        return j

    def plane_ids(self) -> list[int]:
        """The ids of the planes, increasing."""
        return sorted(self.by_plane)

    def of_plane(self, plane_id: int) -> list[int]:
        """Ids of the blocks on a plane, increasing."""
        return self.of_planes([self.check_plane(plane_id)]).tolist()

    def of_planes(self, plane_ids: list[int]) -> IntArray:
        """Ids of the blocks on the planes ``plane_ids`` (existing ones), increasing."""
        parts = [self.by_plane.live(j) for j in plane_ids]
        return np.sort(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)

    def move_plane(self, drop: int, keep: int) -> int:
        """Re-key the blocks of plane ``drop`` onto ``keep`` (same block ids, summaries shifted to
        ``keep``'s anchor) and forget ``drop``; returns the number of moved blocks."""
        anchors = self.graph.anchors
        moved = self.of_plane(drop)
        cols = self.cols
        for bid in moved:
            knot, two = int(cols.knot[bid]), bool(cols.two[bid])
            self._open.pop((knot, drop, two), None)
            self._groups.pop(knot, None)
            cols.plane[bid] = keep
            cols.isam[bid] = -1
            self._factors.pop(bid, None)
            self.by_plane.append(keep, bid)
            if cols.held[bid]:
                C = shift_anchor(cols.scatter_of(bid), anchors[drop], anchors[keep])
                cols.hold(bid, C)
                self.summary[keep] = self.summary.get(keep, np.zeros((4, 4))) + C
        self.summary.pop(drop, None)
        return len(moved)

    def drop_plane(self, plane_id: int) -> None:
        """Forget a plane whose blocks were removed or moved."""
        self.by_plane.pop(plane_id)
        self.summary.pop(plane_id, None)

    # ----------------------------------------------------------------- blocks
    def add(self, knot: int, plane_id: int, points: ArrayLike, alphas: ArrayLike | None,
            sigmas: ArrayLike) -> int:
        """Add a block (see :meth:`Backend.add_observations`); returns its id."""
        block = self._make(knot, plane_id, points, alphas, sigmas)
        key = (block.knot, block.plane_id, block.alphas is not None)
        if self.coalesce and key in self._open:
            old = self.cols.block(self._open[key])
            block = ObservationBlock(
                block.knot, block.plane_id, np.concatenate((old.points, block.points)),
                None if block.alphas is None or old.alphas is None else np.concatenate((old.alphas, block.alphas)),
                np.concatenate((old.sigmas, block.sigmas)))
            self.remove(self._open[key])
        bid = self._insert(block)
        if self.coalesce and not self.cols.held[bid]:
            self._open[key] = bid
        return bid

    def replace(self, block_id: int, points: ArrayLike, alphas: ArrayLike | None, sigmas: ArrayLike) -> int:
        """Replace a block's points (same knot and plane); returns the new block id."""
        if not self.cols.has(block_id):
            raise ValueError(f"block_id: no observation block {block_id}")
        new = self._make(int(self.cols.knot[block_id]), int(self.cols.plane[block_id]), points, alphas, sigmas)
        self.remove(block_id)
        return self._insert(new)

    def remove(self, block_id: int) -> None:
        """Remove a block."""
        if not self.cols.has(block_id):
            raise ValueError(f"block_id: no observation block {block_id}")
        cols = self.cols
        knot, j, two = int(cols.knot[block_id]), int(cols.plane[block_id]), bool(cols.two[block_id])
        C = cols.scatter_of(block_id) if cols.held[block_id] else None
        isam = int(cols.isam[block_id])
        self.graph.removed(None if isam < 0 else isam)
        cols.drop(block_id)
        self._factors.pop(block_id, None)
        self.by_plane.note_dead(j)
        self.by_knot.note_dead(knot + (1 if two else 0))
        key = (knot, j, two)
        if self._open.get(key) == block_id:
            del self._open[key]
        if C is not None:
            self.summary[j] -= C

    def get(self, block_id: int) -> ObservationBlock:
        if not self.cols.has(block_id):
            raise ValueError(f"block_id: no observation block {block_id}")
        return self.cols.block(block_id)

    def _insert(self, block: ObservationBlock) -> int:
        bid = self.graph.new_id()
        self.cols.put(bid, block)
        self.by_plane.append(block.plane_id, bid)
        top = block.knot + (1 if block.alphas is not None else 0)  # the highest knot it touches
        self.by_knot.append(top, bid)
        if top < self.summarized_upto:  # its poses are held by the window already
            self._summarize(bid)
        return bid

    def _make(self, knot: int, plane_id: int, points: ArrayLike, alphas: ArrayLike | None,
              sigmas: ArrayLike) -> ObservationBlock:
        j = self.check_plane(plane_id)
        al = None if alphas is None else np.asarray(alphas, dtype=float).reshape(-1)
        if al is not None and not np.any(al != 0.0):
            al = None
        i = self.graph.check_knot(knot, need_next=al is not None)
        pts = np.ascontiguousarray(points, dtype=float)
        s = np.asarray(sigmas, dtype=float)
        if pts.ndim == 2 and s.ndim == 0:
            s = np.full(pts.shape[0], float(s))
        pts, al, s = check_block(pts, al, s, al is not None, "points_body")
        return ObservationBlock(i, j, pts, al, s)

    # ----------------------------------------------------------------- residuals
    def whitened_residuals(self, blk: ObservationBlock) -> FloatArray:
        """A block's signed point-to-plane residuals over their sigmas at the current estimate."""
        v = self.graph.values
        a = self.graph.anchors.get(blk.plane_id)
        T_b = v.atPose3(X(blk.knot + 1)) if blk.alphas is not None else None
        terms = point_plane_terms(v.atPose3(X(blk.knot)), T_b, v.atOrientedPlane3(P(blk.plane_id)), blk.points,
                                  blk.alphas, jacobians=False, anchor=a)
        return np.asarray(terms.residuals / blk.sigmas)

    def whitened_rows(self) -> tuple[IntArray, FloatArray, FloatArray, FloatArray, FloatArray, IntArray]:
        """Every live block's whitened residuals with its rows (:func:`whitened_rows`)."""
        return whitened_rows(self)

    def all_whitened_residuals(self) -> list[tuple[int, FloatArray]]:
        """(block id, :meth:`whitened_residuals`) of every block, in the store's order
        (:meth:`whitened_rows` split by block)."""
        ids, e, _, _, _, starts = self.whitened_rows()
        return [(b, e[s:t]) for b, s, t in zip(ids.tolist(), starts[:-1].tolist(), starts[1:].tolist(), strict=True)]

    def residuals(self, block_id: int) -> tuple[FloatArray, FloatArray]:
        """Whitened residuals (N,) of a block and the robust weights (N,) its kernel gives them."""
        e = self.whitened_residuals(self.get(block_id))
        return e, robust_weights(e, self.kernel)

    # ----------------------------------------------------------------- factors
    def factor(self, fid: int) -> gtsam.NonlinearFactor:
        """The factor ``fid`` (a record's, or an observation block's: built on first use and kept
        until the block leaves the window or changes)."""
        if not self.cols.has(fid):
            return self.graph.factor(fid)
        f = self._factors.get(fid)
        if f is None:
            f = self._factors[fid] = self.block_factor(self.cols.block(fid))
        return f

    def factor_keys(self, fid: int) -> tuple[int, ...]:
        """The keys of live factor ``fid``."""
        cols = self.cols
        if cols.has(fid):
            return keys_of(int(cols.knot[fid]), bool(cols.two[fid]), int(cols.plane[fid]))
        return self.graph.records[fid].keys

    def factor_ids(self) -> IntArray:
        """The ids of every live factor (records and blocks), increasing."""
        recs = np.fromiter(self.graph.records, dtype=np.int64, count=len(self.graph.records))
        return np.sort(np.concatenate((recs, self.cols.ids())))

    def factors_of_knots(self, a: int, b: int) -> KnotFactors:
        """The live factors whose highest knot is in ``[a, b]`` (so every factor touching a knot
        of ``[a, n)`` for ``b = n - 1``), ordered by highest knot then id; which of them are
        observation blocks (their knot, plane and span in :attr:`cols`) and which records
        (:attr:`FactorGraph.records`)."""
        records, by_knot = self.graph.records, self.graph.by_knot
        ids: list[IntArray] = []
        is_block: list[NDArray[np.bool_]] = []
        top: list[IntArray] = []
        for k in range(a, b + 1):
            recs = np.array([f for f in by_knot.get(k, ()) if f in records], dtype=np.int64)
            blks = self.by_knot.live(k)
            both = np.concatenate((recs, blks))
            order = np.argsort(both, kind="stable")
            ids.append(both[order])
            is_block.append((np.arange(both.shape[0]) >= recs.shape[0])[order])
            top.append(np.full(both.shape[0], k, dtype=np.int64))
        if not ids:
            return KnotFactors(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool))
        return KnotFactors(np.concatenate(ids), np.concatenate(top), np.concatenate(is_block))

    def block_factor(self, blk: ObservationBlock, kernel: RobustKernel | None = None) -> gtsam.NonlinearFactor:
        """A block's own factor, with ``kernel`` (None: the configured one)."""
        kb = X(blk.knot + 1) if blk.alphas is not None else None
        return point_plane_factor(X(blk.knot), kb, P(blk.plane_id), blk.points, blk.alphas, blk.sigmas,
                                  kernel or self.kernel, anchor=self.graph.anchors.get(blk.plane_id))

    def group_factor(self, knot: int, bids: list[int], kernel: RobustKernel | None = None,
                     keep: bool = True) -> gtsam.NonlinearFactor:
        """One factor for the blocks ``bids`` of interval ``knot`` (:func:`point_planes_factor`),
        built from the columns. The factor of the configured kernel is kept (with ``keep``) until
        the interval's blocks change or leave the window (:meth:`hold_before`)."""
        key = tuple(sorted(bids))
        if kernel is None:
            hit = self._groups.get(knot)
            if hit is not None and hit[0] == key:
                return hit[1]
        if len(key) == 1 and kernel is None:
            factor = self.factor(key[0]) if keep else self.block_factor(self.cols.block(key[0]))
        else:
            ids = np.array(key, dtype=np.int64)
            pts, al, sg, starts = self.cols.gather(ids)
            factor = interval_factor(self, knot, ids, pts, al, sg, starts, kernel)
        if kernel is None and keep:
            self._groups[knot] = (key, factor)
        return factor

    def whole_graph(self, kernel: RobustKernel | None = None) -> gtsam.NonlinearFactorGraph:
        """All live factors, the blocks between two knots grouped per interval; blocks rebuilt
        with ``kernel`` if given."""
        graph = gtsam.NonlinearFactorGraph()
        cols = self.cols
        fids = self.factor_ids()
        block = np.zeros(fids.shape[0], dtype=bool)
        inside = fids < cols.live.shape[0]
        block[inside] = cols.live[fids[inside]]
        two = block.copy()
        two[block] = cols.two[fids[block]]
        for fid, blk in zip(fids[~two].tolist(), block[~two].tolist(), strict=True):
            if kernel is not None and blk:
                graph.add(self.block_factor(cols.block(fid), kernel))
            else:
                graph.add(self.factor(fid))
        # the two-pose blocks by interval, the intervals in the order of their first block id
        two_ids = fids[two]
        knots = cols.knot[two_ids]
        order = np.argsort(knots, kind="stable")
        uniq, first, counts = np.unique(knots, return_index=True, return_counts=True)
        bounds = np.concatenate(([0], np.cumsum(counts)))
        intervals = [(int(uniq[u]), two_ids[order[bounds[u]:bounds[u + 1]]].tolist())
                     for u in np.argsort(first, kind="stable").tolist()]
        for factor in group_factors(self, intervals, kernel):
            graph.add(factor)
        return graph

    def drop_group_factors(self) -> None:
        """Forget the interval factors and blocks' factors kept for the next solve (a final
        batch keeps every interval's: 12 kB each)."""
        self._groups.clear()
        self._factors.clear()

    # ----------------------------------------------------------------- summaries
    def hold_before(self, first: int) -> None:
        """Summarise every block of the knots below ``first`` (their poses are held from now on)
        and let go of their factors (built again, the same, if the final batch needs them); the
        held blocks' rows go to disk once there are enough (:meth:`BlockColumns.spill_if_due`)."""
        todo: list[int] = []
        held = self.cols.held
        for k in range(self.summarized_upto, first):
            self.graph.release(k)
            for fid in self.by_knot.live(k).tolist():
                self._factors.pop(fid, None)
                if not held[fid]:
                    todo.append(fid)
        self._summarize_many(todo)
        for knot in [k for k in self._groups if k + 1 < first]:
            del self._groups[knot]
        self.summarized_upto = max(self.summarized_upto, first)
        self.cols.spill_if_due()

    def drop_summaries(self) -> None:
        """Forget the summaries (the held poses have moved)."""
        self.summary, self.summarized_upto = {}, 0
        self.cols.release()

    def _summarize_many(self, bids: list[int]) -> None:
        """:meth:`_summarize` of blocks ``bids`` in that order, the same numbers: the two-pose
        blocks' interpolated poses, world points and robust weights in one pass each (per point
        the same operations), the products that BLAS evaluates (the residuals' dot products, the
        scatters) per block as before."""
        cols = self.cols
        ids = np.array(bids, dtype=np.int64)
        two = ids[cols.two[ids]] if ids.shape[0] else ids
        done: dict[int, FloatArray] = {}
        if two.shape[0]:
            v = self.graph.values
            bknot = cols.knot[two]
            lo, hi = int(bknot.min()), int(bknot.max()) + 1
            T = np.array([v.atPose3(X(k)).matrix() for k in range(lo, hi + 1)])
            pts, al, sg, starts = cols.gather(two)
            R, t = interval_poses(T, np.repeat(bknot - lo, np.diff(starts)), al)
            x = np.einsum("mij,mj->mi", R, pts) + t
            bplane = cols.plane[two]
            rows = {j: plane_row(v, P(j)) for j in set(bplane.tolist())}
            anchors = self.graph.anchors
            e = np.empty(x.shape[0])
            a_rows = np.empty((x.shape[0], 3))
            for j, s, f in zip(bplane.tolist(), starts[:-1].tolist(), starts[1:].tolist(), strict=True):
                n, d, _ = rows[j]
                a = anchors[j]
                e[s:f] = ((x[s:f] - a) @ n + d) / sg[s:f]
                a_rows[s:f] = a
            w = robust_weights(e, self.kernel) / sg**2
            h = np.empty((x.shape[0], 4))
            h[:, :3] = x - a_rows
            h[:, 3] = 1.0
            hw = h * w[:, None]
            for b, s, f in zip(two.tolist(), starts[:-1].tolist(), starts[1:].tolist(), strict=True):
                done[b] = hw[s:f].T @ h[s:f]
        for bid in bids:
            C = done.get(bid)
            if C is None:
                self._summarize(bid)
                continue
            j, knot = int(cols.plane[bid]), int(cols.knot[bid])
            cols.hold(bid, C)
            self.summary[j] = self.summary.get(j, np.zeros((4, 4))) + C
            key = (knot, j, True)
            if self._open.get(key) == bid:
                del self._open[key]

    def _summarize(self, bid: int) -> None:
        """Fold block ``bid`` into its plane's scatter at the current poses (held from now on) and
        robust weights (frozen): see :mod:`slam.backend.plane_summary`."""
        blk = self.cols.block(bid)
        v = self.graph.values
        pts = blk.points
        Ta = v.atPose3(X(blk.knot)).matrix()
        if blk.alphas is None:
            x = pts @ Ta[:3, :3].T + Ta[:3, 3]
        else:
            T = np.stack((Ta, v.atPose3(X(blk.knot + 1)).matrix()))
            R, t = interval_poses(T, np.zeros(pts.shape[0], dtype=np.int64), blk.alphas)
            x = np.einsum("mij,mj->mi", R, pts) + t
        j = blk.plane_id
        a = self.graph.anchors[j]
        pl = v.atOrientedPlane3(P(j))
        e = ((x - a) @ pl.normal().point3() + pl.distance()) / blk.sigmas
        C = scatter(x, a, robust_weights(e, self.kernel) / blk.sigmas**2)
        self.cols.hold(bid, C)
        self.summary[j] = self.summary.get(j, np.zeros((4, 4))) + C
        key = (blk.knot, j, blk.alphas is not None)
        if self._open.get(key) == bid:
            del self._open[key]


def whitened_rows(store: BlockStore) -> tuple[IntArray, FloatArray, FloatArray, FloatArray, FloatArray, IntArray]:
    """Every live block's whitened residuals at the current estimate
    (:meth:`BlockStore.whitened_residuals`, the same numbers) with its rows, the blocks' rows
    gathered once: ``(ids, e, points, alphas, sigmas, starts)``, the blocks in id order, block
    ``ids[i]``'s in ``[starts[i], starts[i + 1])`` (its alphas zero if it has none). The two-pose
    blocks in one compiled pass (each knot and plane read once)."""
    v = store.graph.values
    cols = store.cols
    ids = cols.ids()
    pts, al, sg, starts = cols.gather(ids)
    e = np.empty(pts.shape[0])
    sizes = np.diff(starts)
    is_two = cols.two[ids]
    if is_two.any():
        two = ids[is_two]
        every = bool(is_two.all())  # the usual case: the rows as gathered (a view, no copy)
        rows = slice(None) if every else np.repeat(is_two, sizes)
        sub = starts if every else np.concatenate(([0], np.cumsum(sizes[is_two])))
        bknot, bplane = cols.knot[two], cols.plane[two]
        knots = np.unique(np.concatenate((bknot, bknot + 1)))
        M = np.array([v.atPose3(X(int(k))).matrix() for k in knots])
        planes = np.unique(bplane)
        prow = [plane_row(v, P(int(j))) for j in planes]
        res = _fk.blocks_residuals(
            np.ascontiguousarray(M[:, :3, :3]), np.ascontiguousarray(M[:, :3, 3]),
            np.searchsorted(knots, bknot).astype(np.int64),
            np.array([r[0] for r in prow]), np.array([r[1] for r in prow]), np.array([r[2] for r in prow]),
            np.searchsorted(planes, bplane).astype(np.int64),
            np.array([store.graph.anchors[int(j)] for j in planes]), pts[rows], al[rows], sub)
        e[rows] = res / sg[rows]
    for i in np.flatnonzero(~is_two).tolist():  # from the rows gathered above, not read again
        s, t = int(starts[i]), int(starts[i + 1])
        blk = ObservationBlock(int(cols.knot[ids[i]]), int(cols.plane[ids[i]]), pts[s:t], None, sg[s:t])
        e[s:t] = store.whitened_residuals(blk)
    return ids, e, pts, al, sg, starts


def group_factors(store: BlockStore, intervals: list[tuple[int, list[int]]],
                  kernel: RobustKernel | None) -> list[gtsam.NonlinearFactor]:
    """:meth:`BlockStore.group_factor` of each ``(knot, bids)`` in turn (kept likewise), the rows
    of the intervals not kept gathered at once: one read of the spill files instead of one per
    interval (each factor gets its own copy of its rows, so that none keeps the others')."""
    out: list[gtsam.NonlinearFactor | None] = []
    todo: list[tuple[int, int, NDArray[np.int64]]] = []  # (position, knot, sorted ids)
    for knot, bids in intervals:
        key = tuple(sorted(bids))
        hit = store._groups.get(knot) if kernel is None else None
        if (hit is not None and hit[0] == key) or (len(key) == 1 and kernel is None):
            out.append(store.group_factor(knot, bids, kernel))
        else:
            todo.append((len(out), knot, np.array(key, dtype=np.int64)))
            out.append(None)
    if todo:
        pts, al, sg, starts = store.cols.gather(np.concatenate([ids for _, _, ids in todo]))
        i = 0
        for pos, knot, ids in todo:
            n = ids.shape[0]
            lo, hi = int(starts[i]), int(starts[i + n])
            factor = interval_factor(store, knot, ids, pts[lo:hi].copy(), al[lo:hi].copy(), sg[lo:hi].copy(),
                                     starts[i:i + n + 1] - lo, kernel)
            if kernel is None:
                store._groups[knot] = (tuple(ids.tolist()), factor)
            out[pos] = factor
            i += n
    return [f for f in out if f is not None]


def interval_factors(store: BlockStore, groups: dict[int, list[int]],
                     kernel: RobustKernel) -> list[gtsam.NonlinearFactor]:
    """One factor per interval ``knot -> bids`` (as :meth:`BlockStore.group_factor` with
    ``kernel``, not kept), the rows of all of them gathered at once: one read of the spill files
    for a section of the final batch instead of one per interval."""
    keys = [(knot, np.array(sorted(bids), dtype=np.int64)) for knot, bids in groups.items()]
    if not keys:
        return []
    all_ids = np.concatenate([ids for _, ids in keys])
    pts, al, sg, starts = store.cols.gather(all_ids)
    out = []
    i = 0
    for knot, ids in keys:
        n = ids.shape[0]
        lo, hi = int(starts[i]), int(starts[i + n])
        out.append(interval_factor(store, knot, ids, pts[lo:hi], al[lo:hi], sg[lo:hi], starts[i:i + n + 1] - lo, kernel))
        i += n
    return out


def interval_factor(store: BlockStore, knot: int, ids: NDArray[np.int64], pts: FloatArray, al: FloatArray,
                    sg: FloatArray, starts: NDArray[np.int64], kernel: RobustKernel | None) -> gtsam.NonlinearFactor:
    """The factor of two-pose blocks ``ids`` of interval ``knot`` from their gathered rows
    (``starts``: each block's first row)."""
    cols = store.cols
    assert bool(cols.two[ids].all())
    bplane = cols.plane[ids]
    plane_ids = sorted(set(bplane.tolist()))
    slot = {j: i for i, j in enumerate(plane_ids)}
    index = np.repeat(np.array([slot[j] for j in bplane.tolist()], dtype=np.int64), np.diff(starts))
    return point_planes_factor(
        X(knot), X(knot + 1), [P(j) for j in plane_ids], index, pts, al, sg, kernel or store.kernel,
        np.array([store.graph.anchors[j] for j in plane_ids]), store.planes)


def block_keys(blk: ObservationBlock) -> tuple[int, ...]:
    """The keys of a block's factor (:meth:`BlockStore.block_factor`)."""
    return keys_of(blk.knot, blk.alphas is not None, blk.plane_id)


def keys_of(knot: int, two: bool, plane_id: int) -> tuple[int, ...]:
    """The keys of the factor of a block of interval ``knot`` (``two``: spanning two knots) on a plane."""
    keys = [X(knot)] + ([X(knot + 1)] if two else []) + [P(plane_id)]
    return tuple(int(k) for k in keys)
