"""The incremental solver that keeps the estimate current while the walk is read: one interface,
two implementations, chosen by ``BackendConfig.solver`` in :func:`make_incremental`.

* :class:`WindowSolver` (``"window"``): a fixed-lag window solved to convergence; the blocks of
  older knots enter as one exact summary per plane, so a solve costs what the window holds.
* :class:`Isam2Solver` (``"isam2"``): gtsam's iSAM2 over every factor, updated with what was added
  or removed since the last step (its cost grows with the walk).

Both leave the full problem to a final batch (:mod:`slam.backend.batch`).
"""

from __future__ import annotations

import time as _time
from typing import Protocol, runtime_checkable

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, P, V, X
from numpy.typing import NDArray

from slam.backend.batch import BatchSolver
from slam.backend.blocks import BlockStore
from slam.backend.config import BackendConfig, OptimizeSummary, StepReport
from slam.backend.graph import FactorGraph, copy_value, name_keys
from slam.backend.plane_summary import plane_summary_factor

FloatArray = NDArray[np.float64]


@runtime_checkable
class IncrementalSolver(Protocol):
    """What the back end asks of an incremental solver."""

    def step(self) -> StepReport:
        """Bring the estimate up to date with everything added or removed since the last step
        (nothing to do before the second knot)."""
        ...

    def marginal_covariance(self, key: int) -> FloatArray | None:
        """The marginal covariance of variable ``key`` if the solver holds it for the current
        graph and estimate, else None."""
        ...


class WindowSolver:
    """Fixed-lag window over the newest ``config.window_knots + 1`` knots."""

    def __init__(self, graph: FactorGraph, blocks: BlockStore, batch: BatchSolver, config: BackendConfig) -> None:
        self.graph = graph
        self.blocks = blocks
        self.batch = batch
        self.config = config
        # plane id -> (the summary's matrix, its factor): kept while the summary is unchanged
        self._summaries: dict[int, tuple[FloatArray, gtsam.NonlinearFactor]] = {}

    def step(self) -> StepReport:
        n = len(self.graph.times)
        if n < 2:
            return StepReport(False, 0, 0)
        self.optimize(n - 1 - self.config.window_knots, self.config.window_iterations)
        return StepReport(True, 0, 0)

    def marginal_covariance(self, key: int) -> FloatArray | None:
        return None

    def optimize(self, first_knot: int, max_iterations: int) -> OptimizeSummary:
        """A fixed-lag step: solve (:meth:`BatchSolver.solve`) for the knots from ``first_knot`` on
        (poses, velocities, biases) and every plane they observe, with every factor touching
        those knots and the planes' priors and ties; older variables those factors reach are held
        at their estimates. The observation blocks of older knots enter as one exact summary per
        plane (:mod:`slam.backend.plane_summary`, taken when a block leaves the window: its poses
        are held from then on). The window never reopens summarised knots (``first_knot`` is
        raised to them). Loop closures reach the old knots in the final batch, which drops the
        summaries."""
        t0 = _time.perf_counter()
        fg, blocks = self.graph, self.blocks
        n = len(fg.times)
        first = max(0, min(int(first_knot), n - 1))
        blocks.hold_before(first)
        first = min(blocks.summarized_upto, n - 1)
        active: set[int] = set()
        for k in range(first, n):
            for sym in (X, V, B):
                key = int(sym(k))
                if fg.values.exists(key):
                    active.add(key)
        graph = gtsam.NonlinearFactorGraph()
        used: set[int] = set()
        planes: set[int] = set()
        groups: dict[int, list[int]] = {}
        cols = blocks.cols
        ids, _, is_block = blocks.factors_of_knots(first, n - 1)
        block_ids = ids[is_block]
        bknot, two = cols.knot[block_ids], cols.two[block_ids]
        planes.update(cols.plane[block_ids].tolist())
        used.update(int(X(k)) for k in np.unique(np.concatenate((bknot, bknot[two] + 1))).tolist())
        used.update(int(P(j)) for j in planes)
        knot_of = dict(zip(block_ids.tolist(), bknot.tolist(), strict=True))
        two_of = dict(zip(block_ids.tolist(), two.tolist(), strict=True))
        for fid, blk in zip(ids.tolist(), is_block.tolist(), strict=True):
            if not blk:
                used.update(fg.records[fid].keys)
            elif two_of[fid]:
                groups.setdefault(knot_of[fid], []).append(fid)
                continue
            graph.add(blocks.factor(fid))
        for knot, bids in groups.items():
            graph.add(blocks.group_factor(knot, bids))
        active.update(int(P(j)) for j in planes)
        for fid in fg.knotless:
            rec = fg.records.get(fid)
            if rec is not None and any(k in active for k in rec.keys):
                graph.add(blocks.factor(fid))
                used.update(rec.keys)
        for j in sorted(planes):
            M = blocks.summary.get(j)
            if M is not None:
                hit = self._summaries.get(j)
                if hit is None or not np.array_equal(hit[0], M):  # built again only when it changed
                    hit = (M.copy(), plane_summary_factor(int(P(j)), M))
                    self._summaries[j] = hit
                graph.add(hit[1])
        fg.knotless = [fid for fid in fg.knotless if fid in fg.records]
        values = fg.values.extract(sorted(used))
        fixed = sorted(used - active)
        sol = self.batch.solve(graph, values, max_iterations, fixed=fixed)
        fg.values.update(sol.values.extract(sorted(active & used)))
        fg.pending, fg.pending_removals = [], []
        fg.restructure()
        return OptimizeSummary(float(sol.initial_error), float(sol.final_error), sol.iterations,
                               _time.perf_counter() - t0)


