"""Batch estimation of the scanners' extrinsics (and time offsets) in one factor graph.

Variables (gtsam keys): ``X(i)`` body poses ``T_world_body`` at the SLAM knots, ``P(j)`` the
world planes, ``E(s)`` ``T_body_scanner`` of every non-reference scanner, and with
``time_offsets`` a scalar ``D(s)`` per non-reference scanner (its clock correction [s]; see
:mod:`calibration.factors`). The reference scanner defines the body frame (and clock): its
points enter with its fixed extrinsic and no ``E``.

Factors: one batched point-on-plane block per (knot interval, plane, scanner) (the points of
:class:`calibration.observations.PointObservations` placed at their beam times on the SE(3)
interpolated trajectory, per-point Huber weights), the constant-velocity motion prior of
:mod:`slam.motion` on every three knots, a datum prior fixing the first knot (and a weak prior on
the first interval's motion, as in :mod:`slam.backend`), a weak prior on every knot around its
SLAM pose (``pose_prior_sigma``, rad and m: keeps motions the planes leave free, such as along a
straight corridor, from making the system singular), a weak prior on each
plane (its SLAM estimate, ``plane_prior_sigma``: keeps planes seen from one line direction only
well posed) and on each extrinsic a prior around the initial rig (``sigma_rot`` / ``sigma_trans``,
default 5 deg / 10 cm) and on each offset a prior around 0 (``sigma_time``).

Robustness and the variance factor: the point residuals get a redescending Cauchy kernel
(``kernel``, threshold in units of the *robust* residual scale) so that wrong associations (a
door recessed 1-2 cm associated with its wall, a proud whiteboard) stop pulling. The stated point
sigmas (scanner noise / sqrt(n / 2) per virtual point) ignore such outliers, line-fit and
trajectory model errors, so after each solve the spread of every scanner's whitened residuals is
measured robustly, ``scale = 1.4826 median |e - median e|`` (MAD), floored at ``scale_floor``
(the sensor model is a lower bound; noise-free data would otherwise give a vanishing scale), and
the scanner's point sigmas are multiplied by it; the graph is solved again from the previous
solution (``scale_rounds`` solves in all, the first with the convex ``start_kernel`` (Huber) since the
start may be far off and the scale is not known yet; ``variance_factor=False``: one solve with
``kernel`` and the stated sigmas). The kernel threshold thus tracks the real spread, and
the covariance, computed with the scaled sigmas, is the robust a-posteriori (variance-factor
scaled) covariance of the data part; the priors keep their own sigmas, so a parameter that only
the prior constrains keeps its prior sigma. The IRLS information ``sum w J^T J`` of a robust fit
is still optimistic when many residuals sit in the kernel's down-weighted range, so the sigmas
of the covariance graph get the M-estimator sandwich correction of
:func:`robust_variance_factor` on top (with the thresholds divided by it: same weights).

Per-point factors cannot see errors shared by many points (the trajectory model between two
knots, a line fit's errors-in-variables, one scan's timing): with ``cluster_covariance`` the
batch also reports the cluster-robust sandwich covariance of :func:`cluster_covariances`, with the
blocks of ``cluster_knots[0]`` consecutive knot intervals (default 20: 1 s at 20 knots/s) as a
cluster (``ScannerEstimate.covariance_cluster``; every window of ``cluster_knots`` in
``ScannerEstimate.covariance_clusters``). A window is shortened so that the recording has at
least ``min_clusters`` clusters (a short recording falls back to one knot interval per cluster).
On the 120 s pipeline runs (docs/calibration.md) 1 s windows gave RMS error/sigma 1.7-1.9 where
single knot intervals gave ~3 and the marginal covariance 3.4-4.8.

Solved by a lightly damped Gauss-Newton with step halving (:func:`_solve`, the SLAM back end's
batch scheme) from the SLAM trajectory and planes; the marginal covariances of
``E(s)`` (6x6, gtsam tangent order: rotation then translation, right perturbation of
``T_body_scanner``) and ``D(s)`` come from ``gtsam.Marginals`` at the solution of the last
(scaled) graph.
"""

