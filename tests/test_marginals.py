"""slam.backend.marginals: many marginal covariances from one elimination, against gtsam.Marginals."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L, X

from slam.backend.marginals import dense_marginals, eliminated_marginals, root_marginals

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


def test_dense_marginals_are_the_inverses_blocks() -> None:
    rng = np.random.default_rng(4)
    A = rng.normal(size=(40, 12))
    info = A.T @ A
    spans = [(0, 3), (3, 6), (9, 12)]
    got = dense_marginals(info, spans)
    inv = np.linalg.inv(info)
    for (a, b), c in zip(spans, got, strict=True):
        assert c is not None
        np.testing.assert_allclose(c, inv[a:b, a:b], rtol=1e-9)


def test_a_singular_systems_determined_spans_keep_their_marginals() -> None:
    """A variable (coordinates 6-8) observed along one direction only, with the first: the system
    is singular; that variable has no covariance, the others the covariance they have in any
    completion (the same with its undetermined directions pinned by a prior)."""
    rng = np.random.default_rng(5)
    J = np.zeros((60, 9))
    J[:30, :6] = rng.normal(size=(30, 6))  # the first two variables observed fully
    u = np.array([1.0, 2.0, -1.0]) / np.sqrt(6.0)
    J[30:, 6:] = np.outer(rng.normal(size=30), u)  # the third seen along u only, with the first
    J[30:, :3] = rng.normal(size=(30, 3))
    info = J.T @ J
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(info)
    got = dense_marginals(info, [(0, 3), (3, 6), (6, 9)])
    assert got[2] is None
    pinned = info.copy()
    pinned[6:, 6:] += 1e3 * (np.eye(3) - np.outer(u, u))  # any prior on its undetermined directions
    ref = np.linalg.inv(pinned)
    for i, (a, b) in enumerate([(0, 3), (3, 6)]):
        c = got[i]
        assert c is not None
        np.testing.assert_allclose(c, ref[a:b, a:b], rtol=1e-8)
    assert dense_marginals(np.full((3, 3), np.nan), [(0, 3)]) == [None]


def test_eliminated_marginals_where_the_root_cannot() -> None:
    """A landmark seen from one pose along its line of sight only (singular): root_marginals
    gives up; eliminated_marginals gives the other landmarks' covariances (gtsam's, from the graph
    with the indeterminate landmark pinned along its undetermined directions) and leaves it out."""
    g, v = _walk(8)
    assert root_marginals(g, v, [L(0), L(1), L(2)]) is not None
    bad = L(3)
    v.insert(bad, _LANDMARKS[3])
    u = np.array([1.0, 0.0, 0.0])

    def along(f: gtsam.CustomFactor, values: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        q = values.atPoint3(bad)
        if H is not None:
            H[0] = u.reshape(1, 3)
        return np.array([u @ (q - _LANDMARKS[3])])

    g.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, 0.01), [bad], along))
    keys = [L(0), L(1), L(2), bad]
    assert root_marginals(g, v, keys) is None
    got = eliminated_marginals(g, v, keys)
    assert got is not None and bad not in got and sorted(got) == sorted(keys[:3])
    pinned = gtsam.NonlinearFactorGraph(g)
    pinned.add(gtsam.PriorFactorPoint3(bad, _LANDMARKS[3], gtsam.noiseModel.Diagonal.Sigmas(np.array([1e3, 0.1, 0.1]))))
    ref = gtsam.Marginals(pinned, v)
    for k in keys[:3]:
        np.testing.assert_allclose(got[k], ref.marginalCovariance(k), rtol=1e-6)
