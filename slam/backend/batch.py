"""Batch solves over the whole graph, and the trim of the points that do not fit their plane.

A solve is :func:`slam.backend.solver.solve` (damped Gauss-Newton with a Levenberg-Marquardt
fallback) with the configured iterations and tolerance; the singular systems it met are kept
for the run's statistics. The fixed-lag window (:mod:`slam.backend.incremental`) solves with it too.
"""

from __future__ import annotations

import time as _time
from collections.abc import Sequence

import gtsam
import numpy as np

from slam.backend.blocks import BlockStore
from slam.backend.config import BackendConfig, OptimizeSummary
from slam.backend.factors import RobustKernel
from slam.backend.graph import FactorGraph, name_keys
from slam.backend.solver import Solution, solve


class BatchSolver:
    """Whole-graph solves and the trim of a :class:`FactorGraph` and its blocks."""

    def __init__(self, graph: FactorGraph, blocks: BlockStore, config: BackendConfig) -> None:
        self.graph = graph
        self.blocks = blocks
        self.config = config
        self.singular_systems: list[str] = []  # singular linear systems the solves met (retried damped)

    def solve(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int | None,
              fixed: Sequence[int] = (), relative_tolerance: float | None = None) -> Solution:
        """:func:`slam.backend.solver.solve` with the configured iterations (unless given) and
        tolerance (unless given: the window's ``lm_relative_tolerance``), ``fixed`` keys held; a
        failure of its Levenberg-Marquardt fallback is a ValueError naming the variable."""
        n_max = max_iterations or self.config.lm_max_iterations
        tol = self.config.lm_relative_tolerance if relative_tolerance is None else relative_tolerance
        try:
            sol = solve(graph, values, n_max, tol, fixed, self.blocks.planes)
            self.singular_systems.extend(name_keys(m) for m in sol.singular)
            return sol
        except RuntimeError as err2:
            raise ValueError(f"batch optimisation failed ({name_keys(str(err2))}); is every "
                             "variable constrained by its factors?") from None

    def optimize(self, max_iterations: int | None, graduated: bool, kernel: RobustKernel | None) -> OptimizeSummary:
        """See :meth:`Backend.batch_optimize`."""
        cfg = self.config
        own = kernel is None or kernel == cfg.kernel
        kernel = cfg.kernel if kernel is None else kernel
        graph = self.blocks.whole_graph() if own else self.blocks.whole_graph(kernel=kernel)
        values = self.graph.used_values(graph)
        robust = graduated and kernel.name != "none" and bool(self.blocks.blocks)
        scales = list(cfg.robust_schedule) if robust else []
        # the nominal graph's errors before and after: the solve of the nominal graph has them
        # (its first linearisation's, its last accepted step's) unless graduated stages precede it
        e0 = graph.error(values) if scales else None
        t0 = _time.perf_counter()
        iterations = 0
        for scale in [*scales, 1.0]:
            g = graph
            if scale != 1.0:
                g = self.blocks.whole_graph(kernel=RobustKernel(kernel.name, kernel.threshold * scale))
            sol = self.solve(g, values, max_iterations, relative_tolerance=cfg.batch_relative_tolerance)
            values = sol.values
            iterations += sol.iterations
        self.graph.values.update(values)
        self.graph.restructure()
        self.blocks.drop_summaries()  # the held poses have moved
        return OptimizeSummary(float(sol.initial_error if e0 is None else e0), float(sol.final_error), iterations,
                               _time.perf_counter() - t0)

    def error(self) -> float:
        """Total graph error (0.5 sum of whitened squares, robust losses) at the current estimate."""
        graph = self.blocks.whole_graph()
        return float(graph.error(self.graph.used_values(graph)))

    def trim(self, max_whitened: float, min_distance: float) -> tuple[int, int]:
        """See :meth:`Backend.trim_observations`."""
        if not (max_whitened > 0.0 and min_distance >= 0.0):
            raise ValueError(f"trim thresholds: expected > 0 and >= 0, got {max_whitened}, {min_distance}")
        n_points = n_blocks = 0
        # every block's test in one pass over its gathered rows (elementwise: the same numbers as
        # block by block); the blocks with a point out are changed in id order
        bids, e_all, pts, al, sigmas, starts = self.blocks.whitened_rows()
        if not bids.shape[0]:
            return 0, 0
        out_all = (np.abs(e_all) > max_whitened) & (np.abs(e_all) * sigmas > min_distance)
        hit = np.logical_or.reduceat(out_all, starts[:-1])
        two = self.blocks.cols.two[bids]
        for i in np.flatnonzero(hit).tolist():
            bid = int(bids[i])
            s, e = int(starts[i]), int(starts[i + 1])
            keep = ~out_all[s:e]
            n_points += int(e - s - keep.sum())
            n_blocks += 1
            if not keep.any():
                self.blocks.remove(bid)
            else:
                self.blocks.replace(bid, pts[s:e][keep], al[s:e][keep] if two[i] else None, sigmas[s:e][keep])
        return n_points, n_blocks