from __future__ import annotations

import re
import time as _time
from dataclasses import dataclass, field, replace
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import D, E, P, X
from numpy.typing import NDArray

from calibration.factors import timed_scanner_plane_factor
from calibration.observations import PointObservations
from slam.backend.factors import (
    RobustKernel,
    point_plane_factor,
    point_plane_terms,
    robust_weights,
    scanner_point_plane_factor,
)
from slam.backend.solver import damped_gauss_newton
from slam.motion import (
    MotionPriorConfig,
    constant_velocity_factor,
    datum_prior,
    initial_velocity_factor,
)
from slam.trajectory.interpolation import interpolate_trajectory, knot_fractions

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class EstimatorConfig:
    """Priors and solver settings of the calibration graph (SI units)."""

    sigma_rot: float = float(np.radians(5.0))
    sigma_trans: float = 0.10
    time_offsets: bool = False
    sigma_time: float = 0.005
    kernel: RobustKernel = field(default_factory=lambda: RobustKernel("cauchy", 3.0))
    start_kernel: RobustKernel = field(default_factory=lambda: RobustKernel("huber", 2.5))
    variance_factor: bool = True
    scale_rounds: int = 2
    scale_floor: float = 1.0
    motion: MotionPriorConfig = field(default_factory=lambda: MotionPriorConfig(q_ang=1.0, q_lin=0.25))
    plane_prior_sigma: tuple[float, float] = (0.2, 0.2)
    pose_prior_sigma: tuple[float, float] = (0.5, 1.0)
    min_plane_points: int = 6
    cluster_covariance: bool = True
    cluster_knots: tuple[int, ...] = (20,)
    min_clusters: int = 50
    grazing_cos: float | None = None
    max_iterations: int = 50
    relative_tolerance: float = 1e-9

    def __post_init__(self) -> None:
        for name in ("sigma_rot", "sigma_trans", "sigma_time", "relative_tolerance"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name}: must be > 0, got {v}")
        if self.grazing_cos is not None and not 0.0 < self.grazing_cos <= 1.0:
            raise ValueError(f"grazing_cos: must be in (0, 1], got {self.grazing_cos}")
        if not self.cluster_knots or min(self.cluster_knots) < 1:
            raise ValueError(f"cluster_knots: knot intervals per cluster, each >= 1, got {self.cluster_knots}")
        if self.max_iterations < 1 or self.min_plane_points < 1 or self.scale_rounds < 1 or self.min_clusters < 2:
            raise ValueError("max_iterations, min_plane_points and scale_rounds: must be >= 1; min_clusters >= 2")
        if not (np.isfinite(self.scale_floor) and self.scale_floor > 0):
            raise ValueError(f"scale_floor: must be > 0, got {self.scale_floor}")


@dataclass
class ScannerEstimate:
    """One scanner's calibration: ``T_body_scanner`` (4, 4) before and after, the 6x6 marginal
    covariance (None for the reference), the time offset correction [s] and its sigma (None when
    not estimated), unwhitened point-to-plane residuals [m] before/after, and ``scale``: the
    robust spread of the whitened residuals that multiplied the point sigmas (variance factor
    ``scale**2``) and ``sandwich``, the M-estimator correction on top of it (module docstring);
    ``covariance_cluster`` the cluster-robust alternative of :func:`cluster_covariances` (None for
    the reference or when not computed)."""

    index: int
    name: str
    reference: bool
    T_initial: FloatArray
    T_body_scanner: FloatArray
    covariance: FloatArray | None
    time_offset: float
    time_offset_sigma: float | None
    residuals_before: FloatArray
    residuals_after: FloatArray
    n_points: int
    scale: float = 1.0
    sandwich: float = 1.0
    covariance_cluster: FloatArray | None = None
    covariance_clusters: dict[int, FloatArray] = field(default_factory=dict)


@dataclass
class BatchResult:
    """Outcome of :func:`estimate_extrinsics`."""

    scanners: list[ScannerEstimate]
    T_world_body: FloatArray
    plane_ids: NDArray[np.int64]
    initial_error: float
    final_error: float
    iterations: int
    seconds: float
    n_blocks: int
    prior_sigmas: FloatArray  # (6,) rotation [rad] x3, translation [m] x3


