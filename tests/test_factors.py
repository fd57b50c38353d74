"""Jacobians of the back-end factors against central differences on the manifold (via retract)."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import E, P, X

from slam.backend.factors import (
    NO_KERNEL,
    RobustKernel,
    point_plane_factor,
    point_plane_terms,
    point_planes_factor,
    robust_loss,
    robust_residual,
    robust_rows,
    robust_weights,
    scanner_point_plane_factor,
)
from slam.motion import (
    MotionPriorConfig,
    constant_velocity_factor,
    horizontal_plane_prior,
)
from slam.trajectory.interpolation import (
    adjoint,
    exp_coefficients,
    interpolate_poses,
    interpolate_trajectory,
    knot_fractions,
    se3_exp,
    se3_inverse,
    se3_log,
    se3_right_jacobian,
)

KERNELS = [NO_KERNEL, RobustKernel("huber", 0.7), RobustKernel("cauchy", 0.7),
           RobustKernel("geman_mcclure", 0.7)]


def _random_pose(rng: np.random.Generator, rot: float = 1.0) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * rot), rng.normal(size=3))


def _retract(values: gtsam.Values, key: int, delta: np.ndarray) -> gtsam.Values:
    out = gtsam.Values(values)
    sym = chr(gtsam.Symbol(key).chr())
    if sym == "p":
        out.update(key, values.atOrientedPlane3(key).retract(delta))
    else:
        out.update(key, values.atPose3(key).retract(delta))
    return out


def _check_jacobians(factor: gtsam.NoiseModelFactor, values: gtsam.Values, tol: float = 1e-6) -> None:
    """Whitened analytic Jacobians (from linearize) vs central differences of the whitened error."""
    A, _ = factor.linearize(values).jacobian()
    col = 0
    for key in factor.keys():
        dim = 3 if chr(gtsam.Symbol(key).chr()) == "p" else 6
        h = 1e-6
        num = np.empty((A.shape[0], dim))
        for j in range(dim):
            d = np.zeros(dim)
            d[j] = h
            ep = factor.whitenedError(_retract(values, key, d))
            em = factor.whitenedError(_retract(values, key, -d))
            num[:, j] = (ep - em) / (2 * h)
        ana = A[:, col:col + dim]
        scale = max(1.0, np.abs(num).max())
        assert np.abs(ana - num).max() < tol * scale, (gtsam.Symbol(key).string(), np.abs(ana - num).max())
        col += dim
    assert col == A.shape[1]


def _block_values(rng: np.random.Generator, motion: float) -> gtsam.Values:
    Ta = _random_pose(rng)
    v = gtsam.Values()
    v.insert(X(0), Ta)
    v.insert(X(1), Ta.compose(gtsam.Pose3.Expmap(rng.normal(size=6) * motion)))
    v.insert(P(0), gtsam.OrientedPlane3(gtsam.Unit3(rng.normal(size=3)), rng.normal()))
    v.insert(E(0), _random_pose(rng, 0.5))
    return v


@pytest.mark.parametrize("motion", [1e-7, 0.02, 0.4])
def test_point_plane_factor_jacobians(motion: float) -> None:
    rng = np.random.default_rng(11)
    none = NO_KERNEL
    for _ in range(3):
        v = _block_values(rng, motion)
        n = 25
        pts = rng.normal(size=(n, 3)) * 3.0
        al = rng.uniform(0.0, 1.0, n)
        al[:2] = [0.0, 1.0]
        sig = rng.uniform(0.5, 2.0, n)
        _check_jacobians(point_plane_factor(X(0), X(1), P(0), pts, al, sig, none), v)
        _check_jacobians(point_plane_factor(X(0), None, P(0), pts, None, sig, none), v)
        _check_jacobians(scanner_point_plane_factor(X(0), X(1), P(0), E(0), pts, al, sig, none), v)
        _check_jacobians(scanner_point_plane_factor(X(0), None, P(0), E(0), pts, None, sig, none), v)


@pytest.mark.parametrize("motion", [1e-7, 0.3])
def test_point_planes_factor_jacobians(motion: float) -> None:
    rng = np.random.default_rng(12)
    v = _block_values(rng, motion)
    for j in range(1, 4):
        v.insert(P(j), gtsam.OrientedPlane3(gtsam.Unit3(rng.normal(size=3)), rng.normal()))
    n = 30
    idx = np.concatenate((np.arange(4), rng.integers(0, 4, n - 4)))
    al = rng.uniform(0.0, 1.0, n)
    al[:2] = [0.0, 1.0]
    f = point_planes_factor(X(0), X(1), [P(j) for j in range(4)], idx, rng.normal(size=(n, 3)) * 3.0, al,
                            rng.uniform(0.5, 2.0, n), NO_KERNEL, rng.normal(size=(4, 3)))
    _check_jacobians(f, v)


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: k.name)
def test_point_planes_factor_is_the_blocks_of_its_planes(kernel: RobustKernel) -> None:
    """One factor for an interval's points on several planes: the error and the Gauss-Newton
    system of one block per plane (the back end's grouping changes no step)."""
    rng = np.random.default_rng(13)
    v = _block_values(rng, 0.05)
    J = 3
    for j in range(1, J):
        v.insert(P(j), gtsam.OrientedPlane3(gtsam.Unit3(rng.normal(size=3)), rng.normal()))
    n = 40
    idx = np.concatenate((np.arange(J), rng.integers(0, J, n - J)))
    pts, al, sig = rng.normal(size=(n, 3)) * 2, rng.uniform(0, 1, n), np.full(n, 0.3)
    anchors = rng.normal(size=(J, 3))
    group = gtsam.NonlinearFactorGraph()
    group.add(point_planes_factor(X(0), X(1), [P(j) for j in range(J)], idx, pts, al, sig, kernel, anchors))
    blocks = gtsam.NonlinearFactorGraph()
    for j in range(J):
        m = idx == j
        blocks.add(point_plane_factor(X(0), X(1), P(j), pts[m], al[m], sig[m], kernel, anchors[j]))
    assert group.error(v) == pytest.approx(blocks.error(v), rel=1e-12)
    lg, lb = group.linearize(v), blocks.linearize(v)
    assert lg.error(v.zeroVectors()) == pytest.approx(blocks.error(v), rel=1e-12)
    (Hg, gg), (Hb, gb) = lg.hessian(), lb.hessian()
    np.testing.assert_allclose(Hg, Hb, rtol=1e-12, atol=1e-9 * np.abs(Hb).max())
    np.testing.assert_allclose(gg, gb, rtol=1e-12, atol=1e-9 * np.abs(gb).max())
    with pytest.raises(ValueError, match="plane_index"):
        point_planes_factor(X(0), X(1), [P(0), P(1)], np.full(n, 2), pts, al, sig, kernel)
    with pytest.raises(ValueError, match="plane_keys"):
        point_planes_factor(X(0), X(1), [P(0), P(0)], np.zeros(n), pts, al, sig, kernel)


@pytest.mark.parametrize("kernel", KERNELS[1:], ids=lambda k: k.name)
def test_robust_linearization_is_irls_and_error_is_robust_cost(kernel: RobustKernel) -> None:
    """IRLS Gauss-Newton rows whose linearisation error is the robust cost (``robust_rows``)."""
    rng = np.random.default_rng(5)
    v = _block_values(rng, 0.05)
    pts = rng.normal(size=(40, 3)) * 2
    al = rng.uniform(0, 1, 40)
    sig = np.full(40, 0.5)
    for make in (
        lambda k: point_plane_factor(X(0), X(1), P(0), pts, al, sig, k),
        lambda k: scanner_point_plane_factor(X(0), X(1), P(0), E(0), pts, al, sig, k),
    ):
        plain, robust = make(NO_KERNEL), make(kernel)
        A0, b0 = plain.linearize(v).jacobian()
        A1, b1 = robust.linearize(v).jacobian()
        e = -b0
        sw = np.sqrt(robust_weights(e, kernel))
        assert np.mean(sw < 0.9) > 0.2  # the kernel is active on part of the points
        # IRLS rows, then one correction row without Jacobian: 0.5 ||b||^2 is the robust cost
        assert A1.shape == (A0.shape[0] + 1, A0.shape[1]) and not np.any(A1[-1])
        np.testing.assert_allclose(A1[:-1], sw[:, None] * A0, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b1[:-1], sw * b0, rtol=1e-12, atol=1e-12)
        assert robust.error(v) == pytest.approx(robust_loss(e, kernel).sum(), rel=1e-12)
        assert 0.5 * float(b1 @ b1) == pytest.approx(robust.error(v), rel=1e-12)
        np.testing.assert_allclose(0.5 * robust_residual(e, kernel) ** 2, robust_loss(e, kernel))


@pytest.mark.parametrize("kernel", KERNELS[1:], ids=lambda k: k.name)
def test_compiled_robust_rows_match_their_numpy_formulation(kernel: RobustKernel) -> None:
    e = np.concatenate((np.random.default_rng(8).normal(0.0, 5.0, 200), [0.0, -0.0, 1e-9, 40.0, -300.0]))
    w = robust_weights(e, kernel)
    lin, sw = robust_rows(e, kernel, True)
    assert sw is not None
    np.testing.assert_allclose(sw, np.sqrt(w), rtol=1e-14, atol=0.0)
    np.testing.assert_allclose(lin[:-1], np.sqrt(w) * e, rtol=1e-14, atol=0.0)
    np.testing.assert_allclose(lin[-1], np.sqrt(2.0 * np.sum(robust_loss(e, kernel) - 0.5 * w * e * e)), rtol=1e-12)
    ev, none = robust_rows(e, kernel, False)
    assert none is None and ev[-1] == 0.0
    np.testing.assert_allclose(ev[:-1], robust_residual(e, kernel), rtol=1e-14, atol=0.0)
    assert 0.5 * float(lin @ lin) == pytest.approx(float(robust_loss(e, kernel).sum()), rel=1e-12)


def test_point_plane_residual_is_signed_distance_of_interpolated_point() -> None:
    rng = np.random.default_rng(2)
    v = _block_values(rng, 0.3)
    Ta, Tb, pl = v.atPose3(X(0)), v.atPose3(X(1)), v.atOrientedPlane3(P(0))
    pts = rng.normal(size=(10, 3))
    al = rng.uniform(0, 1, 10)
    T = interpolate_poses(Ta.matrix(), Tb.matrix(), al)
    w = np.einsum("nij,nj->ni", T[:, :3, :3], pts) + T[:, :3, 3]
    expected = w @ pl.normal().point3() + pl.distance()
    got = point_plane_terms(Ta, Tb, pl, pts, al, jacobians=False).residuals
    np.testing.assert_allclose(got, expected, atol=1e-12)
    # alpha = 1 is exactly the second knot
    got1 = point_plane_terms(Ta, Tb, pl, pts, np.ones(10), jacobians=False).residuals
    np.testing.assert_allclose(got1, point_plane_terms(Tb, None, pl, pts, None, False).residuals,
                               atol=1e-12)


def test_robust_weights_downweight_large_residuals() -> None:
    e = np.array([0.0, 1.0, 3.0, 30.0])
    wc = robust_weights(e, RobustKernel("cauchy", 3.0))
    wh = robust_weights(e, RobustKernel("huber", 3.0))
    assert wc[0] == 1.0 and wc[-1] < 0.02 and np.all(np.diff(wc) < 0)
    np.testing.assert_allclose(wh, [1.0, 1.0, 1.0, 0.1])
    wg = robust_weights(e, RobustKernel("geman_mcclure", 3.0))
    assert wg[0] == 1.0 and np.all(np.diff(wg) < 0) and wg[-1] < 0.1 * wc[-1]


@pytest.mark.parametrize("name", ["huber", "cauchy", "geman_mcclure"])
def test_robust_weights_are_the_loss_derivative_over_e(name: str) -> None:
    """IRLS weight w = rho'(e) / e, by central differences of :func:`robust_loss`."""
    k = RobustKernel(name, 2.5)
    e = np.array([-40.0, -7.0, -1.3, 0.4, 2.0, 3.1, 12.0])
    h = 1e-6
    d = (robust_loss(e + h, k) - robust_loss(e - h, k)) / (2 * h)
    np.testing.assert_allclose(robust_weights(e, k), d / e, rtol=1e-6)


def test_block_input_errors_are_clear() -> None:
    with pytest.raises(ValueError, match="points_body"):
        point_plane_factor(X(0), X(1), P(0), np.zeros((3, 2)), np.zeros(3), 0.01, NO_KERNEL)
    with pytest.raises(ValueError, match="alphas"):
        point_plane_factor(X(0), X(1), P(0), np.zeros((3, 3)), np.full(3, 1.5), 0.01, NO_KERNEL)
    with pytest.raises(ValueError, match="alphas"):
        point_plane_factor(X(0), None, P(0), np.zeros((3, 3)), np.full(3, 0.5), 0.01, NO_KERNEL)
    with pytest.raises(ValueError, match="sigmas"):
        point_plane_factor(X(0), None, P(0), np.zeros((3, 3)), None, np.array([0.1, 0.0, 0.1]), NO_KERNEL)
    with pytest.raises(ValueError, match="robust kernel"):
        RobustKernel("tukey", 3.0)


@pytest.mark.parametrize("motion", [1e-8, 0.05, 0.5])
def test_constant_velocity_factor_jacobians(motion: float) -> None:
    rng = np.random.default_rng(7)
    T0 = _random_pose(rng)
    T1 = T0.compose(gtsam.Pose3.Expmap(rng.normal(size=6) * motion))
    T2 = T1.compose(gtsam.Pose3.Expmap(rng.normal(size=6) * motion))
    v = gtsam.Values()
    for i, T in enumerate([T0, T1, T2]):
        v.insert(X(i), T)
    _check_jacobians(constant_velocity_factor(X(0), X(1), X(2), 0.025, 0.03, MotionPriorConfig(q_ang=1.0, q_lin=0.25)), v)


def test_constant_velocity_factor_is_zero_for_constant_twist() -> None:
    xi = np.array([0.1, -0.2, 0.5, 1.2, 0.1, -0.05])
    T0 = se3_exp(np.array([0.3, 0.1, -0.2, 1.0, 2.0, 0.5]))
    v = gtsam.Values()
    for i, t in enumerate([0.0, 0.025, 0.055]):
        v.insert(X(i), gtsam.Pose3(T0 @ se3_exp(t * xi)))
    f = constant_velocity_factor(X(0), X(1), X(2), 0.025, 0.03, MotionPriorConfig(q_ang=1.0, q_lin=0.25))
    assert np.abs(f.unwhitenedError(v)).max() < 1e-12


def test_horizontal_plane_prior_keeps_sign() -> None:
    v = gtsam.Values()
    v.insert(P(0), gtsam.OrientedPlane3(0.0, 0.02, -1.0, 2.0))
    f = horizontal_plane_prior(P(0), [0.0, 0.02, -1.0], 0.01)
    assert np.abs(f.unwhitenedError(v)).max() < 0.03  # small, not antipodal
    with pytest.raises(ValueError, match="normal_world"):
        horizontal_plane_prior(P(0), [1.0, 0.0, 0.0], 0.01)


@pytest.mark.parametrize("scale", [1e-9, 1e-3, 0.3, 0.49, 0.51, 1.5])
def test_se3_tools_match_gtsam(scale: float) -> None:
    rng = np.random.default_rng(3)
    for _ in range(5):
        xi = rng.normal(size=6)
        xi[:3] *= scale / np.linalg.norm(xi[:3])
        T = gtsam.Pose3.Expmap(xi)
        np.testing.assert_allclose(se3_exp(xi), T.matrix(), atol=1e-14)
        np.testing.assert_allclose(se3_log(T.matrix()), xi, atol=1e-12)
        np.testing.assert_allclose(se3_right_jacobian(xi), gtsam.Pose3.ExpmapDerivative(xi),
                                   atol=1e-13)
        np.testing.assert_allclose(adjoint(T.matrix()), T.AdjointMap(), atol=1e-14)
        np.testing.assert_allclose(se3_inverse(T.matrix()), T.inverse().matrix(), atol=1e-14)


def test_exp_coefficients_continuous_at_series_switch() -> None:
    a = np.array(exp_coefficients(np.array([0.5 - 1e-12])))
    b = np.array(exp_coefficients(np.array([0.5 + 1e-12])))
    np.testing.assert_allclose(a, b, rtol=1e-11)
    np.testing.assert_allclose(np.array(exp_coefficients(0.0)).ravel(),
                               [1.0, 0.5, 1 / 6, 1 / 24, 1 / 120])


def test_interpolate_trajectory_hits_knots_and_validates_times() -> None:
    rng = np.random.default_rng(4)
    kt = np.array([0.0, 0.025, 0.05, 0.075])
    poses = np.array([_random_pose(rng).matrix() for _ in kt])
    np.testing.assert_allclose(interpolate_trajectory(kt, poses, kt), poses, atol=1e-12)
    idx, al = knot_fractions(kt, [0.0, 0.0125, 0.075])
    np.testing.assert_array_equal(idx, [0, 0, 2])
    np.testing.assert_allclose(al, [0.0, 0.5, 1.0])
    with pytest.raises(ValueError, match="times"):
        knot_fractions(kt, [0.08])
    with pytest.raises(ValueError, match="knot_times"):
        knot_fractions([0.0, 0.0], [0.0])
