"""Batch solving of a gtsam factor graph: a lightly damped Gauss-Newton driven from Python.

gtsam's own optimizers spend most of their time outside the Python CustomFactors on the graphs
of this project (~2 s per iteration of a 400-knot SLAM graph where ``linearize`` + ``optimize`` +
``error`` take 0.6 s; docs/bench_slam.md), so the steps are taken here: linearise, add a whisper
of Levenberg damping (1e-4 on the whitened Hessian's diagonal, so that a direction no factor
observes stays regular), solve, and halve a step that raises the (robust) error, up to ten times.
A linear system that the elimination finds singular (tight ties beside weak directions) is solved
again with the damping raised a hundredfold, up to ``MAX_DAMPING``: Levenberg-Marquardt's remedy
in the same fast loop. Shared by the SLAM back end and the calibration batch.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from slam.backend.factors import PlaneTable

FloatArray = NDArray[np.float64]

DAMPING = 1e-2  # on the whitened Jacobian: 1e-4 on the Hessian's diagonal
MAX_DAMPING = 1e2  # the largest damping a singular system is retried with
HOLD = 1e6  # "damping" of held variables: their steps stay at zero
FALLBACK_SECONDS = 120.0  # wall-time bound of the Levenberg-Marquardt fallback


@dataclass(frozen=True)
class Solution:
    """A solve's result: the values, the iterations taken, the graph error before and after."""

    values: gtsam.Values
    iterations: int
    initial_error: float
    final_error: float
    singular: tuple[str, ...] = ()  # the elimination errors met (each retried with more damping)


def damped_gauss_newton(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int,
                        relative_tolerance: float, fixed: Sequence[int] = ()) -> tuple[gtsam.Values, int]:
    """Solve from ``values``; returns the solution and the iterations taken (see :func:`solve`)."""
    s = solve(graph, values, max_iterations, relative_tolerance, fixed)
    return s.values, s.iterations


def damping_rows(dims: Sequence[tuple[int, int]], hold: set[int], damping: float,
                 cache: bool = True) -> gtsam.GaussianFactorGraph:
    """One factor per variable (key, dimension): ``damping * I`` rows (``HOLD`` for the keys in
    ``hold``) with zero right-hand side. ``cache``: keep the factors for the next call (the
    window's variables); off for rows used once (a section of the final batch)."""
    out = gtsam.GaussianFactorGraph()
    if not cache:
        parts: dict[tuple[int, float], tuple[FloatArray, FloatArray, gtsam.noiseModel.Diagonal]] = {}
        for k, d in dims:
            w = HOLD if k in hold else damping
            p = parts.get((d, w))
            if p is None:
                p = parts[(d, w)] = (w * np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d))
            out.add(gtsam.JacobianFactor(k, p[0], p[1], p[2]))
        return out
    for k, d in dims:
        w = HOLD if k in hold else damping
        f = _DAMPING_FACTORS.get((k, d, w))
        if f is None:  # (elimination leaves its input factors as they are: one object serves every solve)
            f = gtsam.JacobianFactor(k, w * np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d))
            if len(_DAMPING_FACTORS) >= _DAMPING_CACHE:
                _DAMPING_FACTORS.clear()
            _DAMPING_FACTORS[(k, d, w)] = f
        out.add(f)
    return out


# damping factors kept (key, dimension, weight), cleared when full: enough for the window's
# variables at a few damping levels; each costs ~1.8 kB, so 200,000 of them (an hour's knots)
# held ~360 MB
_DAMPING_CACHE = 8192
_DAMPING_FACTORS: dict[tuple[int, int, float], gtsam.JacobianFactor] = {}


def predicted_end(error: float, predicted_decrease: float, relative_tolerance: float) -> bool:
    """Whether a Gauss-Newton step whose linear model lowers ``error`` by ``predicted_decrease``
    is expected to end a solve that stops below ``relative_tolerance`` (the relative decrease).
    Near convergence the error falls by what the model predicts (its ratio is close to 1), so a
    step predicted to fall short of the tolerance by ``PREDICTED_END_MARGIN`` is expected to be
    the last."""
    return predicted_decrease < PREDICTED_END_MARGIN * relative_tolerance * max(error, 1e-300)


# a step whose model decrease falls below this fraction of the stopping rule's is taken as the
# last: the robust kernels' model underestimates the decrease (office walk, final batch: the error
# fell by 1.2-1.9 times the predicted amount)
PREDICTED_END_MARGIN = 0.5