@dataclass
class _Block:
    knot: int
    plane: int
    scanner: int
    points: FloatArray
    alphas: FloatArray
    sigmas: FloatArray


def _plane_prior(key: int, plane: gtsam.OrientedPlane3, sigmas: tuple[float, float]) -> gtsam.CustomFactor:
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigmas[0], sigmas[0], sigmas[1]]))

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: Any) -> FloatArray:
        e = np.asarray(plane.localCoordinates(v.atOrientedPlane3(key)), dtype=float)
        if H is not None:
            H[0] = np.eye(3)  # weak prior: the exact Jacobian differs from I only to second order
        return e

    return gtsam.CustomFactor(noise, [key], error)


def _blocks(kt: FloatArray, obs: PointObservations) -> list[_Block]:
    idx, alpha = knot_fractions(kt, obs.times)
    order = np.lexsort((obs.scanner, obs.plane_id, idx))
    key = np.stack((idx[order], obs.plane_id[order], obs.scanner[order]), axis=1)
    cut = np.flatnonzero(np.any(np.diff(key, axis=0) != 0, axis=1)) + 1
    out = []
    for sel in np.split(order, cut):
        if sel.size == 0:
            continue
        out.append(_Block(int(idx[sel[0]]), int(obs.plane_id[sel[0]]), int(obs.scanner[sel[0]]),
                          obs.points_scanner[sel], alpha[sel], obs.sigmas[sel]))
    return out


def _grazing(kt: FloatArray, T_world_body: FloatArray, planes: dict[int, tuple[FloatArray, float]],
             obs: PointObservations, T_bs: list[FloatArray], cos_max: float) -> NDArray[np.bool_]:
    """Points whose plane is nearly parallel to their scanner's scan plane at the initial
    estimate: ``|n_scanner . z| > cos_max``. A 2D scanner cannot see such a surface (its scan
    line would lie in it), so the association is wrong: e.g. a horizontal scanner's wall
    segment put on a floor-like spurious plane by SLAM with a rig degrees off."""
    T = interpolate_trajectory(kt, np.asarray(T_world_body, dtype=float), obs.times)
    R_bs = np.stack([np.asarray(t, dtype=float)[:3, :3] for t in T_bs])[obs.scanner]
    n_w = np.array([planes[int(j)][0] for j in obs.plane_id], dtype=float)
    n_b = np.einsum("nji,nj->ni", T[:, :3, :3], n_w)  # R_wb^T n
    z_s = np.einsum("nji,nj->ni", R_bs, n_b)[:, 2]  # (R_bs^T n_b) . z
    return np.asarray(np.abs(z_s) > cos_max)


