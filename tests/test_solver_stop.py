"""The batch solves' stopping rule judged ahead by the linear model (slam.backend.solver.predicted_end):
a step the model says ends the solve is evaluated by its error alone, not linearised; the solve
takes the same steps to the same estimate (whole graph and sectioned)."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from backend_defaults import backend_defaults
from box_scene import Scene, make_scene, perturbed_backend

import slam.backend.solver as solver
from slam.backend import Backend, BackendConfig


@pytest.fixture(scope="module")
def scene() -> Scene:
    return make_scene(duration=2.0, beams=61, sigma_range=0.003, seed=11)


def _solve(scene: Scene, config: BackendConfig, margin: float,
           monkeypatch: pytest.MonkeyPatch) -> tuple[Backend, int, int]:
    """A batch solve with ``PREDICTED_END_MARGIN`` = ``margin``; the backend, its iterations and
    the linearisations (whole graph) or section reductions (sectioned) it made."""
    monkeypatch.setattr(solver, "PREDICTED_END_MARGIN", margin)
    be = perturbed_backend(scene, config, 5)
    lins = [0]
    real = solver._Evaluator.linearize

    def counted(self: solver._Evaluator, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        lins[0] += 1
        return real(self, values)

    monkeypatch.setattr(solver._Evaluator, "linearize", counted)
    summary = be.batch_optimize(10, graduated=False)
    passes = be.sections.sections_solved if be.sections.needed() else lins[0]
    return be, summary.iterations, passes


@pytest.mark.parametrize("sectioned", [False, True])
def test_a_step_predicted_to_end_the_solve_is_not_linearised(scene: Scene, sectioned: bool,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = replace(backend_defaults(), batch_relative_tolerance=1e-3)
    if sectioned:
        cfg = replace(cfg, batch_section_knots=23, batch_whole_knots=0)
    ref, it_ref, passes_ref = _solve(scene, cfg, 0.0, monkeypatch)  # never predicted: every step linearised
    got, it_got, passes_got = _solve(scene, cfg, 0.5, monkeypatch)
    assert it_got == it_ref >= 2
    assert passes_got < passes_ref  # the last step's linearisation (or pass over the sections) saved
    for k in ref.graph.values.keys():
        if gtsam.Symbol(k).chr() == ord("x"):
            assert np.array_equal(got.graph.values.atPose3(k).matrix(), ref.graph.values.atPose3(k).matrix())


def test_predicted_end_compares_the_model_decrease_with_the_tolerance() -> None:
    assert solver.predicted_end(1000.0, 0.4, 1e-3)  # 0.04 % predicted, the rule 0.1 %: the last step
    assert not solver.predicted_end(1000.0, 0.6, 1e-3)  # 0.06 %: within the margin, linearised
    assert not solver.predicted_end(1000.0, 5.0, 1e-3)
    assert solver.predicted_end(1000.0, -1.0, 1e-3)  # a model that would raise the error: nothing to gain