class Isam2Solver:
    """gtsam's iSAM2, rebuilt from the current estimate after a change it cannot follow
    (``FactorGraph.epoch``). A variable enters iSAM2 with its first factor, so a plane needs
    enough observations to fix it (two non-parallel lines) before the step after its creation."""

    def __init__(self, graph: FactorGraph, blocks: BlockStore, batch: BatchSolver, config: BackendConfig) -> None:
        self.graph = graph
        self.blocks = blocks
        self.batch = batch
        self.config = config
        self._isam: gtsam.ISAM2 | None = None
        self._keys: set[int] = set()  # variables iSAM2 holds
        self._epoch = -1  # the graph's epoch iSAM2 was built at
        self._fresh_at = -1  # the graph's version after the last update

    def step(self) -> StepReport:
        """An :meth:`update` of ``config.isam2_iterations``; if it fails numerically (an
        indeterminate system that the same graph relinearised from scratch factors fine) once
        more after a rebuild, and if that fails too, ``config.isam2_fallback_iterations`` batch
        iterations over the whole graph (iSAM2 restarts from their result)."""
        if len(self.graph.times) < 2:
            return StepReport(False, 0, 0)
        rebuilds = fallbacks = 0
        try:
            self.update(self.config.isam2_iterations)
        except ValueError:
            rebuilds = 1
            try:
                self.update()
            except ValueError:
                fallbacks = 1
                self.batch.optimize(self.config.isam2_fallback_iterations, graduated=False, kernel=None)
        return StepReport(True, rebuilds, fallbacks)

    def marginal_covariance(self, key: int) -> FloatArray | None:
        fresh = self._isam is not None and self._epoch == self.graph.epoch and self._fresh_at == self.graph.version
        return np.asarray(self._isam.marginalCovariance(key)) if fresh else None  # type: ignore[union-attr]

    def update(self, iterations: int = 1) -> None:
        """Incremental iSAM2 step(s) with everything added or removed since the last call; a
        failure is a ValueError naming the variable (iSAM2 is rebuilt at the next call)."""
        fg = self.graph
        if self._isam is None or self._epoch != fg.epoch:
            self._rebuild()
        assert self._isam is not None
        graph = gtsam.NonlinearFactorGraph()
        new_values = gtsam.Values()
        ids: list[int] = []
        for fid in fg.pending:
            if not (self.blocks.cols.has(fid) or fid in fg.records):  # removed since
                continue
            graph.add(self.blocks.factor(fid))
            ids.append(fid)
            for k in self.blocks.factor_keys(fid):
                if k not in self._keys and not new_values.exists(k):
                    copy_value(new_values, fg.values, k)
        removals = list(fg.pending_removals)
        try:
            result = self._isam.update(graph, new_values, removals)
            for _ in range(max(iterations, 1) - 1):
                self._isam.update()
        except RuntimeError as err:
            self._isam = None  # its state is undefined after a failed update
            raise ValueError(f"iSAM2 update failed ({name_keys(str(err))}); is every new "
                             "variable constrained by its factors?") from None
        cols = self.blocks.cols
        for fid, idx in zip(ids, result.getNewFactorsIndices(), strict=True):
            if cols.has(fid):  # an observation block: its index is a column
                cols.isam[fid] = int(idx)
            else:
                fg.records[fid].isam_index = int(idx)
        self._keys.update(int(k) for k in new_values.keys())
        fg.pending, fg.pending_removals = [], []
        fg.values.update(self._isam.calculateEstimate())
        fg.version += 1
        self._fresh_at = fg.version

    def _rebuild(self) -> None:
        params = gtsam.ISAM2Params()
        # planes (and IMU velocities/biases) are tied to thousands of factors: relinearising one
        # re-eliminates most of the tree, so they get a coarser threshold than the poses
        thr = self.config.relinearize_threshold
        tmap = gtsam.ISAM2ThresholdMap()
        for char, value in (("x", np.full(6, thr)),
                            ("p", np.full(3, thr * self.config.plane_relinearize_factor)),
                            ("v", np.full(3, 0.01)), ("b", np.full(6, 1e-3))):
            tmap.insert((char, value))
        params.setRelinearizeThreshold(tmap)
        params.relinearizeSkip = self.config.relinearize_skip
        self._isam = gtsam.ISAM2(params)
        self._keys = set()
        self._epoch = self.graph.epoch
        for rec in self.graph.records.values():
            rec.isam_index = None
        self.blocks.cols.isam[:] = -1
        self.graph.pending = self.blocks.factor_ids().tolist()
        self.graph.pending_removals = []


def make_incremental(config: BackendConfig, graph: FactorGraph, blocks: BlockStore,
                     batch: BatchSolver) -> IncrementalSolver:
    """The incremental solver ``config.solver`` names."""
    if config.solver == "window":
        return WindowSolver(graph, blocks, batch, config)
    return Isam2Solver(graph, blocks, batch, config)