def estimate_extrinsics(
    knot_times: FloatArray,
    T_world_body: FloatArray,
    planes: dict[int, tuple[FloatArray, float]],
    obs: PointObservations,
    T_init: list[FloatArray],
    reference: int,
    names: list[str] | None = None,
    T_prior: list[FloatArray] | None = None,
    config: EstimatorConfig | None = None,
) -> BatchResult:
    """Jointly refine poses, planes and the non-reference extrinsics (module docstring).

    ``knot_times`` (K,), ``T_world_body`` (K, 4, 4) initial trajectory; ``planes`` id ->
    (unit normal, d) in the world; ``T_init`` the initial ``T_body_scanner`` per scanner (the
    reference's stays fixed) and ``T_prior`` the prior centres (default ``T_init``).
    """
    cfg = config or EstimatorConfig()
    t_wall = _time.perf_counter()
    kt = np.asarray(knot_times, dtype=float)
    n_sc = len(T_init)
    names = names or [f"scanner{i}" for i in range(n_sc)]
    T_prior = T_prior or T_init
    if not 0 <= reference < n_sc:
        raise ValueError(f"reference: scanner index {reference} outside [0, {n_sc})")
    inside = (obs.times >= kt[0]) & (obs.times <= kt[-1]) & np.isin(obs.plane_id, list(planes))
    obs = obs.select(inside)
    if cfg.grazing_cos is not None and len(obs):
        obs = obs.select(~_grazing(kt, T_world_body, planes, obs, T_init, cfg.grazing_cos))
    counts = {int(j): int(c) for j, c in zip(*np.unique(obs.plane_id, return_counts=True), strict=True)}
    obs = obs.select(np.array([counts[int(j)] >= cfg.min_plane_points for j in obs.plane_id], dtype=bool))
    if len(obs) == 0:
        raise ValueError("observations: no points on known planes within the trajectory's time span")
    calibrated = [s for s in range(n_sc) if s != reference and np.any(obs.scanner == s)]

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    pose_noise = gtsam.noiseModel.Diagonal.Sigmas(np.repeat(cfg.pose_prior_sigma, 3))
    for i, T in enumerate(np.asarray(T_world_body, dtype=float)):
        values.insert(X(i), gtsam.Pose3(T))
        graph.add(gtsam.PriorFactorPose3(X(i), gtsam.Pose3(T), pose_noise))
    graph.add(datum_prior(X(0), gtsam.Pose3(T_world_body[0])))
    if kt.size >= 2:  # weak, as in the SLAM back end: the first interval's motion
        T01 = gtsam.Pose3(T_world_body[0]).between(gtsam.Pose3(T_world_body[1]))
        graph.add(initial_velocity_factor(X(0), X(1), T01, kt[1] - kt[0], 3.0, 3.0))
    for i in range(2, kt.size):
        graph.add(constant_velocity_factor(X(i - 2), X(i - 1), X(i), kt[i - 1] - kt[i - 2],
                                           kt[i] - kt[i - 1], cfg.motion))
    used_planes = sorted(int(j) for j in np.unique(obs.plane_id))
    for j in used_planes:
        n, d = planes[j]
        pl = gtsam.OrientedPlane3(gtsam.Unit3(np.asarray(n, dtype=float)), float(d))
        values.insert(P(j), pl)
        graph.add(_plane_prior(P(j), pl, cfg.plane_prior_sigma))
    prior_sig = np.array([cfg.sigma_rot] * 3 + [cfg.sigma_trans] * 3)
    for s in calibrated:
        values.insert(E(s), gtsam.Pose3(T_init[s]))
        graph.add(gtsam.PriorFactorPose3(E(s), gtsam.Pose3(T_prior[s]),
                                         gtsam.noiseModel.Diagonal.Sigmas(prior_sig)))
        if cfg.time_offsets:
            values.insert(D(s), np.zeros(1))
            graph.add(gtsam.PriorFactorVector(D(s), np.zeros(1),
                                              gtsam.noiseModel.Isotropic.Sigma(1, cfg.sigma_time)))
    blocks = _blocks(kt, obs)
    prior_graph = graph
    scale = np.ones(n_sc)
    before = _residuals(blocks, values, kt, calibrated, T_init, cfg.time_offsets, n_sc)
    e0 = float(_data_graph(prior_graph, blocks, kt, reference, calibrated, T_init, scale, cfg).error(values))
    iterations = 0
    for k in range(cfg.scale_rounds):
        # convex Huber first (the start may be far off), the redescending kernel once scaled
        kern = [cfg.start_kernel] * n_sc if k == 0 and cfg.variance_factor and cfg.scale_rounds > 1 else None
        graph = _data_graph(prior_graph, blocks, kt, reference, calibrated, T_init, scale, cfg, kern)
        result, it = _solve(graph, values, cfg)
        iterations += it
        values = result
        if not cfg.variance_factor:
            break
        res_k = _residuals(blocks, result, kt, calibrated, T_init, cfg.time_offsets, n_sc)
        scale = np.array([max(cfg.scale_floor, robust_scale(res_k[i] / sig[i]))
                          for i, sig in enumerate(_sigmas(blocks, n_sc))])
    solved = graph
    sandwich = np.ones(n_sc)
    if cfg.variance_factor:  # the covariance with the scale of the final residuals
        res_k = _residuals(blocks, result, kt, calibrated, T_init, cfg.time_offsets, n_sc)
        sig_k = _sigmas(blocks, n_sc)
        sandwich = np.array([robust_variance_factor(res_k[i] / (sig_k[i] * scale[i]), cfg.kernel)
                             for i in range(n_sc)])
        # sigmas x sandwich and thresholds / sandwich: the same IRLS weights, information / f^2
        kernels = [replace(cfg.kernel, threshold=cfg.kernel.threshold / f) for f in sandwich]
        graph = _data_graph(prior_graph, blocks, kt, reference, calibrated, T_init, scale * sandwich,
                            cfg, kernels)
    try:
        marginals = gtsam.Marginals(graph, result)
    except RuntimeError as err:
        raise _solve_error(err) from None
    clustered: dict[int, dict[int, FloatArray]] = {}  # scanner -> window -> covariance
    if cfg.cluster_covariance and calibrated:
        try:
            knots = np.array([b.knot for b in blocks])
            per_window = _cluster_covariances(solved, result, prior_graph.size(),
                                              [knots // min(w, max(1, (kt.size - 1) // cfg.min_clusters))
                                               for w in cfg.cluster_knots], [E(s) for s in calibrated])
            clustered = {s: {w: c[E(s)] for w, c in zip(cfg.cluster_knots, per_window, strict=True)}
                         for s in calibrated}
        except (RuntimeError, ValueError, np.linalg.LinAlgError):
            clustered = {}
    T_final = [np.asarray(T_init[s], dtype=float) if s not in calibrated
               else np.asarray(result.atPose3(E(s)).matrix()) for s in range(n_sc)]
    after = _residuals(blocks, result, kt, calibrated, T_final, cfg.time_offsets, n_sc)

    scanners = []
    for s in range(n_sc):
        cal = s in calibrated
        cov = np.asarray(marginals.marginalCovariance(E(s))) if cal else None
        dt, dt_sig = 0.0, None
        if cal and cfg.time_offsets:
            dt = float(result.atVector(D(s))[0])
            dt_sig = float(np.sqrt(marginals.marginalCovariance(D(s))[0, 0]))
        scanners.append(ScannerEstimate(
            s, names[s], s == reference, np.asarray(T_init[s], dtype=float), T_final[s],
            None if cov is None else 0.5 * (cov + cov.T), dt, dt_sig, before[s], after[s],
            int(np.sum(obs.scanner == s)), float(scale[s]), float(sandwich[s]),
            clustered[s][cfg.cluster_knots[0]] if s in clustered else None, clustered.get(s, {})))
    poses = np.array([result.atPose3(X(i)).matrix() for i in range(kt.size)])
    return BatchResult(scanners, poses, np.asarray(used_planes, dtype=np.int64), e0,
                       float(graph.error(result)), iterations,
                       _time.perf_counter() - t_wall, len(blocks), prior_sig)