class _Evaluator:
    """The graph's linearisation and error at a point, with the plane table (if any) serving
    that point's planes meanwhile."""

    def __init__(self, graph: gtsam.NonlinearFactorGraph, table: PlaneTable | None) -> None:
        self.graph, self.table = graph, table

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        if self.table is None:
            return self.graph.linearize(values)
        self.table.at(values)
        try:
            return self.graph.linearize(values)
        finally:
            self.table.at(None)

    def error(self, values: gtsam.Values) -> float:
        if self.table is None:
            return float(self.graph.error(values))
        self.table.at(values)
        try:
            return float(self.graph.error(values))
        finally:
            self.table.at(None)


def solve(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int,
          relative_tolerance: float, fixed: Sequence[int] = (), table: PlaneTable | None = None) -> Solution:
    """Solve from ``values``. Stops when no step lowers the error or the relative decrease falls
    below ``relative_tolerance``. Variables in ``fixed`` (keys) are held at their values. A
    singular linear system is solved again with a hundredfold damping (a tenth of it taken
    off again after each accepted step), up to ``MAX_DAMPING``; beyond it, or when a linearisation fails, the solve falls
    back to gtsam's Levenberg-Marquardt (without held variables), iterated until it converges,
    ``max_iterations`` or ``FALLBACK_SECONDS``; its failure raises RuntimeError. ``table``: the
    plane table of the graph's interval factors (:class:`slam.backend.factors.PlaneTable`),
    serving each linearisation point's planes."""
    ev = _Evaluator(graph, table)
    hold = {int(k) for k in fixed}
    dims = [(int(k), int(d)) for k, d in values.dims().items()]
    zero = values.zeroVectors()
    err0 = err = float("nan")
    singular: list[str] = []
    damping = DAMPING
    try:
        # a linearisation's 0.5 ||b||^2 is the graph's error at its point (the robust blocks carry
        # a correction row: slam.backend.factors.robust_rows), so an accepted step's linearisation also
        # gives its error
        lin: gtsam.GaussianFactorGraph | None = ev.linearize(values)
        assert lin is not None
        err0 = err = lin.error(zero)
        # the damping rows of each damping level, and the elimination ordering (the same
        # structure at every iteration: COLAMD once), kept for the whole solve
        damped: dict[float, gtsam.GaussianFactorGraph] = {}
        ordering: gtsam.Ordering | None = None
        it = 0
        for it in range(1, max_iterations + 1):
            delta = None
            while delta is None:
                if lin is None:
                    lin = ev.linearize(values)
                if damping not in damped:
                    damped[damping] = damping_rows(dims, hold, damping)
                lin.push_back(damped[damping])
                if ordering is None:
                    ordering = gtsam.Ordering.ColamdGaussianFactorGraph(lin)
                try:
                    delta = lin.optimize(ordering)
                    model = lin
                except RuntimeError as e:
                    if damping * 100.0 > MAX_DAMPING:
                        raise
                    singular.append(" ".join(str(e).split())[:300])
                    damping *= 100.0
                lin = None
            # a step the linear model says ends the solve is judged by the error alone: the
            # linearisation at it would be thrown away (linearised after all if it does not end it)
            last = it == max_iterations or predicted_end(err, err - model.error(delta), relative_tolerance)
            del model
            step = 1.0
            for _ in range(10):
                trial = values.retract(delta if step == 1.0 else delta.scale(step))
                lin_trial: gtsam.GaussianFactorGraph | None = None
                if step == 1.0 and not last:
                    lin_trial = ev.linearize(trial)
                    new_err = lin_trial.error(zero)
                else:
                    new_err = ev.error(trial)
                if new_err <= err:
                    lin = lin_trial
                    break
                step *= 0.5
            else:
                return Solution(values, it, err0, err, tuple(singular))  # no step lowers the error: converged
            rel = (err - new_err) / max(err, 1e-300)
            values, err = trial, new_err
            damping = max(DAMPING, damping / 10.0)
            if rel < relative_tolerance:
                break
        return Solution(values, it, err0, err, tuple(singular))
    except RuntimeError as e:
        singular.append(" ".join(str(e).split())[:300])
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_tolerance)
    params.setAbsoluteErrorTol(0.0)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    # iterated here so that it stops after FALLBACK_SECONDS: on a 12 000-knot graph of Python
    # factors gtsam's LM was still iterating after 25 minutes (its error never rises, so the
    # values at the stop are the best it has)
    t0 = time.perf_counter()
    err = float(opt.error())
    for _ in range(max_iterations):
        opt.iterate()
        new_err = float(opt.error())
        done = err - new_err <= relative_tolerance * max(err, 1e-300)
        err = new_err
        if done or time.perf_counter() - t0 > FALLBACK_SECONDS:
            break
    out = opt.values()
    return Solution(out, int(opt.iterations()), err0 if err0 == err0 else graph.error(values), graph.error(out),
                    tuple(singular))
