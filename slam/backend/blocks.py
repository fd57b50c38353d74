"""Observation blocks: the points seen on one plane during one knot interval, their factors and
the exact summaries of the blocks that left the fixed-lag window.

A block's factor is :func:`slam.backend.factors.point_plane_factor` (per-point robust kernel,
points in the body frame at their beam times). The whole-graph and window solves put the blocks
of one knot interval into one :func:`slam.backend.factors.point_planes_factor` (the same rows,
one Python call per linearisation instead of one per block). A block whose poses the window
holds for good is folded into its plane's scatter (:mod:`slam.backend.plane_summary`).
"""

from __future__ import annotations

from dataclasses import dataclass

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
from slam.backend.graph import FactorGraph, Record
from slam.backend.plane_summary import scatter, shift_anchor
from slam.trajectory.placement import interval_poses

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ObservationBlock:
    """Points (N, 3) of plane ``plane_id`` seen during knot interval ``knot`` (body frame at their
    beam times), their interval fractions (N,) (None: at the knot itself) and sigmas (N,) [m]."""

    knot: int
    plane_id: int
    points: FloatArray
    alphas: FloatArray | None
    sigmas: FloatArray


class BlockStore:
    """The observation blocks of a :class:`FactorGraph` (block id = its factor id), by plane,
    with their interval groups and the summaries of the held ones."""

    def __init__(self, graph: FactorGraph, kernel: RobustKernel, coalesce: bool) -> None:
        self.graph = graph
        self.kernel = kernel
        self.coalesce = coalesce
        self.blocks: dict[int, ObservationBlock] = {}
        self.plane_blocks: dict[int, set[int]] = {}  # plane id -> its block ids (every plane)
        self._open: dict[tuple[int, int, bool], int] = {}  # coalescing: (knot, plane, two poses)
        self._groups: dict[int, tuple[tuple[int, ...], gtsam.NonlinearFactor]] = {}  # knot -> group
        self.summary: dict[int, FloatArray] = {}  # plane id -> scatter M of its summarised blocks
        self.summarized: dict[int, FloatArray] = {}  # block id -> its scatter (its plane's anchor)
        self.summarized_upto = 0  # blocks whose highest knot is below this are summarised
        self.planes = PlaneTable()  # the planes of the point a solve evaluates the interval factors at

    # ----------------------------------------------------------------- planes
    def add_plane(self, plane_id: int) -> None:
        self.plane_blocks[plane_id] = set()

    def check_plane(self, plane_id: int) -> int:
        """``plane_id`` as the id of an existing plane."""
        j = int(plane_id)
        if j not in self.plane_blocks:
            raise ValueError(f"plane_id: no plane {j}")
        return j

    def of_plane(self, plane_id: int) -> list[int]:
        """Ids of the blocks on a plane."""
        return sorted(self.plane_blocks[self.check_plane(plane_id)])

    def move_plane(self, drop: int, keep: int) -> int:
        """Re-key the blocks of plane ``drop`` onto ``keep`` (same block ids, summaries shifted to
        ``keep``'s anchor) and forget ``drop``; returns the number of moved blocks."""
        anchors = self.graph.anchors
        moved = sorted(self.plane_blocks[drop])
        for bid in moved:
            old = self.blocks[bid]
            self._open.pop((old.knot, drop, old.alphas is not None), None)
            new = ObservationBlock(old.knot, keep, old.points, old.alphas, old.sigmas)
            self._groups.pop(old.knot, None)
            self.graph.records[bid] = Record(None, block_keys(new), None)
            self.blocks[bid] = new
            self.plane_blocks[keep].add(bid)
            C = self.summarized.get(bid)
            if C is not None:
                C = shift_anchor(C, anchors[drop], anchors[keep])
                self.summarized[bid] = C
                self.summary[keep] = self.summary.get(keep, np.zeros((4, 4))) + C
        self.summary.pop(drop, None)
        return len(moved)

    def drop_plane(self, plane_id: int) -> None:
        """Forget a plane whose blocks were removed or moved."""
        del self.plane_blocks[plane_id]
        self.summary.pop(plane_id, None)

    # ----------------------------------------------------------------- blocks
    def add(self, knot: int, plane_id: int, points: ArrayLike, alphas: ArrayLike | None,
            sigmas: ArrayLike) -> int:
        """Add a block (see :meth:`Backend.add_observations`); returns its id."""
        block = self._make(knot, plane_id, points, alphas, sigmas)
        key = (block.knot, block.plane_id, block.alphas is not None)
        if self.coalesce and key in self._open:
            old = self.blocks[self._open[key]]
            block = ObservationBlock(
                block.knot, block.plane_id, np.concatenate((old.points, block.points)),
                None if block.alphas is None or old.alphas is None else np.concatenate((old.alphas, block.alphas)),
                np.concatenate((old.sigmas, block.sigmas)))
            self.remove(self._open[key])
        bid = self._insert(block)
        if self.coalesce and bid not in self.summarized:
            self._open[key] = bid
        return bid

    def replace(self, block_id: int, points: ArrayLike, alphas: ArrayLike | None, sigmas: ArrayLike) -> int:
        """Replace a block's points (same knot and plane); returns the new block id."""
        old = self.get(block_id)
        new = self._make(old.knot, old.plane_id, points, alphas, sigmas)
        self.remove(block_id)
        return self._insert(new)

    def remove(self, block_id: int) -> None:
        """Remove a block."""
        blk = self.get(block_id)
        self.graph.remove_factor(block_id)
        del self.blocks[block_id]
        self.plane_blocks[blk.plane_id].discard(block_id)
        key = (blk.knot, blk.plane_id, blk.alphas is not None)
        if self._open.get(key) == block_id:
            del self._open[key]
        C = self.summarized.pop(block_id, None)
        if C is not None:
            self.summary[blk.plane_id] -= C

    def get(self, block_id: int) -> ObservationBlock:
        if block_id not in self.blocks:
            raise ValueError(f"block_id: no observation block {block_id}")
        return self.blocks[block_id]

    def _insert(self, block: ObservationBlock) -> int:
        bid = self.graph.add_record(None, block_keys(block))
        self.blocks[bid] = block
        self.plane_blocks[block.plane_id].add(bid)
        top = block.knot + (1 if block.alphas is not None else 0)  # the highest knot it touches
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

    def all_whitened_residuals(self) -> list[tuple[int, FloatArray]]:
        """(block id, :meth:`whitened_residuals`) of every block, in the store's order: the
        two-pose blocks in one compiled pass (each knot and plane read once), the same numbers."""
        v = self.graph.values
        two = [b for b, blk in self.blocks.items() if blk.alphas is not None]
        out: dict[int, FloatArray] = {}
        if two:
            blks = [self.blocks[b] for b in two]
            knots = sorted({k for blk in blks for k in (blk.knot, blk.knot + 1)})
            krow = {k: i for i, k in enumerate(knots)}
            M = np.array([v.atPose3(X(k)).matrix() for k in knots])
            planes = sorted({blk.plane_id for blk in blks})
            prow = {j: i for i, j in enumerate(planes)}
            rows = [plane_row(v, P(j)) for j in planes]
            sizes = np.array([blk.points.shape[0] for blk in blks], dtype=np.int64)
            starts = np.zeros(len(blks) + 1, dtype=np.int64)
            np.cumsum(sizes, out=starts[1:])
            res = _fk.blocks_residuals(
                np.ascontiguousarray(M[:, :3, :3]), np.ascontiguousarray(M[:, :3, 3]),
                np.array([krow[blk.knot] for blk in blks], dtype=np.int64),
                np.array([r[0] for r in rows]), np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                np.array([prow[blk.plane_id] for blk in blks], dtype=np.int64),
                np.array([self.graph.anchors[j] for j in planes]),
                np.concatenate([blk.points for blk in blks]),
                np.concatenate([blk.alphas for blk in blks]), starts)  # type: ignore[misc]
            for b, blk, s, e in zip(two, blks, starts[:-1], starts[1:], strict=True):
                out[b] = res[s:e] / blk.sigmas
        return [(b, out[b] if b in out else self.whitened_residuals(blk)) for b, blk in self.blocks.items()]

    def residuals(self, block_id: int) -> tuple[FloatArray, FloatArray]:
        """Whitened residuals (N,) of a block and the robust weights (N,) its kernel gives them."""
        e = self.whitened_residuals(self.get(block_id))
        return e, robust_weights(e, self.kernel)

    # ----------------------------------------------------------------- factors
    def factor(self, fid: int) -> gtsam.NonlinearFactor:
        """The factor of record ``fid`` (an observation block's built on first use)."""
        rec = self.graph.records[fid]
        if rec.factor is None:
            rec.factor = self.block_factor(self.blocks[fid])
        return rec.factor

    def block_factor(self, blk: ObservationBlock, kernel: RobustKernel | None = None) -> gtsam.NonlinearFactor:
        """A block's own factor, with ``kernel`` (None: the configured one)."""
        kb = X(blk.knot + 1) if blk.alphas is not None else None
        return point_plane_factor(X(blk.knot), kb, P(blk.plane_id), blk.points, blk.alphas, blk.sigmas,
                                  kernel or self.kernel, anchor=self.graph.anchors.get(blk.plane_id))

    def group_factor(self, knot: int, bids: list[int], kernel: RobustKernel | None = None) -> gtsam.NonlinearFactor:
        """One factor for the blocks ``bids`` of interval ``knot`` (:func:`point_planes_factor`).
        The factor of the configured kernel is kept until the interval's blocks change."""
        key = tuple(sorted(bids))
        if kernel is None:
            hit = self._groups.get(knot)
            if hit is not None and hit[0] == key:
                return hit[1]
        blks = [self.blocks[b] for b in key]
        if len(blks) == 1 and kernel is None:
            factor = self.factor(key[0])
        else:
            plane_ids = sorted({b.plane_id for b in blks})
            slot = {j: i for i, j in enumerate(plane_ids)}
            alphas = [b.alphas for b in blks]
            assert all(a is not None for a in alphas)
            factor = point_planes_factor(
                X(knot), X(knot + 1), [P(j) for j in plane_ids],
                np.concatenate([np.full(b.points.shape[0], slot[b.plane_id]) for b in blks]),
                np.concatenate([b.points for b in blks]), np.concatenate(alphas),  # type: ignore[arg-type]
                np.concatenate([b.sigmas for b in blks]), kernel or self.kernel,
                np.array([self.graph.anchors[j] for j in plane_ids]), self.planes)
        if kernel is None:
            self._groups[knot] = (key, factor)
        return factor

    def whole_graph(self, kernel: RobustKernel | None = None) -> gtsam.NonlinearFactorGraph:
        """All live factors, the blocks between two knots grouped per interval; blocks rebuilt
        with ``kernel`` if given."""
        graph = gtsam.NonlinearFactorGraph()
        groups: dict[int, list[int]] = {}
        for fid in sorted(self.graph.records):
            blk = self.blocks.get(fid)
            if blk is not None and blk.alphas is not None:
                groups.setdefault(blk.knot, []).append(fid)
            elif kernel is not None and blk is not None:
                graph.add(self.block_factor(blk, kernel))
            else:
                graph.add(self.factor(fid))
        for knot, bids in groups.items():
            graph.add(self.group_factor(knot, bids, kernel))
        return graph

    # ----------------------------------------------------------------- summaries
    def hold_before(self, first: int) -> None:
        """Summarise every block of the knots below ``first`` (their poses are held from now on)."""
        for k in range(self.summarized_upto, first):
            for fid in self.graph.by_knot.get(k, ()):
                if fid in self.blocks and fid not in self.summarized:
                    self._summarize(fid)
        self.summarized_upto = max(self.summarized_upto, first)

    def drop_summaries(self) -> None:
        """Forget the summaries (the held poses have moved)."""
        self.summary, self.summarized, self.summarized_upto = {}, {}, 0

    def _summarize(self, bid: int) -> None:
        """Fold block ``bid`` into its plane's scatter at the current poses (held from now on) and
        robust weights (frozen): see :mod:`slam.backend.plane_summary`."""
        blk = self.blocks[bid]
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
        self.summarized[bid] = C
        self.summary[j] = self.summary.get(j, np.zeros((4, 4))) + C
        key = (blk.knot, j, blk.alphas is not None)
        if self._open.get(key) == bid:
            del self._open[key]


def block_keys(blk: ObservationBlock) -> tuple[int, ...]:
    """The keys of a block's factor (:meth:`BlockStore.block_factor`)."""
    keys = [X(blk.knot)] + ([X(blk.knot + 1)] if blk.alphas is not None else []) + [P(blk.plane_id)]
    return tuple(int(k) for k in keys)