_DIMS = {"x": 6, "e": 6, "p": 3, "d": 1}


def cluster_covariances(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, n_prior: int,
                        clusters: list[int], keys: list[int]) -> dict[int, FloatArray]:
    """Cluster-robust sandwich covariance ``H^-1 (sum_c g_c g_c^T + H_prior) H^-1`` of the
    variables ``keys`` (gtsam keys of X/E/P/D variables) at ``values``.

    ``graph``'s first ``n_prior`` factors are priors (pose, plane, extrinsic, motion: their
    information enters the middle term as modelled, so a parameter only a prior constrains keeps
    its prior sigma); every later factor ``i`` is a data block belonging to the cluster
    ``clusters[i - n_prior]`` (here: its knot interval). ``H`` is the (robustly weighted) Gauss-Newton
    information of the whole graph and ``g_c`` the gradient of cluster ``c``'s whitened residuals:
    errors shared within a cluster (the trajectory model between two knots, errors-in-variables of
    one scan) add up instead of averaging out, and the spread of the actual residuals replaces the
    stated sigmas; the outer products get the small-sample factor ``G / (G - 1)`` of G clusters.
    Returns key -> 6x6 (tangent order of the variable)."""
    return _cluster_covariances(graph, values, n_prior, [np.asarray(clusters)], keys)[0]


