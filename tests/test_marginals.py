"""slam.backend.marginals: many marginal covariances from one elimination, against gtsam.Marginals."""

from __future__ import annotations

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from slam.backend.marginals import root_marginals

_LANDMARKS = [np.array([5.0, 2.0, 1.0]), np.array([3.0, -4.0, 0.5]), np.array([9.0, 0.0, 2.0]),
              np.array([1.0, 6.0, -1.0])]


def _point_factor(x: int, lm: int, p_body: np.ndarray, model: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """A landmark seen from a pose: its position in the body frame."""

    def error(f: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        T, q = values.atPose3(x), values.atPoint3(lm)
        Hx, Hq = np.zeros((3, 6), order="F"), np.zeros((3, 3), order="F")
        e = np.asarray(T.transformTo(q, Hx, Hq)) - p_body
        if H is not None:
            H[0], H[1] = Hx, Hq
        return e

    return gtsam.CustomFactor(model, [x, lm], error)


def _walk(n: int, landmarks: int = 3, seed: int = 0) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Poses in a chain (odometry), each seeing two of the first ``landmarks`` landmarks, the
    first pose held by a prior; values off the truth by a little."""
    rng = np.random.default_rng(seed)
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    odo = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 0.01, 0.05, 0.05, 0.05]))
    seen = gtsam.noiseModel.Isotropic.Sigma(3, 0.02)
    g.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-3)))
    for j in range(landmarks):
        v.insert(L(j), _LANDMARKS[j] + rng.normal(0, 0.05, 3))
    prev = None
    for i in range(n):
        T = gtsam.Pose3(gtsam.Rot3.Yaw(0.1 * i), np.array([0.5 * i, 0.0, 0.0]))
        v.insert(X(i), T.retract(rng.normal(0, 0.01, 6)))
        if prev is not None:
            g.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), prev.between(T), odo))
        for j in (i % landmarks, (i + 1) % landmarks):
            g.add(_point_factor(X(i), L(j), np.asarray(T.transformTo(_LANDMARKS[j])), seen))
        prev = T
    return g, v


def test_the_roots_marginals_are_gtsams_one_by_one() -> None:
    g, v = _walk(12, landmarks=3)
    keys = [L(0), L(1), L(2), X(5)]
    got = root_marginals(g, v, keys)
    assert got is not None and sorted(got) == sorted(keys)
    ref = gtsam.Marginals(g, v)
    for k in keys:
        np.testing.assert_allclose(got[k], ref.marginalCovariance(k), rtol=1e-8, atol=1e-16)
        assert np.all(np.linalg.eigvalsh(got[k]) > 0.0)
    assert root_marginals(g, v, []) == {}


def test_no_marginals_from_an_indeterminate_or_split_graph() -> None:
    g, v = _walk(6, landmarks=3)
    v.insert(L(3), _LANDMARKS[3])  # a landmark seen once: its position along the ray is free
    g.add(gtsam.BetweenFactorPoint3(L(3), L(3), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
    assert root_marginals(g, v, [L(0), L(3)]) is None
    # two graphs that share no variable: their variables end in two root cliques
    a, va = _walk(4, landmarks=2)
    b = gtsam.NonlinearFactorGraph()
    vb = gtsam.Values()
    vb.insert(X(100), gtsam.Pose3())
    b.add(gtsam.PriorFactorPose3(X(100), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.1)))
    a.push_back(b)
    va.insert(vb)
    assert root_marginals(a, va, [L(0), X(100)]) is None
    assert root_marginals(a, va, [L(0), L(1)]) is not None  # those two are in one piece