def _cluster_covariances(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, n_prior: int,
                         labelings: list[NDArray[np.int64]], keys: list[int]) -> list[dict[int, FloatArray]]:
    """:func:`cluster_covariances` for several clusterings of the data blocks at once."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    lin = graph.linearize(values)
    col: dict[int, int] = {}
    n_col = 0
    for k in values.keys():
        col[int(k)] = n_col
        n_col += _DIMS[chr(gtsam.Symbol(k).chr())]
    rows, cols, vals, rhs, row_cluster = [], [], [], [], []
    n_row = 0
    for i in range(lin.size()):
        f = lin.at(i)
        if f is None:
            continue
        A, b = f.jacobian()
        A = np.asarray(A, dtype=float)
        m = A.shape[0]
        c0 = 0
        for k in f.keys():
            dk = _DIMS[chr(gtsam.Symbol(k).chr())]
            blk = A[:, c0:c0 + dk]
            r, c = np.nonzero(blk)
            rows.append(r + n_row)
            cols.append(c + col[int(k)])
            vals.append(blk[r, c])
            c0 += dk
        rhs.append(np.asarray(b, dtype=float).ravel())
        row_cluster.append(np.full(m, -1 if i < n_prior else i - n_prior, dtype=np.int64))
        n_row += m
    J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n_row, n_col))
    b_all = np.concatenate(rhs)
    block = np.concatenate(row_cluster)
    H = (J.T @ J).tocsc()
    sel = np.concatenate([np.arange(col[int(k)], col[int(k)] + _DIMS[chr(gtsam.Symbol(k).chr())]) for k in keys])
    rhs_e = np.zeros((n_col, sel.size))
    rhs_e[sel, np.arange(sel.size)] = 1.0
    X = splu(H).solve(rhs_e)  # columns of H^-1 for the wanted variables
    U = np.asarray(J @ X)
    data = block >= 0
    Ub = U[data] * b_all[data, None]
    Up = U[~data]
    result = []
    for labels in labelings:
        _, inv = np.unique(np.asarray(labels)[block[data]], return_inverse=True)
        S = np.zeros((int(inv.max()) + 1 if inv.size else 0, sel.size))
        np.add.at(S, inv, Ub)
        g = S.shape[0]
        cov = S.T @ S * (g / max(g - 1, 1)) + Up.T @ Up  # small-sample factor G / (G - 1)
        out, o = {}, 0
        for k in keys:
            dk = _DIMS[chr(gtsam.Symbol(k).chr())]
            c = cov[o:o + dk, o:o + dk]
            out[int(k)] = 0.5 * (c + c.T)
            o += dk
        result.append(out)
    return result


def robust_scale(e: FloatArray) -> float:
    """MAD-based standard deviation ``1.4826 median |e - median e|`` of residuals (0 if empty)."""
    e = np.asarray(e, dtype=float)
    if e.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(e - np.median(e))))


def robust_variance_factor(u: FloatArray, kernel: RobustKernel) -> float:
    """Factor f on the sigmas of an IRLS (M-estimator) fit so that its covariance matches the
    robust sandwich covariance, for residuals ``u`` whitened by the robust scale (N,):
    ``f^2 = mean(psi^2) mean(w) / mean(psi')^2`` (1 for Gaussian residuals without a kernel;
    > 1 when many residuals sit in the down-weighted range). The IRLS information is
    ``sum w J^T J`` against the sandwich ``A^-1 B A^-1`` with ``A = sum psi' J^T J``,
    ``B = sum psi^2 J^T J``; taking psi', psi^2 and w independent of J gives f. ``mean(psi')``
    is floored at 0.1 (a redescending kernel's psi' turns negative far out)."""
    u = np.asarray(u, dtype=float)
    if u.size == 0 or kernel.name == "none":
        return 1.0
    k = kernel.threshold
    w = robust_weights(u, kernel)
    if kernel.name == "huber":
        dpsi = (np.abs(u) <= k).astype(float)
    else:
        q = (u / k) ** 2
        dpsi = (1.0 - q) / (1.0 + q) ** 2
    f2 = float(np.mean((w * u) ** 2) * np.mean(w) / max(float(np.mean(dpsi)), 0.1) ** 2)
    return float(np.sqrt(max(f2, 1.0)))


def _data_graph(prior_graph: gtsam.NonlinearFactorGraph, blocks: list[_Block], kt: FloatArray,
                reference: int, calibrated: list[int], T_init: list[FloatArray], scale: FloatArray,
                cfg: EstimatorConfig, kernels: list[RobustKernel] | None = None
                ) -> gtsam.NonlinearFactorGraph:
    """The priors plus one point-on-plane factor per block, point sigmas times ``scale[scanner]``
    and the scanner's kernel (default ``cfg.kernel`` for all)."""
    graph = gtsam.NonlinearFactorGraph(prior_graph)
    kern = kernels or [cfg.kernel] * len(scale)
    for b in blocks:
        xa, xb, pj = X(b.knot), X(b.knot + 1), P(b.plane)
        sig = b.sigmas * scale[b.scanner]
        if b.scanner == reference or b.scanner not in calibrated:
            Tb = T_init[b.scanner]
            p_b = b.points @ Tb[:3, :3].T + Tb[:3, 3]
            graph.add(point_plane_factor(xa, xb, pj, p_b, b.alphas, sig, kern[b.scanner]))
        elif cfg.time_offsets:
            graph.add(timed_scanner_plane_factor(xa, xb, pj, E(b.scanner), D(b.scanner), b.points,
                                                 b.alphas, kt[b.knot + 1] - kt[b.knot], sig,
                                                 kern[b.scanner]))
        else:
            graph.add(scanner_point_plane_factor(xa, xb, pj, E(b.scanner), b.points, b.alphas,
                                                 sig, kern[b.scanner]))
    return graph


def _solve_error(err: RuntimeError) -> ValueError:
    text = str(err).strip()
    first = text.splitlines()[0] if text else "gtsam error"
    m = re.search(r"Symbol: (\w+)", text)
    return ValueError(f"calibration graph is singular or failed to solve ({first}"
                      f"{' ' + m.group(1) if m else ''})")


def _solve(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
           cfg: EstimatorConfig) -> tuple[gtsam.Values, int]:
    """The SLAM back end's batch solver (:func:`slam.backend.solver.damped_gauss_newton`: lightly damped
    Gauss-Newton with step halving, Levenberg-Marquardt on a singular system); its failures
    become a ValueError."""
    try:
        return damped_gauss_newton(graph, values, cfg.max_iterations, cfg.relative_tolerance)
    except RuntimeError as err2:
        raise _solve_error(err2) from None


def _sigmas(blocks: list[_Block], n_sc: int) -> list[FloatArray]:
    """The stated point sigmas [m] per scanner, in :func:`_residuals`' order."""
    out: list[list[FloatArray]] = [[] for _ in range(n_sc)]
    for b in blocks:
        out[b.scanner].append(b.sigmas)
    return [np.concatenate(r) if r else np.zeros(0) for r in out]


def _residuals(blocks: list[_Block], values: gtsam.Values, kt: FloatArray, calibrated: list[int],
               T_bs: list[FloatArray], timed: bool, n_sc: int) -> list[FloatArray]:
    """Unwhitened signed point-to-plane distances [m] per scanner at ``values``."""
    out: list[list[FloatArray]] = [[] for _ in range(n_sc)]
    for b in blocks:
        cal = b.scanner in calibrated
        T = np.asarray(values.atPose3(E(b.scanner)).matrix()) if cal else T_bs[b.scanner]
        al = b.alphas
        if cal and timed:
            al = al + float(values.atVector(D(b.scanner))[0]) / (kt[b.knot + 1] - kt[b.knot])
        p_b = b.points @ T[:3, :3].T + T[:3, 3]
        t = point_plane_terms(values.atPose3(X(b.knot)), values.atPose3(X(b.knot + 1)),
                              values.atOrientedPlane3(P(b.plane)), p_b, al, jacobians=False)
        out[b.scanner].append(t.residuals)
    return [np.concatenate(r) if r else np.zeros(0) for r in out]
